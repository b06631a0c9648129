"""Closed strokes closed: a loop cut at a synthetic end whose two tails overlap or cross (``export.loops``).

Described in :mod:`stages.export.stage`; measurements in stages/DECISIONS.md.
"""

from __future__ import annotations

import numpy as np

from stages.export.gaps import FREE_PX
from stages.geometry import arc_length


def close_loops(curves: list[dict], max_tail_px: float, max_tail_widths: float) -> list[dict]:
    """Close the loops whose seam came out as two overlapping or crossing tails.

    A closed stroke with no keypoint on it (an eye, an "o") is cut by the topology at a synthetic
    vertex, and the flow moves the two ends apart: the curve's start and finish overshoot each other,
    a small tick or an overlap on a smooth stretch with two free ends where the drawing has none.
    When both ends of a curve are synthetic (no keypoint: the drawing does not say "end" there), and a
    point within its first ``t = max(max_tail_px, max_tail_widths · w)`` of arc comes within
    max(FREE_PX, w) of a point within its last ``t`` (the scorer's meeting radius), the curve is cut
    at that closest pair and closed: the tails beyond are dropped and the last point joins the first.
    A curve shorter than four tails is left (a hook, not a loop).

    Parameters
    ----------
    curves : list of dict
        ``points`` (n, 2), ``end_types``, ``width`` (may be None) and optional ``corners`` (vertex
        indices) per curve.
    max_tail_px, max_tail_widths : float
        Longest tail searched at each end: ``max(max_tail_px, max_tail_widths · w)``.

    Returns
    -------
    list of dict
        The curves, the closed ones with their new ``points`` (first point repeated last) and
        ``corners`` re-indexed; the others unchanged.
    """
    return [_closed(c, max_tail_px, max_tail_widths) or c for c in curves]


def _closed(c: dict, max_tail_px: float, max_tail_widths: float) -> dict | None:
    """The curve ``c`` closed at its tails' closest pair, or None when it is no loop with a seam."""
    types = list(c.get("end_types") or (0, 0))
    if types[0] != 0 or types[-1] != 0:
        return None
    p = np.asarray(c["points"], np.float64).reshape(-1, 2)
    if len(p) < 4 or np.hypot(*(p[0] - p[-1])) <= 1e-9:
        return None                                        # already closed
    w = float(c["width"]) if c.get("width") is not None else 0.0
    tail, meet = max(max_tail_px, max_tail_widths * w), max(FREE_PX, w)
    arc = arc_length(p)
    if arc[-1] < 4.0 * tail:
        return None
    head = np.flatnonzero(arc <= tail)
    back = np.flatnonzero(arc >= arc[-1] - tail)
    d = np.hypot(*(p[head][:, None, :] - p[back][None, :, :]).transpose(2, 0, 1))
    a, b = np.unravel_index(int(np.argmin(d)), d.shape)
    if d[a, b] > meet:
        return None
    i, j = int(head[a]), int(back[b])
    points = np.concatenate([p[i:j + 1], p[i:i + 1]])
    corners = [int(k) - i for k in c.get("corners", []) if i < int(k) < j]
    return dict(c, points=points, corners=corners)
