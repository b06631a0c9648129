"""Pictures for the benchmark report: curves and keypoints drawn over the input drawing."""

from __future__ import annotations

import colorsys
from collections.abc import Sequence

import numpy as np
from skimage.draw import circle_perimeter_aa, line_aa

__all__ = ["curve_colours", "overlay", "hstack_panels"]

#: Marker colours (RGB) by meaning.
MARKER_COLOURS = {
    "free_end": (0, 160, 0),
    "junction": (220, 0, 0),
    "corner": (0, 90, 255),
    "gap": (255, 140, 0),
    "gt": (170, 0, 200),
    "duplicate": (255, 0, 255),
}

#: Marker radius (output pixels) by meaning, where it differs from ``marker_radius``.
MARKER_RADII = {"duplicate": 1}


def curve_colours(n: int) -> np.ndarray:
    """``n`` distinguishable RGB colours (golden-ratio hue steps), uint8 (n, 3)."""
    hues = (np.arange(n) * 0.61803398875) % 1.0
    return np.array([[int(255 * c) for c in colorsys.hsv_to_rgb(h, 0.9, 0.8)] for h in hues], dtype=np.uint8).reshape(-1, 3)


def _blend(img: np.ndarray, rr, cc, val, colour) -> None:
    h, w = img.shape[:2]
    ok = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
    rr, cc, val = rr[ok], cc[ok], val[ok][:, None]
    img[rr, cc] = (1 - val) * img[rr, cc] + val * np.asarray(colour, dtype=np.float64)


def overlay(
    grey: np.ndarray,
    curves: Sequence[np.ndarray] = (),
    markers: dict[str, np.ndarray] | None = None,
    scale: int = 1,
    fade: float = 0.35,
    marker_radius: int = 4,
) -> np.ndarray:
    """Draw polylines (one colour each) and marker circles over a faded copy of the drawing.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) input drawing, uint8 0–255 or float in [0, 1] (1 = white).
    curves : sequence of numpy.ndarray
        Polylines, (n, 2) in (x, y) pixel units (origin at the image corner).
    markers : dict of str to numpy.ndarray
        Name (a key of ``MARKER_COLOURS``) → (k, 2) positions in (x, y).
    scale : int
        Integer magnification of the picture (curves are drawn at the magnified resolution).
    fade : float
        How much the drawing is lightened under the curves (0 = unchanged).
    marker_radius : int
        Circle radius in output pixels.

    Returns
    -------
    numpy.ndarray
        uint8 (H · scale, W · scale, 3).
    """
    g = np.asarray(grey, dtype=np.float64)
    if g.max() > 1.0:
        g = g / 255.0
    g = 1.0 - (1.0 - g) * (1.0 - fade)
    g = np.kron(g, np.ones((scale, scale))) if scale > 1 else g
    img = np.repeat((g * 255.0)[:, :, None], 3, axis=2)
    for colour, c in zip(curve_colours(len(curves)), curves):
        p = np.asarray(c, dtype=np.float64).reshape(-1, 2) * scale
        # pixel (i, j) has its centre at (j + .5, i + .5) in curve coordinates
        q = np.floor(p).astype(np.int64)
        if len(q) == 1:
            q = np.vstack([q, q])
        for a, b in zip(q[:-1], q[1:]):
            rr, cc, val = line_aa(a[1], a[0], b[1], b[0])
            _blend(img, rr, cc, val, colour)
    for name, pts in (markers or {}).items():
        colour = MARKER_COLOURS.get(name, (0, 0, 0))
        for x, y in np.asarray(pts, dtype=np.float64).reshape(-1, 2)[:, :2] * scale:
            rr, cc, val = circle_perimeter_aa(int(np.floor(y)), int(np.floor(x)), MARKER_RADII.get(name, marker_radius))
            _blend(img, rr, cc, val, colour)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def hstack_panels(panels: Sequence[np.ndarray], gap: int = 4) -> np.ndarray:
    """Side-by-side RGB panels on white, top-aligned."""
    h = max(p.shape[0] for p in panels)
    w = sum(p.shape[1] for p in panels) + gap * (len(panels) - 1)
    out = np.full((h, w, 3), 255, dtype=np.uint8)
    x = 0
    for p in panels:
        out[: p.shape[0], x:x + p.shape[1]] = p
        x += p.shape[1] + gap
    return out
