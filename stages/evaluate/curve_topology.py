"""Topology of a set of curves by valence, and its comparison with vector ground truth.

The same extraction (:func:`curve_topology`) runs on the ground-truth strokes and on the output
curves, so the two are judged by one rule. With ``r = max(meet_min_px, w)`` (w = the drawing's stroke
width):

1. **Meeting points.** Curve ends closer than ``r`` are grouped (single linkage) into a meeting point.
   Its *valence* is the number of ends in it plus two for every other curve passing through it: a
   curve passes when a run of its points lies within ``r`` of the meeting point or of one of its ends,
   and that run is not the run leading to one of the curve's own ends in the group. (So a stroke whose
   end touches its own interior, a "6", makes a junction too.)
2. **Classes.** Valence 1 = free end, 2 = continuation (two curves joined at a corner or smoothly, a
   closed loop), >= 3 = junction (T, Y, X ...).
3. **Crossings.** Two curves (or non-neighbouring parts of one curve) that cross farther than ``r``
   from every curve end are a junction as well (valence 4), if they cross at more than
   ``crossing_min_angle_deg`` — the angle used for the ground-truth keypoints (metrics.md §4.1–4.2);
   near-tangent touching is overlap, measured separately. Junctions closer than
   ``junction_merge_factor · r`` are merged.
4. **Defects** (reported for output and ground truth alike):
   - *junction gaps*: free ends whose distance to another curve (or to a far part of their own)
     ahead of them (within 90° of the end's outward direction) lies in ``(r, gap_max]`` with
     ``gap_max = max(gap_max_px, gap_max_widths · w)`` — ends that almost, but do not, meet. Two ends
     that almost meet count as two gaps.
   - *dangling branches*: curves shorter than ``max(dangling_max_px, dangling_max_widths · w)`` with
     one free end and the other end at a junction — the spurious spurs of skeleton methods.
   - *duplicated length*: half the length of curve pieces that run within ``r`` of another curve piece
     (or of a part of their own curve more than ``overlap_self_separation · r`` away along it) at an
     angle below ``overlap_max_angle_deg``, ignoring points within ``overlap_exclusion_factor · r`` of a
     meeting point or junction (where curves legitimately come together). Halving counts a doubled
     piece once.

:func:`compare_topology` matches free ends and junctions of the output to those of the ground truth
one-to-one within ``max(match_min_px, w)`` and reports precision, recall and F1 for both.

Points are (x, y) in pixel units; every geometric test works on the curves resampled every
``resample_px`` (the resampled polyline is the same set of points as the input one).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from stages.evaluate import TopologyParams
from stages.evaluate.matching import match_one_to_one, prf1
from stages.geometry import subdivide

__all__ = ["TopologyParams", "Topology", "curve_topology", "compare_topology", "benchmark_gap_statistics"]


@dataclass
class Topology:
    """Result of :func:`curve_topology`.

    Attributes
    ----------
    free_ends, continuations, junctions : numpy.ndarray
        (k, 2) positions (x, y).
    junction_valence : numpy.ndarray
        int (k,) valence of each junction (4 for a crossing).
    gaps : numpy.ndarray
        (k, 3): x, y and gap distance of every junction gap.
    dangling : list of int
        Indices of dangling-branch curves.
    duplicated_length : float
        Pixels (see the module notes).
    duplicated_points : numpy.ndarray
        (k, 2) points of the duplicated pieces, about every 2 px (for pictures).
    n_curves : int
        Non-degenerate curves.
    total_length : float
        Sum of curve lengths in pixels.
    """

    free_ends: np.ndarray
    continuations: np.ndarray
    junctions: np.ndarray
    junction_valence: np.ndarray
    gaps: np.ndarray
    dangling: list[int] = field(default_factory=list)
    duplicated_length: float = 0.0
    duplicated_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    n_curves: int = 0
    total_length: float = 0.0

    def counts(self) -> dict:
        """Scalar summary (JSON-friendly)."""
        return {
            "curves": self.n_curves,
            "length_px": round(self.total_length, 3),
            "free_ends": len(self.free_ends),
            "continuations": len(self.continuations),
            "junctions": len(self.junctions),
            "junction_gaps": len(self.gaps),
            "dangling": len(self.dangling),
            "duplicated_px": round(self.duplicated_length, 3),
        }


# --------------------------------------------------------------------------------------------------
# geometry helpers

def _clean(curve) -> np.ndarray | None:
    """Finite points without consecutive repeats; None for a curve of zero length."""
    p = np.asarray(curve, dtype=np.float64).reshape(-1, 2)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) < 2:
        return None
    keep = np.r_[True, np.any(np.diff(p, axis=0) != 0, axis=1)]
    p = p[keep]
    return p if len(p) >= 2 else None


def _runs(sorted_idx: np.ndarray, arc: np.ndarray, max_gap: float) -> list[np.ndarray]:
    """Split sorted sample indices of one curve into runs whose arc gaps are <= ``max_gap``."""
    if len(sorted_idx) == 0:
        return []
    cut = np.nonzero(np.diff(arc[sorted_idx]) > max_gap)[0] + 1
    return np.split(sorted_idx, cut)


def _merge_points(pts: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Single-linkage groups of points within ``radius``: (labels, number of groups)."""
    n = len(pts)
    if n == 0:
        return np.zeros(0, dtype=np.int64), 0
    pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray")
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    ncomp, labels = connected_components(g, directed=False)
    return labels, ncomp


