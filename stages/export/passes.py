"""Passes of the pen over one line merged into one centred curve (issue 55, item 2).

A sketcher draws a line two or three times, or doubles a stroke back on itself. Where the passes do not
touch, the graph traces each one, and the selection keeps them all: side-by-side curves, each with its
own two ends, and junctions where they cross or touch — where a person sees one line. Here a piece of
one curve that runs beside another curve (or beside itself, the way back of a retraced stroke) within
``max_gap_widths`` stroke widths, near-parallel (``max_angle_deg``), over at least ``min_run_widths``
widths of arc, is one line drawn twice: the two pieces become one curve along their centre (weighted by
how many passes each already stands for), carried on by whichever of the two goes on past the shared
stretch, and the other curve is dropped (:func:`merge_passes`). A retraced stroke is folded onto
itself: one curve that ends at the turn of the pen.

Two curves are merged only where, at each end of the shared stretch, at most one of them goes on for
more than ``end_slack_widths`` widths (two lines that come together and part again — a narrow V, two
strokes touching along a stretch — are different lines meeting), and the one that stops there ends on
the other (within 0.75 widths): a short stroke along a contour, a hatch beside it, or a stroke's own
flick that ends beside the line keeps its end. An end where the two close up counts as both ending
there: what is left of each past the stretch stays within ``max_gap_widths`` of the other curve and the
two end within that of each other (passes between the same two keypoints, converging on them more
steeply than near-parallel; a stretch cut in two by a kink of one pass) — that piece is their weighted
mean. Runs after the corner joins, on whole strokes (before,
the two passes' pieces ended on different corner keypoints and no longer chained); the gap closing
comes after.

Neighbours are found by a grid of the curves' samples (1 px apart) with cells of the largest merge
distance, so the work is linear in the ink for a bounded stroke width; merges repeat in rounds (each
curve in at most one merge per round) until none is left, each round after the first looking only
at the curves that changed in the last and those near them (a page's later rounds cost what its
few merges touch, not another pass over the page).
"""

from __future__ import annotations

import numpy as np

from stages.export.curve_ends import mean_width
from stages.export.end_index import near_pairs as _near_pairs
from stages.export.overshoots import _distance_to_polyline
from stages.geometry import arc_length, point_at_arc, resample_uniform

__all__ = ["merge_passes"]

_STEP_PX = 1.0            # sample spacing along the curves
_DEFAULT_WIDTH_PX = 2.0   # a curve without a graph width (none known in the drawing)
_ATTACH_WIDTHS = 0.75     # a curve end this close to another curve ends on it (a junction of the two)
_STOP_WIDTHS = 1.0        # a pass that stops beside one that goes on ends within this much arc of the run


