"""Synthetic line drawings with exact geometry, for tests, benchmarks and the bundled example.

Strokes are rendered from their centre lines by an analytic anti-aliased distance profile, so the
ground truth (centre line, width, keypoints) is known exactly. Points are (x, y) in pixel units with
the origin at the top-left corner of the image (pixel ``[i, j]`` has its centre at ``(j + .5, i + .5)``).
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Drawing:
    """A rendered synthetic drawing and its vector ground truth.

    Attributes
    ----------
    grey : numpy.ndarray
        float32 (H, W) in [0, 1], 1 = white paper.
    strokes : list of numpy.ndarray
        Centre lines, each (n, 2) in (x, y).
    width : float
        Stroke width in pixels.
    keypoints : list of tuple
        ``(x, y, type)`` with type 1 endpoint, 3 junction, 5 sharp corner.
    """

    grey: np.ndarray
    strokes: list[np.ndarray]
    width: float
    keypoints: list[tuple[float, float, int]] = field(default_factory=list)

    def png_bytes(self) -> bytes:
        """The drawing as an 8-bit greyscale PNG."""
        from PIL import Image

        buf = io.BytesIO()
        Image.fromarray(np.round(self.grey * 255).astype(np.uint8), mode="L").save(buf, "PNG")
        return buf.getvalue()


def distance_to_polyline(shape: tuple[int, int], pts: np.ndarray) -> np.ndarray:
    """Euclidean distance from every pixel centre to a polyline.

    Parameters
    ----------
    shape : (H, W)
    pts : numpy.ndarray
        (n, 2) vertices in (x, y).

    Returns
    -------
    numpy.ndarray
        float64 (H, W).
    """
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w]
    px = xs.ravel() + 0.5
    py = ys.ravel() + 0.5
    pts = np.asarray(pts, dtype=np.float64)
    best = np.full(px.shape, np.inf)
    if len(pts) == 1:
        return np.hypot(px - pts[0, 0], py - pts[0, 1]).reshape(shape)
    for a, b in zip(pts[:-1], pts[1:]):
        d = b - a
        ll = float(d @ d)
        t = np.zeros_like(px) if ll == 0 else np.clip(((px - a[0]) * d[0] + (py - a[1]) * d[1]) / ll, 0, 1)
        np.minimum(best, np.hypot(px - a[0] - t * d[0], py - a[1] - t * d[1]), out=best)
    return best.reshape(shape)


def render(shape: tuple[int, int], strokes: list[np.ndarray], width: float, darkness: float = 1.0) -> np.ndarray:
    """Render strokes of constant width with anti-aliased edges.

    Returns
    -------
    numpy.ndarray
        float32 (H, W) grey in [0, 1], 1 = white.
    """
    ink = np.zeros(shape)
    for s in strokes:
        d = distance_to_polyline(shape, s)
        np.maximum(ink, np.clip(width / 2 + 0.5 - d, 0.0, 1.0), out=ink)
    return (1.0 - darkness * ink).astype(np.float32)


def _dir(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([np.cos(a), np.sin(a)])


def line(size: int = 64, angle: float = 17.0, length: float = 44.0, width: float = 3.0) -> Drawing:
    """One straight stroke through the image centre at ``angle`` degrees (y down)."""
    c = np.array([size / 2, size / 2])
    d = _dir(angle) * length / 2
    s = np.array([c - d, c + d])
    return Drawing(render((size, size), [s], width), [s], width,
                   [(*s[0], 1), (*s[1], 1)])


def cross(size: int = 64, angle1: float = 10.0, angle2: float = 70.0, length: float = 44.0,
          width: float = 3.0) -> Drawing:
    """Two straight strokes crossing at the centre (an X junction)."""
    c = np.array([size / 2, size / 2])
    strokes = [np.array([c - _dir(a) * length / 2, c + _dir(a) * length / 2]) for a in (angle1, angle2)]
    kps = [(*p, 1) for s in strokes for p in s] + [(*c, 3)]
    return Drawing(render((size, size), strokes, width), strokes, width, kps)


def tee(size: int = 64, angle: float = 17.0, length: float = 44.0, width: float = 3.0) -> Drawing:
    """A bar and a perpendicular stem ending on the bar's centre line (a T junction)."""
    c = np.array([size / 2, size / 2 - 8])
    bar = np.array([c - _dir(angle) * length / 2, c + _dir(angle) * length / 2])
    stem = np.array([c, c + _dir(angle + 90) * length * 0.6])
    return Drawing(render((size, size), [bar, stem], width), [bar, stem], width,
                   [(*bar[0], 1), (*bar[1], 1), (*stem[1], 1), (*c, 3)])


