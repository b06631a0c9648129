"""Clean-up of the graph's ends (steps 5–7b of :mod:`stages.graph.cleanup`; B19 §A.3).

Steps, in the order :func:`stages.graph.run` applies them (measurements in stages/DECISIONS.md):

5. :func:`prune_covered_spurs` — B19's ``removeBranchesFilter1`` (not in the authors' code): short
   dangling branches lying inside the stroke discs of the rest of the graph go, one per junction per
   round.  This is what leaves a straight stroke's ragged tip as a path end instead of a fork.
6. :func:`trim_hooked_tips` — leaves that hook sideways inside their neighbour's disc (rounded tips).
6b. :func:`trim_covered_ends` (run after step 7, so that the pieces of a Y are joined first) — ink
   of *another* stroke is not a stroke end (not in the references).  Where one stroke meets another
   (a T), the field inside the bar is a cross whose normal root continues the stem, so the stem's
   streamlines run on across the bar to its far edge and its chain ends on the far side; a stroke's
   rounded tip often traces as a separate tiny component inside the stroke's own discs.  Such ends
   made spurious junctions.  So a dangling run of vertices that all lie inside the discs (radius
   ``max(width/2, 0.5) + cover_margin``) of vertices of *other* components is cut back to its vertex
   nearest those vertices (a stem then ends on the bar's centre line), if the run is at most
   ``spur_max_length`` long (longer runs are overlapping strokes, left alone); a whole component of
   at most that length with at least ``spur_min_covered`` of its vertices so covered by *longer*
   components is thickness of the other stroke and goes (only the shorter of two short components
   crossing inside a filled blob goes: deleting both can delete a filled eye's only curves).
   Known cost: where the arms of a sharp corner or vee were traced as two components, the cut can
   take the tip.
7. :func:`join_singular_ends` — B19's ``connectStuffAroundSingularities`` (not in the authors' code):
   traces stop at the singularity of a Y junction; joining the dangling end there to the other
   branches gives the Y its valence-3 vertex (edges with ``edge_curve`` −1).
7b. :func:`close_loop_caps` (not in the references) — where a stroke turns back tightly (an eye drawn
   as a thin teardrop), the streamlines do not follow the cap, and the loop's two sides end as leaves
   side by side; two leaves of one component, within ``close_caps_widths`` widths (at least 2 px) of
   each other across ink and more than ``close_caps_min_hops`` edges apart, are joined, so the loop
   is closed and eyes come out as closed curves.  It runs on the narrow band, so it needs prep's
   paper-aware hole repair: with the plain repair the slit of such loops was filled.
"""

from __future__ import annotations

import numpy as np

from stages.geometry import segment_in_band
from stages.graph.cleanup import adjacency, components, edges_from_adjacency


def _leaf_chain(adj, v):
    """From leaf ``v`` along degree-2 vertices: (chain vertices from v, the vertex where it stops)."""
    chain = [v]
    prev, cur = v, next(iter(adj[v]))
    while len(adj[cur]) == 2:
        chain.append(cur)
        prev, cur = cur, next(u for u in adj[cur] if u != prev)
        if cur == v:
            return chain, -1
    return chain, cur


def _covered_count(tree, xy, radius, rmax, chain) -> int:
    """How many chain vertices lie inside the disc of some vertex not on the chain."""
    near = tree.query_ball_point(xy[chain], rmax)
    lens = np.array([len(q) for q in near])
    if lens.sum() == 0:
        return 0
    q = np.concatenate([np.asarray(a, dtype=np.int64) for a in near])
    owner = np.repeat(np.arange(len(chain)), lens)
    hit = ~np.isin(q, chain) & (np.linalg.norm(xy[q] - xy[chain[owner]], axis=1) <= radius[q])
    return int(np.count_nonzero(np.bincount(owner[hit], minlength=len(chain))))


