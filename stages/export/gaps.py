"""Gaps in a faint stroke closed: free curve ends that face each other across a small gap become one curve.

Described in :mod:`stages.export.stage` (``export.gaps``); measurements in stages/DECISIONS.md.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import label

from stages.export.corners import join_linked
from stages.export.end_index import near_pairs, points_near
from stages.export.curve_ends import end_direction
from stages.geometry import arc_length

#: An end is free when no other curve (nor its own other end) comes within max(FREE_PX, width) of
#: it: the acceptance scorer's meeting radius max(2, w).
FREE_PX = 2.0
#: ... except the other curve's own end: an end whose only neighbour is another curve's last
#: TIP_RADII × max(FREE_PX, width) of arc is free for that end alone (two ends of one broken stroke
#: closer than our width estimate, which can exceed the drawn width).
TIP_RADII = 2.0


def close_gaps(curves: list[dict], max_px: float, max_widths: float, max_turn_deg: float,
               tangent_px: float, kept_keypoints: frozenset = frozenset()) -> list[dict]:
    """Join pairs of free curve ends that face each other across a gap of at most a few stroke widths.

    A faint or grainy pencil stroke whose ink breaks (a light stretch, a white gap in the grain) is
    traced as several curves end to end, each with two free ends where the drawing has one stroke.
    Two free ends of different curves at most ``max(max_px, max_widths · w)`` apart (``w`` their mean
    stroke width), each pointing at the other within ``max_turn_deg`` (end directions over
    ``tangent_px`` of arc), are joined — nearest pairs first, each end once — into one curve bridging
    the gap with a straight segment. Ends at a junction or beside another curve are not free and stay.

    Parameters
    ----------
    curves : list of dict
        ``points`` (n, 2), ``end_types``, ``end_keypoints``, ``parts``, ``width`` (may be None) per curve.
    max_px, max_widths : float
        Largest gap: ``max(max_px, max_widths · w)``.
    max_turn_deg : float
        Largest angle between each end's outward direction and the gap.
    tangent_px : float
        Arc over which end directions are measured.
    kept_keypoints : frozenset of int
        Keypoint indices (the curves' ``end_keypoints``) whose ends are never joined (the user's edits).

    Returns
    -------
    list of dict
        The curves after joining (as :func:`~stages.export.corners.join_linked`: joined curves keep
        their first piece's ``id`` and list every piece's ``parts``).
    """
    if len(curves) < 2:
        return curves
    pts, width, ends, where, only = _curves_free_ends(curves, kept_keypoints)
    if len(ends) < 2:
        return curves
    where = np.array(where)
    outward = [end_direction(pts[n], e == 0, tangent_px) for n, e in ends]
    reach = max(max_px, max_widths * max(width))
    cos_max = np.cos(np.radians(max_turn_deg))
    pairs = []
    for a, b in _pairs_within(where, reach):
        i, j = ends[a][0], ends[b][0]
        if i == j or only[a] not in (None, ends[b]) or only[b] not in (None, ends[a]):
            continue
        gap = where[b] - where[a]
        d = float(np.hypot(*gap))
        if d < 1e-9 or d > max(max_px, max_widths * 0.5 * (width[i] + width[j])):
            continue
        u = gap / d
        if outward[a] @ u >= cos_max and outward[b] @ -u >= cos_max:
            pairs.append((d, a, b))
    link: dict = {}
    for _, a, b in sorted(pairs):
        if ends[a] not in link and ends[b] not in link:
            link[ends[a]], link[ends[b]] = ends[b], ends[a]
    return join_linked(curves, link, corner_joints=False) if link else curves


def _tip_owner(pts: list[np.ndarray], o: int, first: int, last: int, reach: float) -> tuple[int, int] | None:
    """``(o, end)`` when the vertices ``first`` … ``last`` of curve ``o`` close to an end lie within
    ``reach`` of arc from one of its ends (that curve's tip); None otherwise."""
    arc = arc_length(pts[o])
    if arc[last] <= reach:
        return o, 0
    if arc[-1] - arc[first] <= reach:
        return o, 1
    return None


def _curves_free_ends(curves: list[dict], kept_keypoints: frozenset = frozenset()
                      ) -> tuple[list, list, list, list, list]:
    """The curves' points and widths (0 for none), and :func:`_free_ends` of them, less the ends at a
    keypoint of ``kept_keypoints`` (one the user added or retyped: no step joins an artist's keypoint away)."""
    pts = [np.asarray(c["points"], np.float64).reshape(-1, 2) for c in curves]
    width = [float(c["width"]) if c.get("width") is not None else 0.0 for c in curves]
    ends, where, only = _free_ends(pts, width)
    if kept_keypoints:
        keep = [k for k, (n, e) in enumerate(ends) if _end_keypoint(curves[n], e) not in kept_keypoints]
        ends, where, only = [ends[k] for k in keep], [where[k] for k in keep], [only[k] for k in keep]
    return pts, width, ends, where, only


def _pairs_within(where: np.ndarray, reach: float) -> list[tuple[int, int]]:
    """Index pairs ``(a, b)``, ``a < b``, of the points ``where`` (k, 2) at most ``reach`` apart."""
    if len(where) < 2:
        return []
    i, j = near_pairs(np.asarray(where, np.float64).reshape(-1, 2), max(reach, 1e-9))   # reach may be 0
    return sorted(zip(np.minimum(i, j).tolist(), np.maximum(i, j).tolist()))


def _free_ends(pts: list[np.ndarray], width: list[float]) -> tuple[list, list, list]:
    """The free curve ends: ``(curve, end)``, its point, and the ``(curve, end)`` of the one other
    curve's tip that is its only neighbour within max(FREE_PX, width) (None when it has none)."""
    cand = [(n, e) for n, p in enumerate(pts) if len(p) >= 2 for e in (0, 1)]
    if not cand:
        return [], [], []
    at = np.array([pts[n][0 if e == 0 else -1] for n, e in cand])
    near = np.array([max(FREE_PX, width[n]) for n, _ in cand])
    loop = np.array([np.hypot(*(pts[n][-1 if e == 0 else 0] - q)) for (n, e), q in zip(cand, at)]) <= near
    # The vertices of every curve near each end, all ends at once (the export's own grid, not
    # scipy.spatial: a λ re-run — flow → select → export — then loads no scipy.spatial, whose import
    # cost about a tenth of that re-run).
    owner = np.repeat(np.arange(len(pts)), [len(p) for p in pts])
    start = np.r_[0, np.cumsum([len(p) for p in pts])]
    q, v = points_near(np.concatenate(pts), at, near, FREE_PX)
    end_curve = np.array([n for n, _ in cand])
    other = owner[v] != end_curve[q]
    q, v = q[other], v[other]
    # Per end: how many other curves come near, and (for one) the first and last of its vertices there.
    order = np.lexsort((v, q))
    q, v = q[order], v[order]
    first = np.r_[True, q[1:] != q[:-1]][:len(q)]
    last = np.r_[first[1:], True][:len(q)]
    curves_near = np.zeros(len(cand), np.int64)
    np.add.at(curves_near, q, np.r_[True, (q[1:] != q[:-1]) | (owner[v[1:]] != owner[v[:-1]])][:len(q)])
    lo, hi = np.zeros(len(cand), np.int64), np.zeros(len(cand), np.int64)
    lo[q[first]], hi[q[last]] = v[first], v[last]
    ends, where, only = [], [], []
    for k, (n, e) in enumerate(cand):
        if loop[k]:
            continue                                       # a closed loop's end meets its own start
        partner = None
        if curves_near[k]:
            o = int(owner[lo[k]])
            partner = _tip_owner(pts, o, lo[k] - start[o], hi[k] - start[o], TIP_RADII * near[k]) \
                if curves_near[k] == 1 else None
            if partner is None:
                continue                                   # at a junction, or beside another curve
        ends.append((n, e))
        where.append(at[k])
        only.append(partner)
    return ends, where, only


def join_lone_meetings(curves: list[dict], kept_keypoints: frozenset = frozenset()) -> list[dict]:
    """Join the two curves whose ends meet alone (a meeting of valence two) into one curve.

    Where exactly two curve ends meet — each the other's only neighbour within max(FREE_PX, w), no
    third curve near — the drawing has one stroke going on there (turning, or at a junction keypoint
    the selection found no third branch for), whatever the turn.  Drawn as two curves it lets the
    stroke's later crossings and touches of itself read as junctions of two curves (the acceptance
    scorer, like a person following the pen, counts none where one stroke meets itself); joined, they
    are one curve.  Ends of one curve (a closed loop) are left, and so are ends at a keypoint in
    ``kept_keypoints`` (one the user added or retyped: an artist's junction is kept where it was put).

    Parameters
    ----------
    curves : list of dict
        As :func:`close_gaps`.
    kept_keypoints : frozenset of int
        Keypoint indices (the curves' ``end_keypoints``) whose ends are never joined here.

    Returns
    -------
    list of dict
        The curves after joining (as :func:`~stages.export.corners.join_linked`).
    """
    if len(curves) < 2:
        return curves
    _, width, ends, where, only = _curves_free_ends(curves, kept_keypoints)
    partner, at = dict(zip(ends, only)), dict(zip(ends, where))
    link: dict = {}
    for a, b in partner.items():
        if b is None or b[0] == a[0] or partner.get(b) != a or a in link or b in link:
            continue
        # each is the other's only neighbour; their ends themselves meet (not just one end and the
        # other's last stretch of arc)
        if np.hypot(*(at[a] - at[b])) <= max(FREE_PX, width[a[0]], width[b[0]]):
            link[a], link[b] = b, a
    return join_linked(curves, link, corner_joints=False) if link else curves


def _end_keypoint(curve: dict, end: int) -> int:
    """The keypoint index at a curve's end 0 (start) or 1 (finish); -1 for a synthetic end."""
    kps = curve.get("end_keypoints") or (-1, -1)
    return int(kps[0 if end == 0 else -1])


def ends_at_keypoints(curve: dict, keypoints: frozenset) -> bool:
    """Whether either end of ``curve`` is at one of ``keypoints`` (indices, as its ``end_keypoints``)."""
    return bool(keypoints) and any(_end_keypoint(curve, e) in keypoints for e in (0, 1))


def join_bridged_ends(curves: list[dict], mask: np.ndarray, max_px: float, max_widths: float,
                      end_types: tuple = (5,), other_types: tuple = (0, 3, 5),
                      kept_keypoints: frozenset = frozenset()) -> list[dict]:
    """Join two free curve ends that the ink bridges: one stroke feature found twice.

    The detector sometimes finds one sharp corner twice a few pixels apart (two corner keypoints
    beyond its suppression distance), or a corner next to where the topology ended a chain (a
    synthetic end); the selection ends one curve at each, and the two ends, farther apart than the
    meeting radius, read as two free ends where the drawing turns.  Two free ends (as
    :func:`close_gaps` reads them) of different curves at most ``max(max_px, max_widths · w)`` apart
    (``w`` their mean stroke width), each the other's nearest such end, at least one of them at a
    keypoint of ``end_types`` and the other of ``other_types`` (not at an endpoint keypoint, by default:
    there the detector says a stroke ends), that the ink (the band ``mask``) connects within their bounding box
    (grown by half a width and a pixel: not round by a far stroke) are joined at any turn, the joint a corner vertex — nearest pairs first, each end once.  Unlike the
    gap closing, the ends need not face each other: the ink between them, not their direction, says
    they are one stroke.

    Parameters
    ----------
    curves : list of dict
        As :func:`close_gaps`.
    mask : numpy.ndarray
        bool (H, W) band (prep ``mask``), in the curves' (internal) pixel coordinates.
    max_px, max_widths : float
        Largest distance between the ends: ``max(max_px, max_widths · w)``.
    end_types : tuple of int
        Keypoint types (``end_types`` codes) of which at least one of the two ends must be ...
    other_types : tuple of int
        ... and the other one of these.
    kept_keypoints : frozenset of int
        As :func:`close_gaps`.

    Returns
    -------
    list of dict
        The curves after joining (as :func:`~stages.export.corners.join_linked`, joints marked as
        corners).
    """
    if len(curves) < 2:
        return curves
    _, width, ends, where, _ = _curves_free_ends(curves, kept_keypoints)
    if len(ends) < 2:
        return curves
    where = np.array(where)
    # Each end's nearest free end of another curve, among those within the largest reach (a farther
    # one could not be joined): a grid, not an all-pairs matrix, on a page of thousands of ends.
    reach = max(max_px, max_widths * max(width))
    nearest, dist = np.full(len(ends), -1), np.full(len(ends), np.inf)
    for a, b in _pairs_within(where, reach):
        if ends[a][0] == ends[b][0]:
            continue                                           # a curve's own two ends are not a pair
        d_ab = float(np.hypot(*(where[a] - where[b])))
        for x, y in ((a, b), (b, a)):
            if (d_ab, y) < (dist[x], nearest[x] if nearest[x] >= 0 else len(ends)):
                nearest[x], dist[x] = y, d_ab
    kind = np.array([int(curves[n]["end_types"][e]) for n, e in ends])
    needed, allowed = np.isin(kind, end_types), np.isin(kind, other_types)
    pairs = []
    for a, b in enumerate(nearest):
        b = int(b)
        if b <= a or nearest[b] != a or not (needed[a] and allowed[b] or needed[b] and allowed[a]):
            continue
        i, j = ends[a][0], ends[b][0]
        if dist[a] > max(max_px, max_widths * 0.5 * (width[i] + width[j])):
            continue
        if _ink_connects(mask, where[a], where[b], 0.5 * max(width[i], width[j]) + 1.0):
            pairs.append((float(dist[a]), a, b))
    link: dict = {}
    for _, a, b in sorted(pairs):
        link[ends[a]], link[ends[b]] = ends[b], ends[a]
    return join_linked(curves, link, corner_joints=True) if link else curves


def _ink_connects(mask: np.ndarray, p: np.ndarray, q: np.ndarray, pad: float) -> bool:
    """Whether the band pixels under ``p`` and ``q`` (x, y) are one connected piece of ink within the
    box spanned by the two points grown by ``pad`` px (8-connected; a point off the ink fails).

    The chord between two ends at a sharp turn cuts across the turn's inner corner, outside the ink;
    the ink round the turn connects them, a far stroke's ink does not (it lies outside the box).
    """
    h, w = mask.shape
    lo = np.floor(np.minimum(p, q) - pad).astype(int)
    hi = np.floor(np.maximum(p, q) + pad).astype(int) + 1
    x0, y0 = max(lo[0], 0), max(lo[1], 0)
    x1, y1 = min(hi[0], w), min(hi[1], h)
    if x1 <= x0 or y1 <= y0:
        return False
    lab, _ = label(mask[y0:y1, x0:x1], structure=np.ones((3, 3), bool))
    at = [lab[int(np.clip(np.floor(r[1]) - y0, 0, y1 - y0 - 1)), int(np.clip(np.floor(r[0]) - x0, 0, x1 - x0 - 1))]
          for r in (p, q)]
    return at[0] > 0 and at[0] == at[1]
