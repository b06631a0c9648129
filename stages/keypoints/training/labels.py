"""Keypoint ground truth from vector strokes (reference/metrics.md §4.1, §4.2).

Given centre lines and stroke widths, find the keypoints a person would mark: stroke **endpoints**,
**junctions** (X crossings, T ends touching another stroke, meetings of three or more ends) and
**sharp corners** (inside a stroke, or two strokes meeting end to end with a turn).

The rules are those used to label shared/data/realvec_dev (§4.2), so that the detector learns the
labelling it is scored against. With r = max(2, w):

* a stroke whose ends are within r and whose length exceeds 6r is closed and has no ends;
* an end within r of another stroke's interior (more than 2r of arc from that stroke's ends), or of
  its own stroke farther than 4r of arc away (``own_stroke_tee``), is a junction (T);
* ends within r of each other meet: three or more → junction, two → sharp corner when the strokes turn
  by more than ``corner_turn_deg`` there (else a smooth continuation, no keypoint), one → endpoint;
* crossings (also self-crossings) at more than ``crossing_min_deg`` → junction;
* junctions are merged within 2r; endpoints within 2r of a junction are dropped;
* corners inside strokes: local maxima of the turning angle between chords of max(4, 2w) px on
  either side, above ``corner_turn_deg`` both there and at ±max(1.5, w) px, and not within 2r of a
  junction or an endpoint.

Choices made on purpose
-----------------------
* **Corner angle 135°** (turning 45°): the paper's Appendix B says 135°, and the realvec_dev labels
  use it; the authors' dataset script uses 139.5° (3.1π/4). The difference only moves borderline
  cases. Configurable as ``corner_turn_deg``.
* Widths vary along a stroke (pressure); r uses the stroke's mean width, and a pair of strokes uses
  the larger of their two radii.
* **Crossing angle 37° here, 20° for the shipped network**: §4.2 and the realvec_dev labels call
  crossings junctions above ≈ 37°, the acceptance scorer above 20°; phase 19g was trained with
  ``crossing_min_deg: 20`` because the scorer's shallow crossings were missed end to end (MODEL_CARD).

Points are (x, y), pixel units, origin at the top-left corner of the image.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from stages.geometry import point_at_arc, resample_uniform
from stages.keypoints.codes import CORNER, ENDPOINT, JUNCTION
from stages.keypoints.training.config import LabelRules


def _at(points: np.ndarray, arc: np.ndarray, s: np.ndarray | float, closed: bool) -> np.ndarray:
    """Point at arc length ``s`` (wrapped on closed strokes, clamped on open ones)."""
    total = arc[-1]
    s = np.asarray(s, dtype=np.float64)
    s = np.mod(s, total) if closed and total > 0 else np.clip(s, 0.0, total)
    return point_at_arc(points, arc, s)


def _turning(points, arc, s, chord, closed) -> np.ndarray:
    """Turning angle (degrees) at arc ``s`` between the chords of length ``chord`` before and after."""
    p = _at(points, arc, s, closed)
    a = p - _at(points, arc, s - chord, closed)
    b = _at(points, arc, s + chord, closed) - p
    na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    cos = np.einsum("...i,...i->...", a, b) / np.maximum(na * nb, 1e-12)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _clusters(points: np.ndarray, radius: np.ndarray | float) -> list[np.ndarray]:
    """Connected groups of points closer than ``radius`` (single linkage)."""
    n = len(points)
    if n == 0:
        return []
    parent = np.arange(n)

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    rad = np.broadcast_to(np.asarray(radius, dtype=np.float64), (n,))
    tree = cKDTree(points)
    for i, j in tree.query_pairs(float(rad.max())):
        if np.hypot(*(points[i] - points[j])) < max(rad[i], rad[j]):
            parent[find(i)] = find(j)
    roots = np.array([find(i) for i in range(n)])
    return [np.flatnonzero(roots == r) for r in np.unique(roots)]


def _segment_crossings(a0, a1, b0, b1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Proper intersections of segment pairs; returns mask, t on a, u on b."""
    da, db = a1 - a0, b1 - b0
    den = da[:, 0] * db[:, 1] - da[:, 1] * db[:, 0]
    w = b0 - a0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[:, 0] * db[:, 1] - w[:, 1] * db[:, 0]) / den
        u = (w[:, 0] * da[:, 1] - w[:, 1] * da[:, 0]) / den
    ok = (np.abs(den) > 1e-12) & (t >= 0) & (t < 1) & (u >= 0) & (u < 1)
    return ok, t, u