def prune_covered_spurs(xy, width, strength, edges, max_length, min_covered):
    """Delete short dangling branches lying inside the stroke discs of the rest of the graph.

    B19's ``removeBranchesFilter1``: a *spur* is a chain from a leaf to the first vertex of degree ≥ 3
    (the junction), at most ``max_length`` px long.  Its vertices are covered when they lie within
    ``max(width/2, 0.5)`` of a vertex not on the spur; a spur with at least ``min_covered`` of its
    vertices covered (or at most one uncovered) is thickness, not a stroke.  At each junction only one
    spur goes per round (the best covered, then the weakest by streamline count, then the shortest), so
    the two ragged ends of a stroke's tip never both vanish; rounds repeat until nothing changes.

    Parameters
    ----------
    xy, width : numpy.ndarray
        Vertex positions and widths.
    strength : numpy.ndarray
        Streamlines per vertex (tie-breaking).
    edges : numpy.ndarray
        (E, 2).
    max_length : float
        Longest spur (px), including the edge into the junction.
    min_covered : float
        Covered fraction from which a spur is deleted.

    Returns
    -------
    edges : numpy.ndarray
        Remaining edges (spur vertices are left isolated).
    removed : int
        Number of spurs deleted.
    """
    from scipy.spatial import cKDTree

    n = len(xy)
    adj = adjacency(n, edges)
    if n == 0:
        return edges, 0
    tree = cKDTree(xy)
    radius = np.maximum(width / 2, 0.5)
    rmax = float(radius.max())
    removed = 0
    while True:
        best = {}
        for v in range(n):
            if len(adj[v]) != 1:
                continue
            chain, j = _leaf_chain(adj, v)
            if j < 0 or len(adj[j]) < 3:
                continue
            pts = xy[chain + [j]]
            length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
            if length > max_length:
                continue
            covered = _covered_count(tree, xy, radius, rmax, np.asarray(chain))
            frac = covered / len(chain)
            if frac < min_covered and len(chain) - covered > 1:
                continue
            key = (-frac, int(strength[chain].sum()), length)
            if j not in best or key < best[j][0]:
                best[j] = (key, chain)
        if not best:
            break
        for j, (_, chain) in best.items():
            for a, b in zip(chain, chain[1:] + [j]):
                adj[a].discard(b)
                adj[b].discard(a)
            removed += 1
    return edges_from_adjacency(adj), removed


def join_singular_ends(xy, width, edges, flags, band, singular, max_distance, min_hops):
    """Join dangling ends next to singularities across them (B19 ``connectStuffAroundSingularities``).

    A vertex counts as next to a singularity if it is flagged (its cross-section or one of its
    streamlines stopped on a singular pixel) or if a singular pixel lies within ``width/2 + 1`` px of
    it (traces stopping short of a singularity leave their last, small cross-sections just outside
    it, unflagged).  Each such leaf is joined to the nearest other such vertex within ``max_distance``
    px that lies ahead of it (the segment continues the leaf's edge direction), whose straight segment
    stays in the band, and that is more than ``min_hops`` edges away in the graph (or in another
    component).  This is what gives a Y junction, where the field has a singularity and the traces
    stop, its valence-3 vertex.

    Returns
    -------
    new_edges : numpy.ndarray
        (K, 2) the added edges (``edge_curve`` −1 in the artifact).
    """
    from scipy.spatial import cKDTree

    sing_px = np.argwhere(singular)
    if len(sing_px):
        # each vertex pixel's distance to the nearest singular pixel, by a tree of the few singular
        # pixels rather than a distance transform of the whole image (whose cost and memory follow
        # the page's area, not the ink); between integer pixel indices both are the same square root
        i = np.clip(np.floor(xy[:, 1]).astype(int), 0, band.shape[0] - 1)
        j = np.clip(np.floor(xy[:, 0]).astype(int), 0, band.shape[1] - 1)
        dist = cKDTree(sing_px).query(np.stack([i, j], axis=1))[0] if len(xy) else np.zeros(0)
        near = (flags & 1).astype(bool) | (dist <= width / 2 + 1)
    else:
        near = (flags & 1).astype(bool)
    n = len(xy)
    adj = adjacency(n, edges)
    flagged = np.flatnonzero(near)
    if len(flagged) < 2:
        return np.zeros((0, 2), np.int64)
    tree = cKDTree(xy[flagged])
    added = []
    for v in flagged:
        if len(adj[v]) != 1:
            continue
        u = next(iter(adj[v]))
        out = xy[v] - xy[u]
        cands = []
        for k in tree.query_ball_point(xy[v], max_distance):
            q = flagged[k]
            if q == v or q in adj[v]:
                continue
            d = xy[q] - xy[v]
            if float(d @ out) <= 0:
                continue
            cands.append((float(np.hypot(*d)), q))
        for _, q in sorted(cands):
            if not segment_in_band(band, xy[v], xy[q]):
                continue
            if _hops_within(adj, v, q, min_hops):
                continue
            added.append((min(v, q), max(v, q)))
            adj[v].add(q)
            adj[q].add(v)
            break
    return np.array(sorted(set(added)), dtype=np.int64).reshape(-1, 2)


