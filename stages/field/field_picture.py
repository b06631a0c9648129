"""Picture of the field artifact over its drawing (for ``polyvec-inspect render``)."""

from __future__ import annotations

import numpy as np


def render_field(grey: np.ndarray, roots: np.ndarray, mask: np.ndarray, step: int = 3, scale: int = 4,
                 singular: np.ndarray | None = None) -> np.ndarray:
    """Draw the frame field as small crosses over the drawing.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) in [0, 1], 1 = white.
    roots : numpy.ndarray
        complex (H, W, 2), the artifact's ``roots``.
    mask : numpy.ndarray
        bool (H, W); band pixels are tinted light yellow.
    step : int
        Draw a cross at every ``step``-th band pixel in both directions.
    scale : int
        Integer magnification of the output (nearest-neighbour upsampling).
    singular : numpy.ndarray, optional
        bool (H, W); singular pixels are marked with green squares.

    Returns
    -------
    numpy.ndarray
        uint8 (H·scale, W·scale, 3) RGB.  Root 0 (larger modulus) in red, root 1 in blue; arm length
        is ``0.45·step`` px times the root's modulus relative to root 0, so a short blue arm means a
        weak second direction.
    """
    from PIL import Image, ImageDraw

    step, scale = max(1, int(step)), max(1, int(scale))
    g = np.clip(np.asarray(grey, dtype=np.float64), 0, 1)
    rgb = np.repeat((g * 255)[..., None], 3, axis=2)
    # Fade the drawing so the crosses stand out; tint the band.
    rgb = 90 + 0.65 * rgb
    rgb[mask] = rgb[mask] * np.array([1.0, 1.0, 0.75])
    rgb = np.repeat(np.repeat(np.clip(rgb, 0, 255).astype(np.uint8), scale, 0), scale, 1)
    img = Image.fromarray(rgb, "RGB")
    draw = ImageDraw.Draw(img)
    if singular is not None:
        for i, j in zip(*np.nonzero(singular)):
            draw.rectangle([j * scale, i * scale, (j + 1) * scale - 1, (i + 1) * scale - 1], outline=(0, 170, 0))
    sel = np.zeros_like(mask, dtype=bool)
    sel[::step, ::step] = True
    sel &= mask
    arm = 0.45 * step * scale
    for i, j in zip(*np.nonzero(sel)):
        r0, r1 = roots[i, j, 0], roots[i, j, 1]
        m0 = abs(r0)
        if m0 == 0:
            continue
        cx, cy = (j + 0.5) * scale, (i + 0.5) * scale
        for r, col in ((r1, (40, 90, 255)), (r0, (230, 20, 20))):
            m = abs(r)
            if m == 0:
                continue
            d = r / m * arm * min(1.0, m / m0)
            draw.line([cx - d.real, cy - d.imag, cx + d.real, cy + d.imag], fill=col, width=max(1, scale // 3))
    return np.asarray(img)
