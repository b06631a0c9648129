"""Clean-up of the cross-section graph and width smoothing (authors-implementation.md §4; B19 §A.3).

Steps, in the order :func:`stages.graph.run` applies them:

1. :func:`merge_close_vertices` — near-duplicate cross-sections.  Stations are placed per streamline
   (:mod:`stages.graph.cross_section`), so where lanes start or end mid-stroke two cross-sections can
   land a fraction of a pixel apart along the same bundle; joined by their shared streamlines they make
   small triangles and ladders.  Adjacent vertices of the same root family closer than
   ``merge_distance`` are merged (greedily, largest cross-section first, one level deep so chains do
   not collapse transitively); the merged vertex keeps the larger cross-section's position, width and
   root and the union of the members, and edges are rebuilt from the streamlines.  Not in the
   reference, whose vertices sit only at streamline ends.
2. :func:`remove_singular_branches` — ``contractSingularityBranches``: on a dangling chain (free end at
   one side, a junction at the other) edges are deleted from the free end while the vertex there is
   flagged *next to singularity*; the vertex left at the cut gets the flag.
3. :func:`remove_small_components` — ``simpleThresholds``: a component goes if its bounding box,
   padded by each vertex's half width (at least 0.5 px), is smaller than ``min_component_area`` px².
   The reference pads nothing, which drops long axis-aligned strokes whose box has zero area; it
   also drops every component in which no vertex crosses more than one streamline, which we do not:
   a one-pixel-wide axis-aligned stroke has exactly one lane, and specks are small anyway.
4. :func:`contract_thickness_loops` — ``contractLoops``: the shortest cycle through every edge not in
   a BFS spanning forest is drawn as a polygon through its vertices; if it encloses at most
   ``max_loop_background`` background pixels (pixel centres off the band) it is a thickness loop, not a
   hole, and is contracted: of its edges only the paths (around the cycle, the shorter way) from its
   *anchors* (vertices with edges off the cycle) to the cycle vertex nearest its centroid are kept.
   Repeated until no cycle is contracted.  Real holes (the inside of an O) enclose many background
   pixels and stay.
5. :func:`prune_covered_spurs` — B19's ``removeBranchesFilter1`` (not in the authors' code): short
   dangling branches lying inside the stroke discs of the rest of the graph go, one per junction per
   round.  This is what leaves a straight stroke's ragged tip as a path end instead of a fork.
6. :func:`trim_hooked_tips` — leaves that hook sideways inside their neighbour's disc (rounded tips).
6b. :func:`trim_covered_ends` (run after step 7, so that the pieces of a Y are joined first) — ink
   of *another* stroke is not a stroke end (not in the references).
   Where one stroke meets another (a T), the field inside the bar is a cross whose normal root
   continues the stem, so the stem's streamlines run on across the bar to its far edge: the stem's
   chain overshoots the junction by the bar's half width and ends on the far side (synthetic T,
   width 3–5: 1.5–2.8 px beyond the bar's centre line).  Likewise a stroke's rounded tip often traces
   as a separate tiny component lying inside the stroke's own discs.  On realvec_dev such ends were
   the largest group of spurious junctions with no ground-truth counterpart (a stem end sticking out
   of the bar, a stroke split at a synthetic end next to its endpoint).  So: a dangling run of
   vertices that all lie inside the discs (radius ``max(width/2, 0.5) + cover_margin``) of vertices
   of *other* components is cut back to its vertex nearest those vertices (a stem then ends on the
   bar's centre line), if the run is at most ``spur_max_length`` long (longer runs are overlapping
   strokes, left alone); a whole component of at most that length with at least ``spur_min_covered``
   of its vertices so covered by *longer* components is thickness of the other stroke and goes (two
   short components crossing inside a filled blob cover each other; only the shorter goes —
   deleting both cost a filled eye of cr_test_199_pencil its only curves, Hausdorff 7 → 11 px).
   Tried and dropped: joining two components whose tips lie in each other's strokes (an L traced
   as two families) instead of cutting both — junction F1 0.857 → 0.853, dangling 0.54 → 0.53,
   Hausdorff unchanged; and cutting only inside the other stroke's *interior* (covering vertices farther
   than their width from its tips, to spare vee tips traced as two components) — realvec_dev
   junction F1 0.857 → 0.845 with no Hausdorff gain.  Known cost: where the arms of a sharp corner
   or vee were traced as two components, the cut can take the tip (cr_test_228_clean, lion_01_pencil:
   Hausdorff 3.6 → 6.7 and 4.0 → 5.7 px).
7. :func:`join_singular_ends` — B19's ``connectStuffAroundSingularities`` (not in the authors' code):
   traces stop at the singularity of a Y junction; joining the dangling end there to the other
   branches gives the Y its valence-3 vertex (edges with ``edge_curve`` −1).
7b. :func:`close_loop_caps` (not in the references) — where a stroke turns back tightly (an eye drawn
   as a thin teardrop), the streamlines do not follow the cap, and the loop's two sides end as leaves
   side by side; two leaves of one component, within ``close_caps_widths`` widths (at least 2 px) of
   each other across ink and more than ``close_caps_min_hops`` edges apart, are joined, so the loop
   is closed.  On realvec_dev (detector keypoints) it changed 8 of 106 drawings: endpoint F1 mean
   0.8597 → 0.8608 (false endpoints 174 → 171), junction F1 mean 0.7117 → 0.7114 (false junctions
   296 → 299), medians and Hausdorff unchanged; kept because the eyes come out as closed curves.
   It runs on the narrow band, so it needs prep's paper-aware hole repair: with the plain repair
   the slit of such loops was filled and there was no loop to close.
8. :func:`smooth_widths` — the reference's width QP (Laplacian equations + data equations, weight 1)
   solved as one sparse linear solve ``(λ² LᵀL + I) w = w_raw`` and clipped to the raw range (instead
   of Gurobi with ±max bounds).  ``(I + λ² L²)⁻¹`` is not entry-wise positive, so the solution could in
   principle overshoot the raw range at a spike; the clip is that safeguard (on the scanned drawings
   it never binds: the solution stays 0.16 px above the smallest and 0.76 px below the largest raw
   width on kitten).

Steps 2–7 only delete or add edges; vertices left without edges are dropped at the end, and the
component filter runs again after the joins.
"""