def _segment_crossings(a0, a1, b0, b1):
    """Proper intersections of segment pairs (vectorised): mask, parameter t on a, |cos| of angle."""
    da = a1 - a0
    db = b1 - b0
    den = da[:, 0] * db[:, 1] - da[:, 1] * db[:, 0]
    w = b0 - a0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[:, 0] * db[:, 1] - w[:, 1] * db[:, 0]) / den
        u = (w[:, 0] * da[:, 1] - w[:, 1] * da[:, 0]) / den
        ok = (den != 0) & (t >= 0) & (t < 1) & (u >= 0) & (u < 1)
        cos = np.abs(np.einsum("ij,ij->i", da, db)) / (np.hypot(*da.T) * np.hypot(*db.T))
    return ok, t, cos


# --------------------------------------------------------------------------------------------------

def curve_topology(curves: Sequence, width: float, params: TopologyParams) -> Topology:
    """Free ends, continuations, junctions and defects of a set of curves.

    Parameters
    ----------
    curves : sequence of array-like
        Polylines, each (n, 2) in (x, y) pixel units.
    width : float
        Stroke width of the drawing in pixels (sets the tolerances, see the module notes).
    params : TopologyParams

    Returns
    -------
    Topology
    """
    r = max(params.meet_min_px, float(width))
    step = params.resample_px
    polys = [q for q in (_clean(c) for c in curves) if q is not None]
    empty = np.zeros((0, 2))
    if not polys:
        return Topology(empty, empty, empty, np.zeros(0, np.int64), np.zeros((0, 3)))

    samples, arcs, owner = [], [], []
    for ci, p in enumerate(polys):
        s, a = subdivide(p, step)
        samples.append(s)
        arcs.append(a)
        owner.append(np.full(len(s), ci))
    start = np.r_[0, np.cumsum([len(s) for s in samples])]
    S = np.concatenate(samples)
    A = np.concatenate(arcs)
    O = np.concatenate(owner)
    lengths = np.array([a[-1] for a in arcs])
    tree = cKDTree(S)
    nc = len(polys)

    # 1. meeting points of curve ends --------------------------------------------------------------
    # An end is linked to another curve's end when the other curve's nearest point to it, within r,
    # is at most 2r of arc from that end (a sloppily drawn L is a corner, not a T; the ground-truth
    # rule of metrics.md §4.2). A curve's own two ends link only when it is long enough to be a closed
    # loop (> 6r, the same rule).
    end_sample = np.stack([start[:-1], start[1:] - 1], axis=1).ravel()  # curve c: ends 2c, 2c+1
    end_xy = S[end_sample]
    end_arc = A[end_sample]
    links = []
    for e in range(2 * nc):
        c = e // 2
        cand = np.array(tree.query_ball_point(end_xy[e], r * (1 - 1e-9)), dtype=np.int64)
        # the end's own neighbourhood on its curve is not another curve
        cand = cand[(O[cand] != c) | (np.abs(A[cand] - end_arc[e]) > 2 * r)]
        if len(cand) == 0:
            continue
        dist = np.hypot(*(S[cand] - end_xy[e]).T)
        for oc in np.unique(O[cand]):
            mine = cand[O[cand] == oc]
            nearest = mine[np.argmin(dist[O[cand] == oc])]
            if oc == c and lengths[c] <= 6 * r:
                continue
            if A[nearest] <= 2 * r:
                links.append((e, 2 * oc))
            elif lengths[oc] - A[nearest] <= 2 * r:
                links.append((e, 2 * oc + 1))
    links = np.array(links, dtype=np.int64).reshape(-1, 2)
    g = coo_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(2 * nc, 2 * nc))
    nmeet, labels = connected_components(g, directed=False)
    valence = np.zeros(nmeet, dtype=np.int64)
    meet_xy = np.zeros((nmeet, 2))
    for m in range(nmeet):
        ends = np.nonzero(labels == m)[0]
        centre = end_xy[ends].mean(axis=0)
        meet_xy[m] = centre
        near = set(tree.query_ball_point(centre, r))
        for e in ends:
            near.update(tree.query_ball_point(end_xy[e], r))
        near = np.array(sorted(near), dtype=np.int64)
        passes = 0
        for c in np.unique(O[near]):
            own_arcs = end_arc[ends[ends // 2 == c]]
            for run in _runs(near[O[near] == c], A, max_gap=r):
                if len(own_arcs) and np.min(np.abs(A[run][:, None] - own_arcs[None, :])) <= 2 * r:
                    continue  # the run leading to this curve's own end in the group
                passes += 1
        valence[m] = len(ends) + 2 * passes
    end_meet = labels.reshape(nc, 2)

    # 2. crossings away from curve ends -------------------------------------------------------------
    seg_a = np.arange(len(S) - 1)
    seg_a = seg_a[O[seg_a] == O[seg_a + 1]]  # segments inside one curve
    mids = 0.5 * (S[seg_a] + S[seg_a + 1])
    cross_xy = empty
    if len(seg_a) > 1:
        pairs = cKDTree(mids).query_pairs(step * 1.0001, output_type="ndarray")
        i, j = seg_a[pairs[:, 0]], seg_a[pairs[:, 1]]
        far = (O[i] != O[j]) | (np.abs(A[i] - A[j]) > params.overlap_self_separation * r)
        i, j = i[far], j[far]
        ok, t, cos = _segment_crossings(S[i], S[i + 1], S[j], S[j + 1])
        ok &= cos < np.cos(np.deg2rad(params.crossing_min_angle_deg))
        pts = S[i[ok]] + t[ok, None] * (S[i[ok] + 1] - S[i[ok]])
        if len(pts):
            d_end, _ = cKDTree(end_xy).query(pts)
            cross_xy = pts[d_end >= r]

    # 3. classes and junction merging ---------------------------------------------------------------
    free = valence == 1
    junc_xy = np.vstack([meet_xy[valence >= 3], cross_xy])
    junc_val = np.r_[valence[valence >= 3], np.full(len(cross_xy), 4)]
    if len(junc_xy):
        jl, nj = _merge_points(junc_xy, params.junction_merge_factor * r)
        merged_xy = np.array([junc_xy[jl == k].mean(axis=0) for k in range(nj)])
        merged_val = np.array([junc_val[jl == k].max() for k in range(nj)], dtype=np.int64)
    else:
        merged_xy, merged_val = empty, np.zeros(0, np.int64)

    # 4a. junction gaps ----------------------------------------------------------------------------
    gap_max = max(params.gap_max_px, params.gap_max_widths * float(width))
    gaps = []
    for m in np.nonzero(free)[0]:
        e = int(np.nonzero(labels == m)[0][0])
        c, q = e // 2, end_xy[e]
        cand = np.array(tree.query_ball_point(q, gap_max), dtype=np.int64)
        if len(cand) == 0:
            continue
        own_far = np.abs(A[cand] - A[end_sample[e]]) > max(params.overlap_self_separation * r, 2 * gap_max)
        # only what lies ahead of the end (within 90° of its outward tangent): a short branch pointing
        # away from the curve it hangs on is not almost touching that curve
        es = end_sample[e]
        back = S[es + 1] if e % 2 == 0 else S[es - 1]
        ahead = (S[cand] - q) @ (q - back) > 0
        cand = cand[((O[cand] != c) | own_far) & ahead]
        if len(cand) == 0:
            continue
        d = _distance_to_samples(q, cand, S, O)
        if r <= d <= gap_max:
            gaps.append((q[0], q[1], d))

    # 4b. dangling branches ------------------------------------------------------------------------
    dang_max = max(params.dangling_max_px, params.dangling_max_widths * float(width))
    dangling = []
    for c in range(nc):
        v0, v1 = valence[end_meet[c, 0]], valence[end_meet[c, 1]]
        if lengths[c] < dang_max and min(v0, v1) == 1 and max(v0, v1) >= 3:
            dangling.append(c)

    # 4c. duplicated (overlapping, near-parallel) length -----------------------------------------
    tangent = np.zeros_like(S)
    for c in range(nc):
        s = S[start[c]:start[c + 1]]
        tangent[start[c]:start[c + 1]] = np.gradient(s, axis=0)
    tangent /= np.maximum(np.hypot(*tangent.T), 1e-12)[:, None]
    pairs = tree.query_pairs(r, output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    other = (O[i] != O[j]) | (np.abs(A[i] - A[j]) > params.overlap_self_separation * r)
    par = np.abs(np.einsum("ij,ij->i", tangent[i], tangent[j])) >= np.cos(np.deg2rad(params.overlap_max_angle_deg))
    i, j = i[other & par], j[other & par]
    overlapping = np.zeros(len(S), dtype=bool)
    overlapping[i] = True
    overlapping[j] = True
    special = np.vstack([meet_xy, merged_xy])
    d_special, _ = cKDTree(special).query(S)
    overlapping &= d_special > params.overlap_exclusion_factor * r
    # each sample stands for the arc half-way to its neighbours
    ds = np.zeros(len(S))
    for c in range(nc):
        a = A[start[c]:start[c + 1]]
        ds[start[c]:start[c + 1]] = np.gradient(a) if len(a) > 1 else 0.0
    duplicated = 0.5 * float(ds[overlapping].sum())

    return Topology(
        free_ends=meet_xy[free],
        continuations=meet_xy[valence == 2],
        junctions=merged_xy,
        junction_valence=merged_val,
        gaps=np.array(gaps, dtype=np.float64).reshape(-1, 3),
        dangling=dangling,
        duplicated_length=duplicated,
        duplicated_points=S[overlapping][:: max(1, int(round(2.0 / step)))],
        n_curves=nc,
        total_length=float(lengths.sum()),
    )


def _distance_to_samples(q: np.ndarray, cand: np.ndarray, S: np.ndarray, O: np.ndarray) -> float:
    """Exact distance from ``q`` to the polyline pieces around the candidate samples."""
    best = np.inf
    for k in cand:
        for a, b in ((k - 1, k), (k, k + 1)):
            if a < 0 or b >= len(S) or O[a] != O[b]:
                continue
            d = S[b] - S[a]
            ll = d @ d
            t = 0.0 if ll == 0 else min(1.0, max(0.0, float((q - S[a]) @ d) / ll))
            best = min(best, float(np.hypot(*(q - S[a] - t * d))))
    return best


def compare_topology(output: Topology, gt: Topology, width: float, params: TopologyParams) -> dict:
    """Endpoint and junction F1 of an output topology against the ground truth.

    Parameters
    ----------
    output, gt : Topology
        From :func:`curve_topology` on the output curves and on the ground-truth strokes.
    width : float
        Stroke width in pixels; the matching radius is ``max(match_min_px, width)``.
    params : TopologyParams

    Returns
    -------
    dict
        ``endpoint_{precision,recall,f1}``, ``junction_{precision,recall,f1}``, the output's counts
        (``curves``, ``free_ends``, ``junctions``, ``junction_gaps``, ``dangling``, ``duplicated_px``)
        and the ground truth's with a ``gt_`` prefix.
    """
    radius = max(params.match_min_px, float(width))
    res: dict = {}
    for name, a, b in (("endpoint", output.free_ends, gt.free_ends), ("junction", output.junctions, gt.junctions)):
        tp = len(match_one_to_one(a, b, radius))
        p, rc, f1 = prf1(tp, len(a) - tp, len(b) - tp)
        res.update({f"{name}_precision": p, f"{name}_recall": rc, f"{name}_f1": f1})
    res.update(output.counts())
    res.update({f"gt_{k}": v for k, v in gt.counts().items()})
    return res


def benchmark_gap_statistics(curves: Sequence, long_edge: float, threshold: float = 1e-4) -> tuple[float, int]:
    """Junction-gap statistic of the sketch benchmark (metrics.md §2.6, ``endpoint_statistics``).

    For every curve end: the distance to the nearest end of another curve; if that is not zero, the
    distance to the nearest point of another curve when smaller; divided by ``long_edge``.

    Returns
    -------
    (float, int)
        Sum of the normalised gaps and the number of gaps above ``threshold``.
    """
    polys = [q for q in (_clean(c) for c in curves) if q is not None]
    if len(polys) < 2:
        return 0.0, 0
    ends = np.array([[p[0], p[-1]] for p in polys])  # (n, 2, 2)
    gaps = []
    for c, p in enumerate(polys):
        others = [q for k, q in enumerate(polys) if k != c]
        other_ends = np.concatenate([[q[0], q[-1]] for q in others])
        for q in ends[c]:
            g = float(np.min(np.hypot(*(other_ends - q).T)))
            if g > 0:
                g = min(g, min(_point_polyline_distance(q, o) for o in others))
            gaps.append(g / long_edge)
    gaps = np.array(gaps)
    return float(gaps.sum()), int(np.count_nonzero(gaps > threshold))


def _point_polyline_distance(q: np.ndarray, p: np.ndarray) -> float:
    a, b = p[:-1], p[1:]
    d = b - a
    ll = np.einsum("ij,ij->i", d, d)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(ll > 0, np.clip(((q - a) * d).sum(1) / ll, 0, 1), 0.0)
    return float(np.min(np.hypot(*(q - a - t[:, None] * d).T)))