def close_loop_caps(xy, width, edges, band, max_widths, min_hops):
    """Join two free ends of one chain that lie side by side in the ink (a narrow loop's cap).

    Where a stroke turns back on itself tightly — the round end of an eye drawn as a thin teardrop,
    the tip of a hairpin — the field's streamlines do not follow the turn, so the two sides are traced
    as chains that end next to each other with nothing across the cap.  Two leaves closer than
    ``max_widths`` times the larger of their widths (at least 2 px: the last cross-sections of a
    thin cap are narrower than the stroke), whose straight segment stays in the band and
    which are more than ``min_hops`` edges apart in the graph (connected far away: the loop's other
    end), are joined.  Each leaf is joined at most once, to its nearest such partner.

    Returns
    -------
    new_edges : numpy.ndarray
        (K, 2) the added edges (``edge_curve`` −1 in the artifact).
    """
    from scipy.spatial import cKDTree

    n = len(xy)
    leaves = np.flatnonzero(np.bincount(edges.ravel(), minlength=n) == 1)
    if len(leaves) < 2 or max_widths <= 0:
        return np.zeros((0, 2), np.int64)
    _, comp = components(n, edges)
    pairs = []
    for a, b in cKDTree(xy[leaves]).query_pairs(float(max_widths * max(width[leaves].max(), 2.0))):
        u, v = int(leaves[a]), int(leaves[b])
        d = float(np.hypot(*(xy[u] - xy[v])))
        # same chain only: two separate strokes touching end to end are left to the topology stage
        # (see trim_covered_ends for why joining those was dropped)
        if comp[u] == comp[v] and d <= max_widths * max(width[u], width[v], 2.0):
            pairs.append((d, u, v))
    if not pairs:
        return np.zeros((0, 2), np.int64)
    adj = adjacency(n, edges)
    added, used = [], set()
    for _, u, v in sorted(pairs):
        if u in used or v in used or not segment_in_band(band, xy[u], xy[v]) or _hops_within(adj, u, v, min_hops):
            continue
        added.append((min(u, v), max(u, v)))
        used.update((u, v))
    return np.array(sorted(added), dtype=np.int64).reshape(-1, 2)


def _hops_within(adj, a, b, hops):
    """Whether b is at most ``hops`` edges from a."""
    seen = {a}
    frontier = [a]
    for _ in range(hops):
        nxt = []
        for v in frontier:
            for u in adj[v]:
                if u == b:
                    return True
                if u not in seen:
                    seen.add(u)
                    nxt.append(u)
        frontier = nxt
    return False


def trim_hooked_tips(xy, width, edges, min_angle_deg):
    """Drop leaf vertices that hook sideways inside their neighbour's disc.

    At a stroke's rounded tip the field turns with the outline and the last, small cross-sections
    can land off the centre line.  A leaf ``v`` whose neighbour ``u`` continues a chain (degree 2,
    other neighbour ``p``) is removed when it lies inside ``u``'s disc (``|v − u| ≤ max(width_u/2,
    0.5)``, so no coverage is lost) and the step ``u → v`` turns by more than ``min_angle_deg`` from
    ``p → u``.  Repeated while it applies.  Not in the references.

    Returns
    -------
    edges : numpy.ndarray
        Remaining edges.
    removed : int
        Number of tips removed.
    """
    n = len(xy)
    adj = adjacency(n, edges)
    cos_max = np.cos(np.deg2rad(min_angle_deg))
    removed = 0
    todo = [v for v in range(n) if len(adj[v]) == 1]
    while todo:
        v = todo.pop()
        if len(adj[v]) != 1:
            continue
        u = next(iter(adj[v]))
        if len(adj[u]) != 2:
            continue
        p = next(q for q in adj[u] if q != v)
        a = xy[u] - xy[p]
        b = xy[v] - xy[u]
        nb = np.hypot(*b)
        na = np.hypot(*a)
        if nb > max(width[u] / 2, 0.5) or na == 0 or nb == 0:
            continue
        if float(a @ b) / (na * nb) >= cos_max:
            continue
        adj[v].discard(u)
        adj[u].discard(v)
        removed += 1
        todo.append(u)
    return edges_from_adjacency(adj), removed