from __future__ import annotations

from collections import deque

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla



def _adjacency(n: int, edges: np.ndarray) -> list[set]:
    adj = [set() for _ in range(n)]
    for a, b in edges:
        adj[a].add(b)
        adj[b].add(a)
    return adj


def _components(n: int, edges: np.ndarray) -> tuple[int, np.ndarray]:
    """Number of connected components of the graph and each vertex's component label."""
    g = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return csgraph.connected_components(g, directed=False)


def _edges_from_adj(adj: list[set]) -> np.ndarray:
    out = [(a, b) for a, nb in enumerate(adj) for b in nb if a < b]
    return np.array(out, dtype=np.int64).reshape(-1, 2)


def merge_close_vertices(xy, root, member_vertex, member_curve, member_param, edges, distance, min_cos):
    """Merge adjacent near-duplicate vertices (see module docstring, step 1).

    Parameters
    ----------
    xy : numpy.ndarray
        (V, 2) vertex positions.
    root : numpy.ndarray
        complex (V,) unit roots.
    member_vertex, member_curve, member_param : numpy.ndarray
        Crossings of every vertex.
    edges : numpy.ndarray
        (E, 2) streamline edges.
    distance : float
        Adjacent vertices closer than this (px) are merged.
    min_cos : float
        ... if their roots agree, ``|cos| ≥ min_cos``.

    Returns
    -------
    keep : numpy.ndarray
        int64 (V',) ids of the surviving vertices (into the input arrays).
    member_vertex : numpy.ndarray
        Crossings re-assigned to the new vertex ids ``0..V'-1``.
    """
    n = len(xy)
    counts = np.bincount(member_vertex, minlength=n)
    if len(edges):
        d = np.linalg.norm(xy[edges[:, 0]] - xy[edges[:, 1]], axis=1)
        c = np.abs((root[edges[:, 0]] * np.conj(root[edges[:, 1]])).real)
        close = edges[(d < distance) & (c >= min_cos)]
    else:
        close = np.zeros((0, 2), np.int64)
    adj = _adjacency(n, close)
    rep = np.full(n, -1, np.int64)
    for v in np.argsort(-counts, kind="stable"):
        if rep[v] >= 0:
            continue
        rep[v] = v
        for u in adj[v]:
            if rep[u] < 0:
                rep[u] = v
    keep = np.unique(rep)
    new_id = np.full(n, -1, np.int64)
    new_id[keep] = np.arange(len(keep))
    return keep, new_id[rep[member_vertex]]


