"""Constrained shortest paths for covering the drawing (paper §4.2, AliAbdi et al. 2019 in the paper).

Problem: among walks over the graph between two terminals (key vertices), find the cheapest one that
visits at least ``need`` vertices not yet covered by the subgraph.

The authors run a label-setting search from every terminal, keeping Pareto labels (cost, #uncovered)
that carry their whole path, with a linear-scan queue; it is their bottleneck and gives up above 200
terminals (their issue #10 crashes on big components).  Here the resource is capped at ``need`` (only
"at least ``need``" matters), which turns the problem into an ordinary Dijkstra over the product
states (directed edge, min(#uncovered, need)):

* **one** multi-source search from all terminals at once answers "cheapest terminal-to-terminal walk
  with ≥ need uncovered vertices" — cost O(A·(need+1)·log) for A arcs, independent of the number of
  terminals;
* states are *arcs* rather than vertices so that (a) walks never reverse along an edge (a walk cannot
  pad its count by running into a dead-end spur and back), and (b) the Y-junction turn test, which
  depends on the incoming and outgoing arc, is a transition rule of the search.

What is given up: simple-path-ness.  A walk may still pass a vertex twice around a cycle; callers
therefore re-count *distinct* uncovered vertices of the returned walk and treat a short count as a
failure (see ``stages.topology.__init__``).  For the stage this is harmless: a found walk only
contributes its edges to the covering subgraph, and allowed paths are enumerated on that subgraph
afterwards.
"""

from __future__ import annotations

import heapq

import numpy as np
from numba import njit


@njit(cache=True)
def _search(indptr, indices, arc_w, arc_rev, turn_ptr, turn_ok, v0, v1, uncovered, is_source,
            is_target, need):
    """Multi-source Dijkstra over (arc, capped count) states of the vertex range [v0, v1).

    Returns the arcs of the cheapest walk (empty if none) as global arc ids.
    """
    a0 = indptr[v0]
    na = indptr[v1] - a0
    k1 = need + 1
    dist = np.full(na * k1, np.inf)
    pred = np.full(na * k1, -1, np.int64)
    heap = [(0.0, np.int64(0))]
    heap.pop()
    for s in range(v0, v1):
        if not is_source[s]:
            continue
        for a in range(indptr[s], indptr[s + 1]):
            k = min(need, uncovered[s] + uncovered[indices[a]])
            st = (a - a0) * k1 + k
            c = arc_w[a]
            if c < dist[st]:
                dist[st] = c
                pred[st] = -1
                heapq.heappush(heap, (c, np.int64(st)))
    best = np.int64(-1)
    while len(heap) > 0:
        c, st = heapq.heappop(heap)
        if c > dist[st]:
            continue
        a = st // k1 + a0
        k = st % k1
        v = indices[a]
        if k == need and is_target[v]:       # §4.2: a walk to a key vertex visiting ≥ N uncovered vertices
            best = st
            break
        rev = arc_rev[a]
        tp = turn_ptr[a]
        for j in range(indptr[v + 1] - indptr[v]):
            b = indptr[v] + j
            if b == rev or not turn_ok[tp + j]:   # no reversal; §4.3 Fig. 10: only allowed turns at a Y
                continue
            k2 = min(need, k + uncovered[indices[b]])
            s2 = (b - a0) * k1 + k2
            c2 = c + arc_w[b]
            if c2 < dist[s2]:
                dist[s2] = c2
                pred[s2] = st
                heapq.heappush(heap, (c2, s2))
    if best < 0:
        return np.zeros(0, np.int64)
    n = 0
    st = best
    while st >= 0:
        n += 1
        st = pred[st]
    out = np.empty(n, np.int64)
    st = best
    for i in range(n - 1, -1, -1):
        out[i] = st // k1 + a0
        st = pred[st]
    return out


def constrained_walk(g, arc_w, turn_ptr, turn_ok, comp: int, uncovered: np.ndarray,
                     sources: np.ndarray, targets: np.ndarray, need: int):
    """Cheapest walk from a source to a target visiting ≥ ``need`` uncovered vertices.

    Parameters
    ----------
    g : stages.topology.work_graph.WorkGraph
    arc_w : numpy.ndarray
        float64 (A,) arc costs (Euclidean lengths).
    turn_ptr, turn_ok : numpy.ndarray
        The Y-junction turn table (:func:`stages.topology.work_graph.turn_table`).
    comp : int
        Component to search (its vertex range).
    uncovered : numpy.ndarray
        bool (V,) vertices that count.
    sources, targets : numpy.ndarray
        bool (V,) allowed first / last vertices.
    need : int
        Required count (visits, capped), ≥ 1.

    Returns
    -------
    vertices, arcs : numpy.ndarray or None
        The walk's vertex sequence and arc ids, or ``None`` when no walk qualifies.
    """
    v0, v1 = int(g.comp_ptr[comp]), int(g.comp_ptr[comp + 1])
    arcs = _search(g.indptr, g.indices, arc_w, g.arc_rev, turn_ptr, turn_ok, v0, v1,
                   uncovered.astype(np.int64), sources, targets, int(need))
    if len(arcs) == 0:
        return None
    tails = np.searchsorted(g.indptr, arcs, side="right") - 1
    return np.concatenate([tails[:1], g.indices[arcs]]), arcs
