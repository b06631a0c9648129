"""Cubic Bézier fitting of polylines (Schneider, "An algorithm for automatically fitting digitized
curves", Graphics Gems 1990): chord-length parameters, least-squares control points for fixed end
tangents, Newton re-parametrisation, split at the point of largest error.
"""

from __future__ import annotations

import numpy as np

from stages.geometry import arc_length, unit


def _bezier(ctrl: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Points of one cubic Bézier (4, 2) at parameters u."""
    u = u[:, None]
    v = 1 - u
    return v ** 3 * ctrl[0] + 3 * v * v * u * ctrl[1] + 3 * v * u * u * ctrl[2] + u ** 3 * ctrl[3]


def _fit_segment(pts: np.ndarray, u: np.ndarray, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """Least-squares control points for fixed end points and end tangent directions."""
    p0, p3 = pts[0], pts[-1]
    v = 1 - u
    a0 = (3 * v * v * u)[:, None] * t0
    a1 = (3 * v * u * u)[:, None] * t1
    c00, c01, c11 = (a0 * a0).sum(), (a0 * a1).sum(), (a1 * a1).sum()
    rest = pts - _bezier(np.array([p0, p0, p3, p3]), u)
    x0, x1 = (a0 * rest).sum(), (a1 * rest).sum()
    det = c00 * c11 - c01 * c01
    seg = np.hypot(*(p3 - p0))
    if abs(det) > 1e-12:
        al0 = (x0 * c11 - x1 * c01) / det
        al1 = (c00 * x1 - c01 * x0) / det
    else:
        al0 = al1 = seg / 3
    if al0 < 1e-6 * seg or al1 < 1e-6 * seg:  # degenerate: Wu–Barsky heuristic
        al0 = al1 = seg / 3
    return np.array([p0, p0 + al0 * t0, p3 + al1 * t1, p3])


def _reparameterise(ctrl: np.ndarray, pts: np.ndarray, u: np.ndarray) -> np.ndarray:
    """One Newton step on |B(u) − p|² per point."""
    d1 = 3 * np.diff(ctrl, axis=0)
    d2 = 2 * np.diff(d1, axis=0)
    diff = _bezier(ctrl, u) - pts
    uu = u[:, None]
    b1 = (1 - uu) ** 2 * d1[0] + 2 * (1 - uu) * uu * d1[1] + uu ** 2 * d1[2]
    b2 = (1 - uu) * d2[0] + uu * d2[1]
    num = (diff * b1).sum(1)
    den = (b1 * b1).sum(1) + (diff * b2).sum(1)
    step = np.where(np.abs(den) > 1e-12, num / np.where(np.abs(den) > 1e-12, den, 1), 0)
    return np.clip(u - step, 0, 1)


def fit_cubic_beziers(points: np.ndarray, tolerance: float, max_depth: int = 32) -> list[np.ndarray]:
    """Fit a polyline with a chain of cubic Béziers within ``tolerance`` (max point distance).

    Parameters
    ----------
    points : numpy.ndarray
        (n, 2) polyline in (x, y).
    tolerance : float
        Largest allowed distance (px) between a polyline vertex and its fitted point.

    Returns
    -------
    list of numpy.ndarray
        (4, 2) control points per piece; consecutive pieces share end points.
    """
    pts = np.asarray(points, np.float64)
    keep = np.r_[True, np.hypot(*np.diff(pts, axis=0).T) > 1e-9]
    pts = pts[keep]
    if len(pts) < 2:
        return []
    if len(pts) == 2:
        a, b = pts
        return [np.array([a, a + (b - a) / 3, a + 2 * (b - a) / 3, b])]

    def tangent_at(i: int, direction: int) -> np.ndarray:
        # Direction from vertex i towards its neighbours (≥ 2 px of arc, to average out jitter).
        j, acc = i, 0.0
        while 0 <= j + direction < len(pts) and acc < 2.0:
            acc += np.hypot(*(pts[j + direction] - pts[j]))
            j += direction
        return unit(pts[j] - pts[i])

    out: list[np.ndarray] = []

    def fit(lo: int, hi: int, t0: np.ndarray, t1: np.ndarray, depth: int) -> None:
        seg = pts[lo:hi + 1]
        if len(seg) == 2:
            a, b = seg
            d = np.hypot(*(b - a)) / 3
            out.append(np.array([a, a + d * t0, b + d * t1, b]))
            return
        s = arc_length(seg)
        u = s / s[-1]
        ctrl = _fit_segment(seg, u, t0, t1)
        for _ in range(20):
            err = np.hypot(*(_bezier(ctrl, u) - seg).T)
            if err.max() <= tolerance:
                out.append(ctrl)
                return
            if err.max() > 4 * tolerance:
                break
            u = _reparameterise(ctrl, seg, u)
            ctrl = _fit_segment(seg, u, t0, t1)
        err = np.hypot(*(_bezier(ctrl, u) - seg).T)
        if err.max() <= tolerance or depth >= max_depth:
            out.append(ctrl)
            return
        k = int(np.argmax(err[1:-1])) + 1
        tc = unit(seg[k - 1] - seg[k + 1])
        if not tc.any():
            tc = unit(np.array([-(seg[k + 1] - seg[k])[1], (seg[k + 1] - seg[k])[0]]))
        fit(lo, lo + k, t0, tc, depth + 1)
        fit(lo + k, hi, -tc, t1, depth + 1)

    fit(0, len(pts) - 1, tangent_at(0, 1), tangent_at(len(pts) - 1, -1), 0)
    return out


def fit_with_corners(points: np.ndarray, corners: list[int], tolerance: float) -> list[np.ndarray]:
    """Cubic Bézier pieces of a polyline, fitted separately between its corner vertices.

    Parameters
    ----------
    points : numpy.ndarray
        (n, 2) polyline.
    corners : list of int
        Indices of interior vertices where the curve turns sharply (see
        :func:`stages.export.corners.join_at_corners`); the fit keeps them as corners.
    tolerance : float
        As :func:`fit_cubic_beziers`.

    Returns
    -------
    list of numpy.ndarray
        (4, 2) control points per piece, in order, the pieces of consecutive spans joined at the corners.
    """
    cuts = [0] + sorted(i for i in set(corners) if 0 < i < len(points) - 1) + [len(points) - 1]
    pieces: list[np.ndarray] = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        pieces += fit_cubic_beziers(points[a:b + 1], tolerance)
    return pieces
