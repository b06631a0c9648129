"""Curve ends as the export's curve edits read them: which ends may be joined, where an end points.

The export's clean-ups share these: the joins at junctions (:mod:`stages.export.joins`), the spurs
(:mod:`stages.export.spurs`), the overshoots (:mod:`stages.export.overshoots`) and the gap closing
(:mod:`stages.export.gaps`) measure an end's outward direction over the same arc (:func:`end_direction`);
the joins and the overshoots act only on the end types of :data:`JOINABLE_TYPES`; the joins, the spurs
and the corner joins (:mod:`stages.export.corners`) give a curve made of pieces their length-weighted
width (:func:`mean_width`).  A module of their own, not :mod:`stages.export.joins` (which still gives
these names): the spurs and overshoots modules, whose functions the joins module gives too, import
them from here without importing the joins module back.
"""

from __future__ import annotations

import numpy as np

from stages.geometry import arc_length, point_at_arc, polyline_length, unit

JOINABLE_TYPES = (0, 3)      # synthetic ends and junctions; never endpoints (1) or sharp corners (5)


def end_direction(points: np.ndarray, at_start: bool, arc_px: float) -> np.ndarray:
    """Unit direction pointing *out of* a curve end: from the point ``arc_px`` along it to the end.

    Parameters
    ----------
    points : numpy.ndarray
        (n, 2) the curve's points.
    at_start : bool
        The end at ``points[0]`` (else the one at ``points[-1]``).
    arc_px : float
        Arc length over which the direction is measured (at most half the curve's length).

    Returns
    -------
    numpy.ndarray
        float64 (2,) unit vector; zeros for a curve of zero length.
    """
    pts = np.asarray(points, np.float64)
    if not at_start:
        pts = pts[::-1]
    s = arc_length(pts)
    if s[-1] <= 1e-12:
        return np.zeros(2)
    q = point_at_arc(pts, s, min(arc_px, 0.5 * s[-1]))
    return unit(pts[0] - q)


def mean_width(pieces: list[dict]):
    """Stroke width of curves joined into one: their widths weighted by length (unknown ones left out).

    Parameters
    ----------
    pieces : list of dict
        Curves with ``points`` (n, 2) and ``width`` (float or None).

    Returns
    -------
    float or None
        The widths' length-weighted mean; the one known width when only one is; None when none is.
    """
    known = [c for c in pieces if c.get("width") is not None]
    if len(known) < 2:
        return known[0]["width"] if known else None
    lengths = [polyline_length(c["points"]) for c in known]
    return float(sum(c["width"] * ln for c, ln in zip(known, lengths)) / max(sum(lengths), 1e-12))
