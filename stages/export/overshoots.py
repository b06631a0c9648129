"""Unlabelled overshoots: curve ends at junctions extended over the ink that goes on past them.

An export clean-up beyond the paper (:mod:`stages.export.stage` describes it, stages/DECISIONS.md
has the measurements), run after the joins and spurs; see :func:`extend_overshoots`.  Curves are
dicts ``{"id", "points", "end_types", "end_keypoints", "parts", "width", ...}``
(stages/INTERFACES.md, export); points are (x, y) pixel coordinates, corner origin.
"""

from __future__ import annotations

import numpy as np

from stages.export.curve_ends import JOINABLE_TYPES, end_direction
from stages.export.end_index import points_near
from stages.geometry import arc_length, polyline_length

_MIDPOINT_CELL_PX = 4.0     # cell of the segment-midpoint grid of the overshoot extension (a few segments per cell)


def _distance_to_polyline(p: np.ndarray, pts: np.ndarray) -> float:
    """Euclidean distance from point p to a polyline (n ≥ 1 points)."""
    if len(pts) == 1:
        return float(np.hypot(*(pts[0] - p)))
    return _distance_to_segments(p, pts[:-1], pts[1:])


def _distance_to_segments(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Euclidean distance from point p to the nearest of the segments a[k]–b[k] (inf when none)."""
    if len(a) == 0:
        return np.inf
    ab = b - a
    den = np.maximum((ab * ab).sum(1), 1e-24)
    u = np.clip(((p - a) * ab).sum(1) / den, 0.0, 1.0)
    return float(np.hypot(*(a + u[:, None] * ab - p).T).min())


def extend_overshoots(curves: list[dict], mask: np.ndarray, tangent_px: float, min_px: float,
                      min_widths: float, max_px: float, max_widths: float, clearance: float,
                      step_px: float = 0.25) -> list[dict]:
    """Extend curve ends at junctions over an ink overshoot that no keypoint marks.

    A stroke that crosses another one and stops a few pixels beyond leaves a short tip of ink past
    the junction.  Without an endpoint keypoint at the tip the topology ends the curve at the
    junction and the tip is lost (it is the largest Hausdorff error of many realvec_dev drawings).
    For every curve end at a junction keypoint or a synthetic end, we walk from the end straight on
    (its direction over ``tangent_px``) through the band ``mask`` until the ink stops at distance
    ``s``; the stroke's centre line ends half a width before its ink does, so the overshoot is
    ``e = s − width/2``.  The curve is extended by ``e`` when
    ``max(min_px, min_widths·width) ≤ e ≤ max(max_px, max_widths·width)`` (a plain T has e ≈ 0: the
    ink ahead is the crossed stroke's half width; ink that goes on is another stroke's business) and
    the new tip lies at least ``clearance · e`` from every other curve (a Y's gap between branches,
    or a neighbouring stroke, fails this).

    The extended end is no longer at its keypoint: its type becomes 0 and its keypoint −1, and the
    junction is listed in the curve's ``through_keypoints``; ``extended`` gives the length (px) added
    at each end.

    Parameters
    ----------
    curves : list of dict
        As :func:`~stages.export.joins.join_continuations`.
    mask : numpy.ndarray
        bool (H, W) band (prep ``mask``); pixel [i, j] covers x ∈ [j, j+1), y ∈ [i, i+1).
    tangent_px : float
        Arc length over which end directions are measured.
    min_px, min_widths, max_px, max_widths : float
        Bounds on the extension (px, and in units of the curve's width).
    clearance : float
        Minimum distance of the new tip from other curves, as a fraction of the extension.
    step_px : float
        Sampling step of the walk.

    Returns
    -------
    list of dict
    """
    curves = [dict(c, points=np.asarray(c["points"], np.float64)) for c in curves]
    h, w_img = mask.shape
    # Every curve's segments, stacked once, for the clearance test; their midpoints near each tip are
    # found for all tips at once (a segment within r of it has its midpoint within r + half the
    # longest segment), where testing every segment of the drawing for every end was quadratic. (The
    # export's own grid, not a scipy k-d tree: a λ re-run then loads no scipy.spatial.)
    seg_a = [c["points"][:-1] if len(c["points"]) > 1 else c["points"] for c in curves]
    seg_b = [c["points"][1:] if len(c["points"]) > 1 else c["points"] for c in curves]
    seg_owner = np.repeat(np.arange(len(curves)), [len(a) for a in seg_a])
    seg_a = np.concatenate(seg_a) if curves else np.zeros((0, 2))
    seg_b = np.concatenate(seg_b) if curves else np.zeros((0, 2))
    half = 0.5 * float(np.hypot(*(seg_b - seg_a).T).max()) if len(seg_a) else 0.0
    tips = []                                              # (curve, end, tip, length) of each candidate
    for i, c in enumerate(curves):
        w = float(c.get("width") or 0.0)
        lo, hi = max(min_px, min_widths * w), max(max_px, max_widths * w)
        for e in (0, 1):
            if c["end_types"][e] not in JOINABLE_TYPES or polyline_length(c["points"]) <= 1e-9:
                continue
            p = c["points"][0 if e == 0 else -1]
            d = end_direction(c["points"], e == 0, tangent_px)
            s = np.arange(0.0, hi + 0.5 * w + 1.0, step_px)
            x, y = p[0] + s * d[0], p[1] + s * d[1]
            j, ii = np.floor(x).astype(int), np.floor(y).astype(int)
            inside = (ii >= 0) & (ii < h) & (j >= 0) & (j < w_img)
            ink = np.zeros(len(s), bool)
            ink[inside] = mask[ii[inside], j[inside]]
            if ink.all():
                continue                                   # the ink goes on: not an overshoot
            ln = float(s[np.argmin(ink)]) - 0.5 * w
            if lo <= ln <= hi:
                tips.append((i, e, p + ln * d, ln))
    adds = [[None, None] for _ in curves]
    reach = np.array([clearance * ln + half for _, _, _, ln in tips])
    at, seg = points_near(0.5 * (seg_a + seg_b), np.array([t for _, _, t, _ in tips]).reshape(-1, 2), reach,
                          _MIDPOINT_CELL_PX)
    keep = seg_owner[seg] != np.array([i for i, _, _, _ in tips], np.int64)[at] if len(at) else np.zeros(0, bool)
    at, seg = at[keep], seg[keep]
    bounds = np.searchsorted(at, np.arange(len(tips) + 1))
    for k, (i, e, tip, ln) in enumerate(tips):
        # Other curves, and this curve's own far part (a closed loop's other end, a hairpin).
        pts = curves[i]["points"] if e == 0 else curves[i]["points"][::-1]
        own = pts[arc_length(pts) > 2.0 * ln]
        others = seg[bounds[k]:bounds[k + 1]]
        near = min(_distance_to_segments(tip, seg_a[others], seg_b[others]),
                   _distance_to_polyline(tip, own) if len(own) else np.inf)
        if near >= clearance * ln:
            adds[i][e] = (tip, ln)
    for c, ext in zip(curves, adds):
        if ext == [None, None]:
            continue
        pts, types, kps = c["points"], list(c["end_types"]), list(c["end_keypoints"])
        through = list(c.get("through_keypoints", []))
        lengths = [0.0, 0.0]
        for e in (0, 1):
            if ext[e] is None:
                continue
            tip, ln = ext[e]
            pts = np.vstack([tip[None], pts]) if e == 0 else np.vstack([pts, tip[None]])
            if kps[e] >= 0:
                through.append(int(kps[e]))
            types[e], kps[e], lengths[e] = 0, -1, round(float(ln), 3)
        c.update(points=pts, end_types=types, end_keypoints=kps, through_keypoints=through, extended=lengths)
    return curves