def wye(size: int = 64, angle: float = 17.0, length: float = 22.0, width: float = 3.0) -> Drawing:
    """Three strokes meeting at the centre at 120° (a Y junction)."""
    c = np.array([size / 2, size / 2])
    strokes = [np.array([c, c + _dir(angle + k * 120) * length]) for k in range(3)]
    kps = [(*s[1], 1) for s in strokes] + [(*c, 3)]
    return Drawing(render((size, size), strokes, width), strokes, width, kps)


def vee(size: int = 64, angle: float = 17.0, opening: float = 50.0, length: float = 26.0,
        width: float = 3.0) -> Drawing:
    """One stroke with a single sharp corner."""
    c = np.array([size / 2 - 8, size / 2])
    s = np.array([c + _dir(angle - opening / 2) * length, c, c + _dir(angle + opening / 2) * length])
    return Drawing(render((size, size), [s], width), [s], width,
                   [(*s[0], 1), (*s[1], 5), (*s[2], 1)])


def zigzag(size: int = 96, teeth: int = 3, width: float = 3.0) -> Drawing:
    """A polyline with ``2 * teeth - 1`` sharp corners."""
    n = 2 * teeth + 1
    xs = np.linspace(14, size - 14, n)
    ys = np.where(np.arange(n) % 2 == 0, size / 2 + 14, size / 2 - 14)
    s = np.stack([xs, ys], axis=1)
    kps = [(*s[0], 1), (*s[-1], 1)] + [(*p, 5) for p in s[1:-1]]
    return Drawing(render((size, size), [s], width), [s], width, kps)


def circle(size: int = 64, radius: float = 20.0, width: float = 3.0, n: int = 256) -> Drawing:
    """A closed loop without keypoints."""
    t = np.linspace(0, 2 * np.pi, n + 1)
    s = np.stack([size / 2 + radius * np.cos(t), size / 2 + radius * np.sin(t)], axis=1)
    return Drawing(render((size, size), [s], width), [s], width, [])


def example_drawing() -> Drawing:
    """The bundled example: a small house-and-sun scene with ends, corners, X, T and Y junctions.

    Made entirely by this module so the project ships no third-party drawing.
    """
    size = (220, 300)
    w = 3.0
    strokes = [
        np.array([[40, 190], [40, 110], [110, 55], [180, 110], [180, 190], [40, 190]], float),  # house
        np.array([[85, 190], [85, 145], [115, 145], [115, 190]], float),  # door (ends on the base: T)
        np.array([[130, 125], [165, 125]], float),  # window bar
        np.array([[147.5, 110], [147.5, 140]], float),  # window bar crossing it (X)
    ]
    t = np.linspace(0, 2 * np.pi, 200)
    strokes.append(np.stack([245 + 22 * np.cos(t), 55 + 22 * np.sin(t)], axis=1))  # sun
    for a in (20, 80, 140):  # rays
        d = _dir(a)
        strokes.append(np.array([[245, 55] + d * 28, [245, 55] + d * 42]))
    tree = np.array([230, 195])
    strokes += [np.array([tree, tree + [0, -45]]),
                np.array([tree + [0, -45], tree + [-18, -70]]),
                np.array([tree + [0, -45], tree + [18, -70]])]  # Y
    grey = render(size, strokes, w)
    return Drawing(grey, strokes, w, [])