def remove_singular_branches(n: int, edges: np.ndarray, flags: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Trim dangling chains that run into a singularity (module docstring, step 2).

    Returns
    -------
    edges : numpy.ndarray
        The remaining edges.
    flags : numpy.ndarray
        Updated flags (bit 0 set on the vertex left at each cut).
    removed : int
        Number of edges deleted.
    """
    adj = _adjacency(n, edges)
    flags = flags.copy()
    near = (flags & 1).astype(bool)
    removed = 0
    for v0 in range(n):
        if len(adj[v0]) != 1 or not near[v0]:
            continue
        # the chain must hang off a junction
        prev, cur = v0, next(iter(adj[v0]))
        while len(adj[cur]) == 2:
            prev, cur = cur, next(u for u in adj[cur] if u != prev)
            if cur == v0:
                break
        if len(adj[cur]) < 3:
            continue
        cur = v0
        while near[cur] and len(adj[cur]) == 1:
            u = next(iter(adj[cur]))
            if len(adj[u]) > 2:
                break  # never cut into the junction itself
            adj[cur].discard(u)
            adj[u].discard(cur)
            removed += 1
            cur = u
        flags[cur] |= 1
    return _edges_from_adj(adj), flags, removed


def remove_small_components(xy, width, edges, min_area) -> np.ndarray:
    """Vertices to keep after dropping insignificant components (module docstring, step 3).

    Parameters
    ----------
    xy, width : numpy.ndarray
        Vertex positions and widths.
    edges : numpy.ndarray
        (E, 2).
    min_area : float
        Components whose padded bounding box is smaller (px²) are dropped.

    Returns
    -------
    numpy.ndarray
        bool (V,) mask of the vertices to keep.
    """
    n = len(xy)
    if n == 0:
        return np.zeros(0, bool)
    ncomp, lab = _components(n, edges)
    r = np.maximum(width / 2, 0.5)
    lo_x = np.full(ncomp, np.inf); hi_x = np.full(ncomp, -np.inf)
    lo_y = np.full(ncomp, np.inf); hi_y = np.full(ncomp, -np.inf)
    np.minimum.at(lo_x, lab, xy[:, 0] - r); np.maximum.at(hi_x, lab, xy[:, 0] + r)
    np.minimum.at(lo_y, lab, xy[:, 1] - r); np.maximum.at(hi_y, lab, xy[:, 1] + r)
    area = (hi_x - lo_x) * (hi_y - lo_y)
    return (area >= min_area)[lab]


def _shortest_cycle_path(adj, a, b, limit):
    """BFS path a → b avoiding the edge (a, b), at most ``limit`` vertices; None if none."""
    parent = {a: -1}
    q = deque([a])
    while q:
        v = q.popleft()
        for u in adj[v]:
            if u in parent or (v == a and u == b):
                continue
            parent[u] = v
            if u == b:
                path = [b]
                while path[-1] != a:
                    path.append(parent[path[-1]])
                return path[::-1]
            q.append(u)
        if len(parent) > limit:
            return None
    return None


def _background_inside(poly_xy: np.ndarray, band: np.ndarray) -> int:
    from skimage.draw import polygon

    # skimage puts pixel centres at integer coordinates, ours at +0.5
    rr, cc = polygon(poly_xy[:, 1] - 0.5, poly_xy[:, 0] - 0.5, shape=band.shape)
    return int((~band[rr, cc]).sum())


def contract_thickness_loops(xy, edges, band, max_background, max_cycle_vertices, max_searches=None):
    """Contract cycles enclosing at most ``max_background`` background pixels (module docstring, step 4).

    Parameters
    ----------
    xy : numpy.ndarray
        (V, 2) vertex positions.
    edges : numpy.ndarray
        (E, 2).
    band : numpy.ndarray
        bool (H, W) the narrow band.
    max_background : int
        Largest number of enclosed background pixels of a contractible loop (reference 4).
    max_cycle_vertices : int
        Cycles are searched by BFS up to this many visited vertices (bounds the cost on huge rings,
        which are real holes anyway).
    max_searches : int, optional
        Guard on the number of cycle searches in all (each one a BFS of at most
        ``max_cycle_vertices``): a graph of many tiny loops (a scribbled blob) is left with the loops
        not reached.  None = no limit.

    Returns
    -------
    edges : numpy.ndarray
        The remaining edges.
    contracted : int
        Number of loops contracted.
    cut : bool
        Whether ``max_searches`` stopped the contraction with edges left to search.
    """
    n = len(xy)
    adj = _adjacency(n, edges)
    contracted = 0
    # enclosed background of a cycle does not change once computed; remember the holes
    holes = set()
    while True:
        changed = False
        # non-tree edges of a BFS spanning forest, each closing one fundamental cycle
        seen = np.zeros(n, bool)
        tree = set()
        for s in range(n):
            if seen[s] or not adj[s]:
                continue
            seen[s] = True
            q = deque([s])
            while q:
                v = q.popleft()
                for u in adj[v]:
                    if not seen[u]:
                        seen[u] = True
                        tree.add((min(u, v), max(u, v)))
                        q.append(u)
        extra = [(a, b) for a, nb in enumerate(adj) for b in nb if a < b and (a, b) not in tree]
        for a, b in extra:
            if b not in adj[a]:
                continue
            if max_searches is not None:
                if max_searches <= 0:
                    return _edges_from_adj(adj), contracted, True
                max_searches -= 1
            path = _shortest_cycle_path(adj, a, b, max_cycle_vertices)
            if path is None:
                continue
            key = frozenset(path)
            if key in holes:
                continue
            if _background_inside(xy[path], band) > max_background:
                holes.add(key)
                continue
            _contract(adj, xy, path)
            contracted += 1
            changed = True
        if not changed:
            break
    return _edges_from_adj(adj), contracted, False


def _contract(adj, xy, cycle):
    """Keep only the paths from the cycle's anchors to its most central vertex (reference ``contract_edges``)."""
    m = len(cycle)
    on = set(cycle)
    cyc_edges = [(cycle[k], cycle[(k + 1) % m]) for k in range(m)]
    anchors = [k for k, v in enumerate(cycle) if any(u not in on for u in adj[v])]
    centre = int(np.argmin(np.linalg.norm(xy[cycle] - xy[cycle].mean(axis=0), axis=1)))
    seg = np.linalg.norm(xy[[e[0] for e in cyc_edges]] - xy[[e[1] for e in cyc_edges]], axis=1)
    keep = np.zeros(m, bool)  # keep[k]: edge cycle[k] — cycle[k+1]
    if not anchors:
        # an isolated small loop: open it opposite its centre, leaving a path
        keep[:] = True
        keep[(centre + m // 2) % m] = False
    for k in anchors:
        fwd = [(k + t) % m for t in range((centre - k) % m)]          # edges k → centre going forward
        bwd = [(centre + t) % m for t in range((k - centre) % m)]     # edges centre → k going forward
        if seg[fwd].sum() <= seg[bwd].sum():
            keep[fwd] = True
        else:
            keep[bwd] = True
    for k, (a, b) in enumerate(cyc_edges):
        if not keep[k]:
            adj[a].discard(b)
            adj[b].discard(a)


def smooth_widths(width_raw: np.ndarray, edges: np.ndarray, weight: float) -> np.ndarray:
    """Laplacian least-squares smoothing of the widths (module docstring, step 5).

    Minimises ``weight² ‖L w‖² + ‖w − width_raw‖²`` with ``L`` the graph Laplacian.

    Parameters
    ----------
    width_raw : numpy.ndarray
        (V,) raw cross-section widths.
    edges : numpy.ndarray
        (E, 2).
    weight : float
        Weight of the Laplacian equations relative to the data equations (reference 1).

    Returns
    -------
    numpy.ndarray
        (V,) smoothed widths, within the range of ``width_raw``.
    """
    n = len(width_raw)
    if n == 0:
        return width_raw.copy()
    adj = sp.coo_matrix((np.ones(2 * len(edges)), (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])),
                        shape=(n, n)).tocsr()
    adj.data[:] = 1.0
    lap = sp.diags(np.asarray(adj.sum(axis=1)).ravel()) - adj
    a = (weight ** 2) * (lap.T @ lap) + sp.identity(n)
    w = spla.spsolve(a.tocsc(), width_raw.astype(np.float64))
    return np.clip(w, width_raw.min(), width_raw.max())


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
    adj = _adjacency(n, edges)
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
    return _edges_from_adj(adj), removed


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
    from scipy.ndimage import distance_transform_edt
    from scipy.spatial import cKDTree

    if singular.any():
        dist = distance_transform_edt(~singular)
        i = np.clip(np.floor(xy[:, 1]).astype(int), 0, band.shape[0] - 1)
        j = np.clip(np.floor(xy[:, 0]).astype(int), 0, band.shape[1] - 1)
        near = (flags & 1).astype(bool) | (dist[i, j] <= width / 2 + 1)
    else:
        near = (flags & 1).astype(bool)
    n = len(xy)
    adj = _adjacency(n, edges)
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
            if not _segment_in_band(xy[v], xy[q], band):
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
    _, comp = _components(n, edges)
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
    adj = _adjacency(n, edges)
    added, used = [], set()
    for _, u, v in sorted(pairs):
        if u in used or v in used or not _segment_in_band(xy[u], xy[v], band) or _hops_within(adj, u, v, min_hops):
            continue
        added.append((min(u, v), max(u, v)))
        used.update((u, v))
    return np.array(sorted(added), dtype=np.int64).reshape(-1, 2)


def _segment_in_band(a, b, band):
    k = max(2, int(np.ceil(np.hypot(*(b - a)) / 0.25)) + 1)
    t = np.linspace(0, 1, k)[:, None]
    p = a + t * (b - a)
    i = np.floor(p[:, 1]).astype(int)
    j = np.floor(p[:, 0]).astype(int)
    h, w = band.shape
    if (i < 0).any() or (j < 0).any() or (i >= h).any() or (j >= w).any():
        return False
    return bool(band[i, j].all())


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
    adj = _adjacency(n, edges)
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
    return _edges_from_adj(adj), removed


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
    _, labels = _components(n, edges)
    adj = _adjacency(n, edges)
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
    return _edges_from_adj(adj), trimmed