def _cover_pairs(xy, width, labels, margin):
    """Pairs (u, v, distance) of vertices of different components with v inside u's disc.

    The disc radius is ``max(width/2, 0.5) + margin`` of the covering vertex u.
    """
    from scipy.spatial import cKDTree

    n = len(xy)
    radius = np.maximum(width / 2, 0.5) + margin
    near = cKDTree(xy).query_ball_point(xy, radius)
    lens = np.fromiter((len(q) for q in near), np.int64, count=n)
    if lens.sum() == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    v = np.concatenate([np.asarray(q, np.int64) for q in near])
    u = np.repeat(np.arange(n), lens)
    other = labels[u] != labels[v]
    u, v = u[other], v[other]
    return u, v, np.hypot(*(xy[u] - xy[v]).T)


def _cover_distance(n, pairs, ok):
    """Per vertex: distance to the nearest covering vertex among the pairs with ``ok`` (inf if none)."""
    u, v, d = pairs
    out = np.full(n, np.inf)
    np.minimum.at(out, v[ok], d[ok])
    return out


def trim_covered_ends(xy, width, edges, max_length, min_covered, margin):
    """Cut dangling ends and drop small components lying inside other components' strokes.

    Module docstring, step 6b.  Parameters as :func:`prune_covered_spurs`, plus ``margin`` (px)
    added to the disc radius ``max(width/2, 0.5)``.

    Returns
    -------
    edges : numpy.ndarray
        Remaining edges.
    trimmed : int
        Number of ends cut back plus components dropped.
    """
    n = len(xy)
    if n == 0 or len(edges) == 0:
        return edges, 0
    _, labels = components(n, edges)
    adj = adjacency(n, edges)
    has = np.array([len(a) > 0 for a in adj])
    # One neighbour query serves every cover test below; vertices left without edges by the earlier
    # steps (pruned spurs) cover nothing.
    pairs = _cover_pairs(xy, width, labels, margin)
    cover = _cover_distance(n, pairs, has[pairs[0]])
    covered = np.isfinite(cover)
    if not covered.any():
        return edges, 0
    trimmed = 0
    # Whole components that are thickness of a *longer* one (two short components crossing inside a
    # filled blob cover each other: only the shorter goes).
    seg = np.hypot(*(xy[edges[:, 0]] - xy[edges[:, 1]]).T)
    comp_len = np.bincount(labels[edges[:, 0]], weights=seg, minlength=labels.max() + 1)
    rank = np.empty(len(comp_len), np.int64)
    rank[np.lexsort((np.arange(len(comp_len)), comp_len))] = np.arange(len(comp_len))
    u, v, _ = pairs
    by_longer = np.isfinite(_cover_distance(n, pairs, has[u] & (rank[labels[u]] > rank[labels[v]])))
    n_all = np.bincount(labels[has], minlength=labels.max() + 1)
    n_cov = np.bincount(labels[has & by_longer], minlength=labels.max() + 1)
    drop = (comp_len <= max_length) & (n_all > 0) & (n_cov >= min_covered * n_all)
    for v in np.flatnonzero(drop[labels] & has):
        for u in list(adj[v]):
            adj[u].discard(v)
        adj[v].clear()
    trimmed += int(drop.sum())
    if drop.any():
        # what covers the ends is what remains
        has = np.array([len(a) > 0 for a in adj])
        cover = _cover_distance(n, pairs, has[pairs[0]])
        covered = np.isfinite(cover)
    # dangling runs inside another component's stroke: cut back to the vertex nearest to it
    for v in range(n):
        if len(adj[v]) != 1 or not covered[v]:
            continue
        run, length = [v], 0.0
        prev, cur = v, next(iter(adj[v]))
        while covered[cur] and len(adj[cur]) == 2:
            length += float(np.hypot(*(xy[cur] - xy[prev])))
            run.append(cur)
            prev, cur = cur, next(u for u in adj[cur] if u != prev)
        if length > max_length or len(run) < 2:
            continue
        keep = run[int(np.argmin(cover[run]))]
        if keep == v:
            continue
        k = run.index(keep)
        for a, b in zip(run[:k], run[1:k + 1]):
            adj[a].discard(b)
            adj[b].discard(a)
        trimmed += 1
    return edges_from_adjacency(adj), trimmed
