"""Plane geometry shared by the stages: polylines, arc length, band tests, bilinear sampling.

Points are (x, y), x right, y down, in pixel units, origin at the top-left *corner* of the image:
the centre of pixel ``[i, j]`` is ``(j + 0.5, i + 0.5)`` (stages/INTERFACES.md).

Each helper exists here once. The compiled (numba) kernels of the graph and flow stages keep their
own bilinear samplers and resampler, because nopython code cannot call these numpy functions; each
names :func:`bilinear` or :func:`resample_uniform` as its reference.
"""

from __future__ import annotations

import numpy as np

__all__ = ["arc_length", "bilinear", "point_at_arc", "polyline_length", "resample_uniform", "segment_in_band", "subdivide",
           "turn_deg", "unit"]


def arc_length(points: np.ndarray) -> np.ndarray:
    """Cumulative arc length at every vertex of a polyline.

    Parameters
    ----------
    points : numpy.ndarray
        (n, 2) vertices (x, y), n ≥ 1.

    Returns
    -------
    numpy.ndarray
        float64 (n,), 0 at the first vertex.
    """
    return np.r_[0.0, np.cumsum(np.hypot(*np.diff(points, axis=0).T))]


def polyline_length(points) -> float:
    """Length of a polyline (0 for fewer than two vertices).

    Parameters
    ----------
    points : array_like
        (n, 2) vertices (x, y).

    Returns
    -------
    float
    """
    return float(np.hypot(*np.diff(np.asarray(points, np.float64), axis=0).T).sum()) if len(points) > 1 else 0.0


def point_at_arc(points: np.ndarray, arc: np.ndarray, s) -> np.ndarray:
    """The point(s) at arc length ``s`` along a polyline (linear between vertices, clamped at the ends).

    Parameters
    ----------
    points : numpy.ndarray
        (n, 2) vertices (x, y).
    arc : numpy.ndarray
        (n,) increasing arc length of the vertices (:func:`arc_length`).
    s : float or numpy.ndarray
        Arc length(s).

    Returns
    -------
    numpy.ndarray
        (2,) for a scalar ``s``, else ``s.shape + (2,)``.
    """
    return np.stack([np.interp(s, arc, points[:, 0]), np.interp(s, arc, points[:, 1])], axis=-1)


