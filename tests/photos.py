"""Synthetic phone photos of a drawn sheet on a desk (tests of prep's photographed-sheet rule and the CLI).

The sheet is turned about its centre (or seen at an angle by a pinhole camera) and pasted on a darker
textured desk, lit unevenly from one side; the drawing's ink is moved the same way, so a test knows where
every stroke is in the photograph.
"""

from __future__ import annotations

import numpy as np
from PIL import Image


def photographed(sheet: Image.Image, angle: float, centre: tuple[int, int], size: tuple[int, int] = (1000, 1300),
                 seed: int = 0, tilt: float = 0.0) -> tuple[Image.Image, np.ndarray]:
    """A photograph (grey, ``size`` = (width, height)) of ``sheet`` turned by ``angle`` degrees with its
    centre at ``centre`` (x, y), on a desk of grey 50–130; and the ink (``sheet`` darker than 128) in the
    photograph's pixels, bool (height, width).

    ``tilt`` (degrees) leans the sheet's top away from a pinhole camera whose focal length is the photo's
    longer side (its centre the photo's; the sheet's centre at its own size): a phone held at an angle.
    """
    rng = np.random.default_rng(seed)
    w, h = size
    if tilt:
        coeffs = _camera_coefficients(sheet.size, angle, tilt, centre, size)
        a = Image.new("L", sheet.size, 255).transform(size, Image.PERSPECTIVE, coeffs, Image.BILINEAR, fillcolor=0)
        photo = sheet.transform(size, Image.PERSPECTIVE, coeffs, Image.BILINEAR, fillcolor=255)
        ink = Image.fromarray((np.asarray(sheet) < 128).astype(np.uint8) * 255)
        drawing = ink.transform(size, Image.PERSPECTIVE, coeffs, Image.NEAREST, fillcolor=0)
    else:
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


def sheet_to_photo(sheet_size: tuple[int, int], angle: float, tilt: float, centre: tuple[int, int],
                   size: tuple[int, int]) -> np.ndarray:
    """The homography (3×3) from a sheet's pixels to the photograph's under :func:`photographed`'s
    camera (``tilt`` ≠ 0)."""
    (sw, sh), (w, h), f = sheet_size, size, float(max(size))
    a, t = np.radians(angle), np.radians(tilt)
    turn = np.array([[np.cos(a), np.sin(a), 0], [-np.sin(a), np.cos(a), 0], [0, 0, 1]])   # as PIL's rotate
    lean = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    r = lean @ turn
    k = np.array([[f, 0, 0.5 * w], [0, f, 0.5 * h], [0, 0, 1]])
    plane = np.c_[r[:, 0], r[:, 1], [centre[0] - 0.5 * w, centre[1] - 0.5 * h, f]]
    return k @ plane @ np.array([[1, 0, -0.5 * sw], [0, 1, -0.5 * sh], [0, 0, 1]])


def _camera_coefficients(sheet_size, angle, tilt, centre, size) -> tuple[float, ...]:
    """PIL's ``PERSPECTIVE`` coefficients (photo → sheet) of :func:`sheet_to_photo`."""
    inv = np.linalg.inv(sheet_to_photo(sheet_size, angle, tilt, centre, size))
    return tuple((inv / inv[2, 2]).ravel()[:8])