def _curve_samples(c: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A curve resampled ``_STEP_PX`` apart: points, unit tangents, arcs."""
    p, s = resample_uniform(np.asarray(c["points"], np.float64), _STEP_PX)
    # Tangents over ±2 samples: a pixel's jitter of the flowed curve does not turn them.
    lo, hi = np.maximum(np.arange(len(p)) - 2, 0), np.minimum(np.arange(len(p)) + 2, len(p) - 1)
    t = p[hi] - p[lo]
    t /= np.maximum(np.hypot(*t.T), 1e-12)[:, None]
    return p, t, s


def _samples(per_curve: list[tuple], widths: np.ndarray):
    """Every curve's :func:`_curve_samples` in one: points, unit tangents, curve index, arc, offsets, widths."""
    owner = np.repeat(np.arange(len(per_curve)), [len(p) for p, _, _ in per_curve])
    offsets = np.r_[0, np.cumsum([len(p) for p, _, _ in per_curve])]
    return (np.concatenate([p for p, _, _ in per_curve]), np.concatenate([t for _, t, _ in per_curve]), owner,
            np.concatenate([s for _, _, s in per_curve]), offsets, widths[owner])


def _partners(P, T, owner, arc, W, max_gap_widths: float, max_angle_deg: float, cell: float | None = None):
    """Sample pairs of two passes: near, near-parallel, each sample's nearest on each other curve.

    A sample of the same curve counts only running the other way (a retrace) and more than the
    hairpin's length of arc away, so a curve's own neighbouring samples never pair. ``cell`` is the
    side of the neighbour grid (the largest merge distance; default that of these samples): the
    nearest of two samples at equal distances is the first the grid finds.

    Returns
    -------
    i, j : numpy.ndarray
        Sample indices: ``j`` is the nearest sample to ``i`` on curve ``owner[j]`` (one per curve and
        sample), sorted by (``owner[i]``, ``owner[j]``, ``i``).
    """
    none = np.zeros(0, np.int64)
    r = max_gap_widths * W
    cos_min = np.cos(np.radians(max_angle_deg))

    def two_passes(i, j, d):
        ok = d <= 0.5 * (r[i] + r[j])
        near = np.flatnonzero(ok)              # the directions only of these (a fraction of the grid's)
        i, j = i[near], j[near]
        cos = np.einsum("ij,ij->i", T[i], T[j])
        same = owner[i] == owner[j]
        ok[near] = (np.abs(cos) >= cos_min) & (~same | ((cos < 0) & (np.abs(arc[i] - arc[j])
                                                                      > 2.0 * np.maximum(r[i], r[j]))))
        return ok

    if cell is None:
        cell = float(r.max()) if len(r) else 0.0
    # The pairs filtered as they are found: a page's millions of pairs within the grid's cell (mostly
    # a curve's own neighbouring samples) are never held at once.
    i, j = _near_pairs(P, cell, two_passes)
    if not len(i):
        return none, none
    d = np.hypot(*(P[i] - P[j]).T)
    a, b, dd = np.r_[i, j], np.r_[j, i], np.r_[d, d]
    order = np.lexsort((dd, owner[b], a))
    a, b = a[order], b[order]
    first = np.r_[True, (a[1:] != a[:-1]) | (owner[b[1:]] != owner[b[:-1]])]
    a, b = a[first], b[first]
    order = np.lexsort((a, owner[b], owner[a]))
    return a[order], b[order]


def _near_samples(P: np.ndarray, touched: np.ndarray, cell: float) -> np.ndarray:
    """Indices (sorted) of the samples in the grid cells (side ``cell``) at or next to a ``touched`` sample's."""
    key = np.floor(P / cell).astype(np.int64)
    key -= key.min(axis=0) - 1
    span = int(key[:, 1].max()) + 2
    flat = key[:, 0] * span + key[:, 1]
    around = np.unique(flat[touched])
    around = np.unique((around[:, None] + (np.arange(-1, 2)[:, None] * span + np.arange(-1, 2)).ravel()).ravel())
    return np.flatnonzero(np.isin(flat, around))


def _runs(i, j, owner, arc, W, min_run_widths: float):
    """Stretches of one curve beside one other curve (or itself): (length, a, b, samples of a, partners).

    Holes of up to a stroke width (samples with no partner on b) are bridged.
    """
    runs = []
    if not len(i):
        return runs
    ca, cb = owner[i], owner[j]
    cuts = np.flatnonzero((ca[1:] != ca[:-1]) | (cb[1:] != cb[:-1])) + 1
    for grp in np.split(np.arange(len(i)), cuts):
        a, b = int(ca[grp[0]]), int(cb[grp[0]])
        if b < a:
            continue                          # each pair once, from its lower index (itself: a == b)
        s = arc[i[grp]]
        gaps = np.flatnonzero(np.diff(s) > max(W[i[grp[0]]], 1.0) + _STEP_PX) + 1
        for seg in np.split(grp, gaps):
            length = float(arc[i[seg[-1]]] - arc[i[seg[0]]])
            if length >= min_run_widths * W[i[seg[0]]]:
                runs.append((length, a, b, i[seg], j[seg]))
    runs.sort(key=lambda r: -r[0])
    return runs


def _cut(points: np.ndarray, s0: float, s1: float) -> np.ndarray:
    """The piece of a polyline between arc lengths s0 ≤ s1 (its vertices in between kept)."""
    s = arc_length(points)
    inner = points[(s > s0) & (s < s1)]
    return np.vstack([point_at_arc(points, s, s0), inner, point_at_arc(points, s, s1)])


def _carried_corners(points: np.ndarray, sources: list[dict], reach: float) -> list[int]:
    """``corners`` (vertex indices) of a rebuilt curve: the sources' corner vertices, at its nearest vertices.

    Corner joins ran before: a pass through a sharp corner keeps it, where the merged curve passes
    within ``reach`` of it (the two passes' corners at one place become one).
    """
    at = [np.asarray(c["points"], np.float64)[[int(k) for k in c.get("corners", [])]] for c in sources]
    at = np.concatenate(at) if at else np.zeros((0, 2))
    if not len(at):
        return []
    groups: list[list[np.ndarray]] = []        # the passes' corners within reach of each other: one corner
    for p in at:
        g = next((g for g in groups if np.hypot(*(np.mean(g, axis=0) - p)) <= reach), None)
        g.append(p) if g is not None else groups.append([p])
    at = np.array([np.mean(g, axis=0) for g in groups])
    d = np.hypot(*(points[None, :, :] - at[:, None, :]).transpose(2, 0, 1))
    idx, near = d.argmin(1), d.min(1) <= reach
    return sorted({int(k) for k in idx[near] if 0 < k < len(points) - 1})


def _flipped(c: dict) -> dict:
    """The curve run the other way (points and ends)."""
    n = len(c["points"])
    return dict(c, points=np.asarray(c["points"], np.float64)[::-1], end_types=list(c["end_types"])[::-1],
                end_keypoints=list(c["end_keypoints"])[::-1], corners=[n - 1 - int(k) for k in c.get("corners", [])])


def _ramp(arc_run: np.ndarray, lam_start: float, lam_end: float, lam_mid: float, taper: float):
    """Share of the second pass along a run: ``lam_mid``, eased to the given values at its two ends."""
    x0 = np.clip((arc_run - arc_run[0]) / taper, 0.0, 1.0)
    x1 = np.clip((arc_run[-1] - arc_run) / taper, 0.0, 1.0)
    lam = lam_start + (lam_mid - lam_start) * x0
    return np.where(x1 < x0, lam_end + (lam_mid - lam_end) * x1, lam)


def _beside(piece: np.ndarray, other: np.ndarray, gap: float) -> bool:
    """Whether every point of ``piece`` (resampled ``_STEP_PX`` apart) lies within ``gap`` of ``other``'s samples."""
    p, _ = resample_uniform(piece, _STEP_PX)
    for k in range(0, len(p), 256):            # chunks: a bounded (256 × len(other)) distance table
        d = np.hypot(*(p[k:k + 256, None, :] - other[None, :, :]).transpose(2, 0, 1)).min(1)
        if np.any(d > gap + _STEP_PX):
            return False
    return True


def _blend(pa: np.ndarray, pb: np.ndarray, mid: float) -> np.ndarray:
    """Two pieces' weighted mean (``mid`` the share of the second) at equal fractions of their arcs."""
    sa, sb = arc_length(pa), arc_length(pb)
    n = max(int(np.ceil(max(sa[-1], sb[-1]) / _STEP_PX)) + 1, 2)
    u = np.linspace(0.0, 1.0, n)
    return (1.0 - mid) * point_at_arc(pa, sa, u * sa[-1]) + mid * point_at_arc(pb, sb, u * sb[-1])


def _merge_pair(ca: dict, cb: dict, pa: np.ndarray, sa: np.ndarray, La: float, pb: np.ndarray, sb: np.ndarray,
                q: np.ndarray, na: int, nb: int, w: float, slack: float, attach: float, gap: float):
    """Two passes merged along a run, or None when they are two lines that meet.

    ``pa``/``sa`` are a's samples and arcs along the run (a is ``La`` long), ``pb``/``sb`` all of b's
    samples and arcs, ``q`` the arc on b beside each of a's samples; ``na``/``nb`` the passes each
    curve stands for already (the centre is their weighted mean); an end within ``attach`` of the
    other curve ends on it. At an end of the run where what is left of both curves stays within
    ``gap`` of the other curve and the two end within ``gap`` of each other (the passes close up into
    one end, e.g. at a keypoint both reach, converging there more steeply than near-parallel), the
    two are one line to that end: their weighted mean.
    """
    Lb = float(sb[-1])
    if q[-1] < q[0]:                           # b runs the other way: turn it round
        cb, q = _flipped(cb), Lb - q
        pb, sb = pb[::-1], Lb - sb[::-1]
    q = np.maximum.accumulate(q)               # a monotone map of a's run onto b
    run_a, run_b = (float(sa[0]), float(sa[-1])), (float(q[0]), float(q[-1]))
    if not 0.6 <= (run_b[1] - run_b[0]) / max(run_a[1] - run_a[0], 1e-9) <= 1.6:
        return None                            # not side by side all along (b folds or jumps)
    before, after = (run_a[0], run_b[0]), (La - run_a[1], Lb - run_b[1])
    pts_a, pts_b = np.asarray(ca["points"], np.float64), np.asarray(cb["points"], np.float64)
    rest = [(_cut(pts_a, 0.0, run_a[0]), _cut(pts_b, 0.0, run_b[0])),
            (_cut(pts_a, run_a[1], La), _cut(pts_b, run_b[1], Lb))]
    full_a = None
    together = []
    for side, (ra, rb) in enumerate(rest):
        far = 0 if side == 0 else -1
        # Only where one of them goes on past the slack: both within it, the ends meet as they did.
        ok = max(before if side == 0 else after) > slack and np.hypot(*(ra[far] - rb[far])) <= gap
        if ok:
            full_a = resample_uniform(pts_a, _STEP_PX)[0] if full_a is None else full_a
            ok = _beside(ra, pb, gap) and _beside(rb, full_a, gap)
        together.append(bool(ok))
    if any(min(left) > slack and not tog for left, tog in zip((before, after), together)):
        return None                            # both go on past the shared stretch: lines that meet
    if any(max(left) > slack and min(left) > _STOP_WIDTHS * w and not tog
           for left, tog in zip((before, after), together)):
        return None                            # one goes on, the other leaves it to end apart: a spur
    # Where one curve goes on past the shared stretch, the other must end on it (a braid of touching
    # passes, a pass that stops short on the line): one that ends beside it, apart, keeps its end — a
    # short stroke along a contour, a hatch beside it, a stroke's own flick (validation split).
    for side, left in ((0, before), (1, after)):
        if max(left) > slack and not together[side]:
            stops, goes_on = (pts_a, pts_b) if left[1] > left[0] else (pts_b, pts_a)
            if _distance_to_polyline(stops[0 if side == 0 else -1], goes_on) > attach:
                return None
    head_from_b, tail_from_b = before[1] > before[0], after[1] > after[0]
    head = _cut(pts_b, 0.0, run_b[0]) if head_from_b else _cut(pts_a, 0.0, run_a[0])
    tail = _cut(pts_b, run_b[1], Lb) if tail_from_b else _cut(pts_a, run_a[1], La)
    # The second pass's share eases from the pass the line comes from to the weighted centre and on
    # to the pass it goes on as, over two widths: no step where a pass runs into the shared stretch.
    # Where both passes end near each other the line ends centred: the longer's last bit is shifted
    # onto the centre.
    mid = nb / (na + nb)
    head_ends, tail_ends = max(before) <= slack or together[0], max(after) <= slack or together[1]
    lam = _ramp(sa - sa[0], mid if head_ends else float(head_from_b), mid if tail_ends else float(tail_from_b),
                mid, max(min(2.0 * w, (run_a[1] - run_a[0]) / 3.0), 1e-9))
    centre = pa + lam[:, None] * (point_at_arc(pb, sb, q) - pa)
    if together[0]:
        head = _blend(*rest[0], mid)
    elif head_ends:
        head = head + (centre[0] - head[-1])
    if together[1]:
        tail = _blend(*rest[1], mid)
    elif tail_ends:
        tail = tail + (centre[-1] - tail[0])
    ends = [(cb if head_from_b else ca, 0), (cb if tail_from_b else ca, 1)]
    pts = np.vstack([head[:-1], centre, tail[1:]])
    return dict(ca, id=(ca if La >= Lb else cb)["id"], points=pts, corners=_carried_corners(pts, [ca, cb], slack),
                parts=list(ca["parts"]) + list(cb["parts"]), width=mean_width([ca, cb]),
                end_types=[int(c["end_types"][e]) for c, e in ends],
                end_keypoints=[int(c["end_keypoints"][e]) for c, e in ends])


def _fold(c: dict, p: np.ndarray, s: np.ndarray, q: np.ndarray, slack: float, max_turn: float, w: float):
    """A retraced curve folded onto itself at the turn of the pen, or None.

    ``p``/``s`` are the way out's samples and arcs, ``q`` the arcs of the way back beside them
    (decreasing); the turn between them is at most ``max_turn`` of arc (a hairpin, not a loop).
    """
    pts = np.asarray(c["points"], np.float64)
    full, sf = resample_uniform(pts, _STEP_PX)
    q = np.minimum.accumulate(q)
    out0, out1, back1, back0, L = float(s[0]), float(s[-1]), float(q[-1]), float(q[0]), float(sf[-1])
    if min(out0, L - back0) > slack or not 0.0 < back1 - out1 <= max_turn:
        return None                            # open on both sides (a loop), or no hairpin
    centre = 0.5 * (p + point_at_arc(full, sf, q))
    tip = point_at_arc(full, sf, 0.5 * (out1 + back1))
    keep = 0 if out0 >= L - back0 else 1       # the side where the stroke goes on keeps its end
    if keep == 0:
        new = np.vstack([_cut(pts, 0.0, out0)[:-1], centre, tip])
    else:
        new = np.vstack([tip, centre[::-1], _cut(pts, back0, L)[1:]])
    types, kps = [0, 0], [-1, -1]              # the turn of the pen: a free end no keypoint marks
    types[keep], kps[keep] = int(c["end_types"][keep]), int(c["end_keypoints"][keep])
    return dict(c, points=new, end_types=types, end_keypoints=kps, corners=_carried_corners(new, [c], w))


def merge_passes(curves: list[dict], max_gap_widths: float, min_run_widths: float, max_angle_deg: float,
                 end_slack_widths: float, max_rounds: int = 8) -> list[dict]:
    """Curves that are passes of the pen over one line merged into one centred curve.

    Parameters
    ----------
    curves : list of dict
        ``id``, ``points`` (n, 2), ``end_types``, ``end_keypoints``, ``parts`` and ``width`` (px or
        None) per curve.
    max_gap_widths : float
        Passes lie at most this many stroke widths apart, centre to centre.
    min_run_widths : float
        ... beside each other over at least this many widths of arc.
    max_angle_deg : float
        ... their directions at most this far from parallel (or antiparallel).
    end_slack_widths : float
        At each end of the shared stretch at most one of the two curves goes on for longer than this.
    max_rounds : int
        Guard on the merge rounds (each curve takes part in at most one merge a round).

    Returns
    -------
    list of dict
        The curves, two merged passes replaced by one curve in the place of the first (its ``parts``
        those of both; at each end the end of the pass that goes on further; its width their
        length-weighted mean), a retraced curve by its fold; the others as they were, in order.
    """
    curves = [dict(c, points=np.asarray(c["points"], np.float64)) for c in curves]
    counts = [1] * len(curves)
    # A pair of curves is looked at again only when one of them changed in the last round: two curves
    # that did not merge then, as they are, do not now (each merge depends on its two curves alone),
    # and a merge skipped because one of them merged with a third involves the changed curve.
    touched, fallback_was = None, None         # None: all curves
    per_curve = [_curve_samples(c) for c in curves]
    for _ in range(max_rounds):
        known = [c["width"] for c in curves if c.get("width")]
        fallback = float(np.median(known)) if known else _DEFAULT_WIDTH_PX
        widths = np.array([float(c["width"]) if c.get("width") else fallback for c in curves])
        if not len(curves):
            break
        if fallback != fallback_was and len(known) < len(curves):
            touched = None                     # the widths of the curves without one moved
        fallback_was = fallback
        cell = float(max_gap_widths * widths.max())   # the whole drawing's grid, as a first round's
        P, T, owner, arc, offsets, W = _samples(per_curve, widths)
        if touched is None:
            i, j = _partners(P, T, owner, arc, W, max_gap_widths, max_angle_deg, cell)
        else:
            # Only the changed curves' samples and those within a cell of them: their pairs are
            # found as among all samples (the same grid, the same order).
            mine = np.isin(owner, touched)
            sub = _near_samples(P, np.flatnonzero(mine), cell)
            i, j = _partners(P[sub], T[sub], owner[sub], arc[sub], W[sub], max_gap_widths, max_angle_deg, cell)
            i, j = sub[i], sub[j]
            keep = mine[i] | mine[j]
            i, j = i[keep], j[keep]
        used, dropped = set(), set()
        for _, a, b, ia, jb in _runs(i, j, owner, arc, W, min_run_widths):
            if a in used or b in used:
                continue
            w = float(0.5 * (widths[a] + widths[b]))
            q = arc[jb]
            if a == b:
                if q[0] < arc[ia[0]]:
                    continue                   # the way back of a retrace: its way out is the run
                new = _fold(curves[a], P[ia], arc[ia], q, end_slack_widths * w, 3.0 * max_gap_widths * w, w)
            else:
                lo, hi = offsets[b], offsets[b + 1]
                new = _merge_pair(curves[a], curves[b], P[ia], arc[ia], float(arc[offsets[a + 1] - 1]),
                                  P[lo:hi], arc[lo:hi], q, counts[a], counts[b], w, end_slack_widths * w,
                                  _ATTACH_WIDTHS * w, max_gap_widths * w)
            if new is None:
                continue
            curves[a], per_curve[a] = new, _curve_samples(new)
            if a != b:
                counts[a] += counts[b]
                dropped.add(b)
            used |= {a, b}
        if not used:
            break
        kept = [k for k in range(len(curves)) if k not in dropped]
        touched = np.flatnonzero(np.isin(kept, sorted(used)))
        curves = [curves[k] for k in kept]
        per_curve = [per_curve[k] for k in kept]
        counts = [counts[k] for k in kept]
    return curves