def resample_uniform(pts: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Resample a polyline at constant arc-length spacing (at most ``step``; first and last vertex kept).

    Repeated vertices (closer than 1e-9) are dropped first.

    Parameters
    ----------
    pts : numpy.ndarray
        (n, 2) vertices.
    step : float
        Largest spacing in pixels.

    Returns
    -------
    points : numpy.ndarray
        (m, 2) resampled vertices.
    arc : numpy.ndarray
        (m,) arc length of each resampled vertex.
    """
    pts = np.asarray(pts, dtype=np.float64)
    seg = np.hypot(*np.diff(pts, axis=0).T)
    keep = np.concatenate([[True], seg > 1e-9])
    pts = pts[keep]
    if len(pts) < 2:
        return pts[:1].copy(), np.zeros(1)
    cum = arc_length(pts)
    n = max(int(np.ceil(cum[-1] / step)), 1)
    s = np.linspace(0.0, cum[-1], n + 1)
    return point_at_arc(pts, cum, s), s


def subdivide(p: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ≤ ``step`` along a polyline, its vertices kept, and their arc lengths.

    Unlike :func:`resample_uniform` the result is the same set of points as the input polyline:
    every segment is cut into equal parts of at most ``step``.

    Parameters
    ----------
    p : numpy.ndarray
        (n, 2) vertices, n ≥ 2.
    step : float
        Largest spacing in pixels.

    Returns
    -------
    points : numpy.ndarray
        (m, 2) points.
    arc : numpy.ndarray
        (m,) arc length of each point.
    """
    seg = np.diff(p, axis=0)
    seglen = np.hypot(seg[:, 0], seg[:, 1])
    n = np.maximum(1, np.ceil(seglen / step)).astype(np.int64)
    idx = np.repeat(np.arange(len(seg)), n)
    k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
    t = k / n[idx]
    pts = np.vstack([p[idx] + t[:, None] * seg[idx], p[-1:]])
    cum = np.r_[0.0, np.cumsum(seglen)]
    arc = np.r_[cum[idx] + t * seglen[idx], cum[-1]]
    return pts, arc


def segment_in_band(mask: np.ndarray, p: np.ndarray, q: np.ndarray, step: float = 0.25) -> bool:
    """Whether every pixel the straight segment ``p → q`` (x, y) passes through is a band pixel.

    The segment is sampled every ≤ ``step`` px (ends included); a sample outside the image fails.

    Parameters
    ----------
    mask : numpy.ndarray
        bool (H, W) narrow band.
    p, q : numpy.ndarray
        (2,) end points (x, y).
    step : float
        Sampling step in pixels.

    Returns
    -------
    bool
    """
    n = max(2, int(np.ceil(np.hypot(*(q - p)) / step)) + 1)
    t = np.linspace(0.0, 1.0, n)[:, None]
    pts = p + t * (q - p)
    j = np.floor(pts[:, 0]).astype(np.int64)
    i = np.floor(pts[:, 1]).astype(np.int64)
    h, w = mask.shape
    if (i < 0).any() or (j < 0).any() or (i >= h).any() or (j >= w).any():
        return False
    return bool(mask[i, j].all())


def unit(v: np.ndarray) -> np.ndarray:
    """``v`` scaled to length 1; the zero vector when ``v`` is shorter than 1e-12.

    Parameters
    ----------
    v : numpy.ndarray
        (2,) vector.

    Returns
    -------
    numpy.ndarray
        (2,)
    """
    n = np.hypot(*v)
    return v / n if n > 1e-12 else np.zeros(2)


def turn_deg(d_a: np.ndarray, d_b: np.ndarray) -> float:
    """Turn (degrees) between two unit directions that point *away* from the joint they meet at.

    0° = straight on (the two directions are opposite), 180° = a hairpin.

    Parameters
    ----------
    d_a, d_b : numpy.ndarray
        (2,) unit vectors, each pointing out of the joint along its branch.

    Returns
    -------
    float
    """
    return float(np.degrees(np.arccos(np.clip(-(d_a @ d_b), -1.0, 1.0))))


def bilinear(c: np.ndarray, xy) -> np.ndarray:
    """Bilinear samples of a pixel-centre grid at points; pixels outside the image count as 0.

    The reference version of the compiled samplers (``stages.graph.trace.coeffs_at``,
    ``stages.flow.kernel._bilinear`` and ``_bilinear_field``).

    Parameters
    ----------
    c : numpy.ndarray
        (H, W) real or complex grid (e.g. the field's ``c0``, 0 off the band).
    xy : array_like
        (N, 2) or (2,) points (x, y), corner origin.

    Returns
    -------
    numpy.ndarray
        complex128 (N,), or a 0-d array for a single point.
    """
    xy = np.asarray(xy, dtype=np.float64)
    single = xy.ndim == 1
    pts = np.atleast_2d(xy)
    h, w = c.shape
    u = pts[:, 0] - 0.5
    v = pts[:, 1] - 0.5
    j0 = np.floor(u).astype(np.int64)
    i0 = np.floor(v).astype(np.int64)
    fu = u - j0
    fv = v - i0
    out = np.zeros(len(pts), dtype=np.complex128)
    for di, dj, wt in ((0, 0, (1 - fu) * (1 - fv)), (0, 1, fu * (1 - fv)),
                       (1, 0, (1 - fu) * fv), (1, 1, fu * fv)):
        ii, jj = i0 + di, j0 + dj
        ok = (ii >= 0) & (ii < h) & (jj >= 0) & (jj < w)
        out[ok] += wt[ok] * c[ii[ok], jj[ok]]
    return out[0] if single else out
