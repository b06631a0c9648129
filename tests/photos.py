"""Synthetic phone photos of a drawn sheet on a desk (tests of prep's photographed-sheet rule and the CLI).

The sheet is turned about its centre and pasted on a darker textured desk, lit unevenly from one side;
the drawing's ink is turned the same way, so a test knows where every stroke is in the photograph.
"""

from __future__ import annotations

import numpy as np
from PIL import Image


def photographed(sheet: Image.Image, angle: float, centre: tuple[int, int], size: tuple[int, int] = (1000, 1300),
                 seed: int = 0) -> tuple[Image.Image, np.ndarray]:
    """A photograph (grey, ``size`` = (width, height)) of ``sheet`` turned by ``angle`` degrees with its
    centre at ``centre`` (x, y), on a desk of grey 50–130; and the ink (``sheet`` darker than 128) in the
    photograph's pixels, bool (height, width)."""
    rng = np.random.default_rng(seed)
    w, h = size
    turned = sheet.rotate(angle, resample=Image.BILINEAR, expand=True, fillcolor=255)
    alpha = Image.new("L", sheet.size, 255).rotate(angle, resample=Image.BILINEAR, expand=True, fillcolor=0)
    ink = Image.fromarray((np.asarray(sheet) < 128).astype(np.uint8) * 255).rotate(angle, expand=True)
    corner = (centre[0] - turned.size[0] // 2, centre[1] - turned.size[1] // 2)
    photo, a, drawing = (Image.new("L", size, 0) for _ in range(3))
    photo.paste(turned, corner)
    a.paste(alpha, corner)
    drawing.paste(ink, corner)
    yy, xx = np.mgrid[0:h, 0:w]
    desk = 90 + 40 * np.sin(xx / 37.0) * np.sin(yy / 53.0) + rng.normal(0, 8, (h, w))
    light = 0.8 + 0.15 * xx / w
    opacity = np.asarray(a) / 255.0
    px = opacity * np.asarray(photo) * light + (1 - opacity) * desk
    return Image.fromarray(np.clip(px, 0, 255).astype(np.uint8), "L"), np.asarray(drawing) > 127