def label_keypoints(strokes: list[np.ndarray], widths: list[float] | np.ndarray,
                    rules: LabelRules) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints of a vector drawing by the rules of metrics.md §4.2.

    Parameters
    ----------
    strokes : list of numpy.ndarray
        Centre lines, each (n, 2) in (x, y).
    widths : sequence of float
        Mean stroke width of each stroke, pixels.
    rules : LabelRules
        Thresholds.

    Returns
    -------
    points : numpy.ndarray
        float64 (N, 2) in (x, y).
    types : numpy.ndarray
        int8 (N,) in {1 endpoint, 3 junction, 5 sharp corner}.
    """
    rs, arcs, radius, closed = [], [], [], []
    for pts, w in zip(strokes, widths):
        p, s = resample_uniform(pts, rules.step)
        rs.append(p)
        arcs.append(s)
        r = max(rules.min_radius, float(w))
        radius.append(r)
        closed.append(len(p) > 2 and np.hypot(*(p[0] - p[-1])) < r and s[-1] > 6 * r)
    n = len(rs)
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, np.int8)
    radius = np.array(radius)
    junctions: list[np.ndarray] = []
    endpoints: list[np.ndarray] = []
    corners: list[np.ndarray] = []

    # All resampled points, for "is this end near another stroke's interior" queries.
    all_pts = np.concatenate(rs)
    owner = np.concatenate([np.full(len(p), k) for k, p in enumerate(rs)])
    arc_all = np.concatenate(arcs)
    length = np.array([a[-1] for a in arcs])
    tree = cKDTree(all_pts)

    # --- stroke ends -------------------------------------------------------------------------
    free_ends = []  # (stroke, which end 0/1, position)
    for k in range(n):
        if closed[k]:
            continue
        if length[k] < radius[k]:
            # A dot: one end, at its centre.
            ends = [(0, rs[k].mean(axis=0))]
        else:
            ends = [(0, rs[k][0]), (1, rs[k][-1])]
        for which, p in ends:
            near = np.asarray(tree.query_ball_point(p, float(radius.max())), dtype=np.int64)
            is_t = False
            if len(near):
                o = owner[near]
                d = np.hypot(*(all_pts[near] - p).T)
                rr = np.maximum(radius[o], radius[k])
                a = arc_all[near]
                other = (o != k) & (d < rr) & (
                    np.array([closed[j] for j in o], dtype=bool)
                    | ((a > 2 * rr) & (a < length[o] - 2 * rr)))
                s_end = 0.0 if which == 0 else length[k]
                own = (o == k) & (d < radius[k]) & (np.abs(a - s_end) > 4 * radius[k]) & rules.own_stroke_tee
                is_t = bool(other.any() or own.any())
            if is_t:
                junctions.append(p)
            else:
                free_ends.append((k, which, p))

    if free_ends:
        pos = np.array([e[2] for e in free_ends])
        rad = np.array([radius[e[0]] for e in free_ends])
        for group in _clusters(pos, rad):
            if len(group) >= 3:
                junctions.append(pos[group].mean(axis=0))
            elif len(group) == 2:
                (k1, w1, p1), (k2, w2, p2) = free_ends[group[0]], free_ends[group[1]]
                chord = max(4.0, 2 * max(float(widths[k1]), float(widths[k2])))
                # Direction of travel arriving at end 1, then leaving from end 2.
                s1 = length[k1] - chord if w1 == 1 else chord
                d_in = p1 - _at(rs[k1], arcs[k1], s1, False)
                s2 = chord if w2 == 0 else length[k2] - chord
                d_out = _at(rs[k2], arcs[k2], s2, False) - p2
                cos = d_in @ d_out / max(np.linalg.norm(d_in) * np.linalg.norm(d_out), 1e-12)
                if np.degrees(np.arccos(np.clip(cos, -1, 1))) > rules.corner_turn_deg:
                    corners.append(pos[group].mean(axis=0))
            else:
                endpoints.append(pos[group[0]])

    # --- crossings ---------------------------------------------------------------------------
    seg_a = np.concatenate([p[:-1] for p in rs if len(p) > 1]) if n else np.zeros((0, 2))
    if len(seg_a):
        seg_b = np.concatenate([p[1:] for p in rs if len(p) > 1])
        seg_owner = np.concatenate([np.full(len(p) - 1, k) for k, p in enumerate(rs) if len(p) > 1])
        seg_arc = np.concatenate([a[:-1] for a, p in zip(arcs, rs) if len(p) > 1])
        mid = 0.5 * (seg_a + seg_b)
        pairs = cKDTree(mid).query_pairs(2 * rules.step + 1e-6, output_type="ndarray")
        if len(pairs):
            i, j = pairs[:, 0], pairs[:, 1]
            oi, oj = seg_owner[i], seg_owner[j]
            rr = np.maximum(radius[oi], radius[oj])
            # Self-crossings only between parts of a stroke far apart along it.
            far = (oi != oj) | (np.abs(seg_arc[i] - seg_arc[j]) > 4 * rr)
            if closed and any(closed):
                wrap = np.array([closed[o] for o in oi]) & (oi == oj)
                far &= ~wrap | (np.minimum(np.abs(seg_arc[i] - seg_arc[j]),
                                           length[oi] - np.abs(seg_arc[i] - seg_arc[j])) > 4 * rr)
            i, j, oi, oj, rr = i[far], j[far], oi[far], oj[far], rr[far]
            ok, t, _ = _segment_crossings(seg_a[i], seg_b[i], seg_a[j], seg_b[j])
            for a_, b_, ka, kb, r_, tt in zip(i[ok], j[ok], oi[ok], oj[ok], rr[ok], t[ok]):
                p = seg_a[a_] + tt * (seg_b[a_] - seg_a[a_])
                chord = max(2.0, r_)
                ta = _at(rs[ka], arcs[ka], seg_arc[a_] + chord, closed[ka]) - _at(rs[ka], arcs[ka], seg_arc[a_] - chord, closed[ka])
                tb = _at(rs[kb], arcs[kb], seg_arc[b_] + chord, closed[kb]) - _at(rs[kb], arcs[kb], seg_arc[b_] - chord, closed[kb])
                cos = abs(ta @ tb) / max(np.linalg.norm(ta) * np.linalg.norm(tb), 1e-12)
                if np.degrees(np.arccos(np.clip(cos, 0, 1))) > rules.crossing_min_deg:
                    junctions.append(p)

    r_draw = float(np.median(radius))
    # --- merge junctions, drop endpoints near them ----------------------------------------------
    if junctions:
        jp = np.array(junctions)
        junctions = [jp[g].mean(axis=0) for g in _clusters(jp, 2 * r_draw)]
    jp = np.array(junctions).reshape(-1, 2)
    if endpoints and len(jp):
        endpoints = [e for e in endpoints if np.min(np.hypot(*(jp - e).T)) >= 2 * r_draw]

    # --- corners inside strokes --------------------------------------------------------------
    for k in range(n):
        chord = max(4.0, 2 * float(widths[k]))
        inner = max(1.5, float(widths[k]))
        s = arcs[k]
        if s[-1] < 2 * chord + rules.step:
            continue
        cand = s if closed[k] else s[(s >= chord) & (s <= s[-1] - chord)]
        if len(cand) == 0:
            continue
        theta = _turning(rs[k], s, cand, chord, closed[k])
        big = theta > rules.corner_turn_deg
        if not big.any():
            continue
        theta_in = _turning(rs[k], s, cand, inner, closed[k])
        # Local maxima over ±chord (non-maximum suppression along the arc).
        win = max(int(round(chord / rules.step)), 1)
        order = np.argsort(-theta)
        taken = np.zeros(len(cand), bool)
        for idx in order:
            if not big[idx]:
                break
            if taken[idx]:
                continue
            lo, hi = idx - win, idx + win + 1
            if closed[k]:
                taken[np.arange(lo, hi) % len(cand)] = True
            else:
                taken[max(lo, 0):hi] = True
            if theta_in[idx] > rules.corner_turn_deg:
                corners.append(_at(rs[k], s, cand[idx], closed[k]))

    keep_c = []
    others = np.array(list(jp) + list(endpoints)).reshape(-1, 2)
    for c in corners:
        if len(others) == 0 or np.min(np.hypot(*(others - c).T)) >= 2 * r_draw:
            keep_c.append(c)

    pts = list(endpoints) + list(jp) + keep_c
    types = [ENDPOINT] * len(endpoints) + [JUNCTION] * len(jp) + [CORNER] * len(keep_c)
    if not pts:
        return np.zeros((0, 2)), np.zeros(0, np.int8)
    return np.array(pts, dtype=np.float64), np.array(types, dtype=np.int8)
