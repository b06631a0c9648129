"""Clean-up of the cross-section graph and width smoothing (authors-implementation.md §4; B19 §A.3).

Steps, in the order :func:`stages.graph.run` applies them (steps 5–7b, on the graph's ends, are in
:mod:`stages.graph.ends`; measurements in stages/DECISIONS.md):

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
5.–7b. The graph's ends (:mod:`stages.graph.ends`): covered spurs, hooked tips, ends inside another
   stroke, joins at singularities, narrow loop caps.
8. :func:`smooth_widths` — the reference's width QP (Laplacian equations + data equations, weight 1)
   solved as one sparse linear solve ``(λ² LᵀL + I) w = w_raw`` and clipped to the raw range (instead
   of Gurobi with ±max bounds).  ``(I + λ² L²)⁻¹`` is not entry-wise positive, so the solution could in
   principle overshoot the raw range at a spike; the clip is that safeguard.

Steps 2–7 only delete or add edges; vertices left without edges are dropped at the end, and the
component filter runs again after the joins.
"""

from __future__ import annotations

from collections import deque
from itertools import chain

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla

from stages.arrays import sorted_unique


def adjacency(n: int, edges: np.ndarray) -> list[set]:
    """Neighbour sets of the ``n`` vertices of an undirected edge list."""
    adj = [set() for _ in range(n)]
    # plain ints (tolist) instead of numpy scalars: 3x faster, same insertion order, so the sets
    # iterate in the same order
    for a, b in np.asarray(edges).reshape(-1, 2).tolist():
        adj[a].add(b)
        adj[b].add(a)
    return adj


def components(n: int, edges: np.ndarray) -> tuple[int, np.ndarray]:
    """Number of connected components of the graph and each vertex's component label."""
    g = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return csgraph.connected_components(g, directed=False)


def edges_from_adjacency(adj: list[set]) -> np.ndarray:
    """The ``(a, b)``, ``a < b`` edges of neighbour sets, by ``a`` then in set order."""
    deg = np.fromiter(map(len, adj), np.int64, len(adj))
    b = np.fromiter(chain.from_iterable(adj), np.int64, int(deg.sum()))
    a = np.repeat(np.arange(len(adj), dtype=np.int64), deg)
    keep = a < b
    return np.stack([a[keep], b[keep]], axis=1)


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
    adj = adjacency(n, close)
    rep = np.full(n, -1, np.int64)
    for v in np.argsort(-counts, kind="stable").tolist():
        if rep[v] >= 0:
            continue
        rep[v] = v
        for u in adj[v]:
            if rep[u] < 0:
                rep[u] = v
    keep = sorted_unique(rep)
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
    adj = adjacency(n, edges)
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
    return edges_from_adjacency(adj), flags, removed


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
    ncomp, lab = components(n, edges)
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
    adj = adjacency(n, edges)
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
                    return edges_from_adjacency(adj), contracted, True
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
    return edges_from_adjacency(adj), contracted, False


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
