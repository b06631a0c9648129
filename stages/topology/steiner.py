"""Steiner tree approximations over the drawing graph (paper §4.2 "Finding connecting subgraphs").

Both are the classic 2-approximations, written on scipy's sparse graph routines (one multi-source
Dijkstra for Mehlhorn, one per terminal for Kou) so that a component of tens of thousands of vertices
costs milliseconds.  The steps follow networkx ``algorithms/approximation/steinertree.py``.

Why not networkx's own ``steiner_tree``: measured on the 586 Steiner problems of the 13 drawings of
``../shared/data/drawings`` (components of median 41, at most 5293 vertices;
``tests/benchmarks/steiner_vs_networkx.py``), it returns trees of the same weight but takes 5.2 s for
Mehlhorn (worst call 0.50 s) and 26.6 s for Kou (worst 12.5 s), plus 0.8 s to build the networkx
graphs, against 1.5 s and 1.4 s here (worst 29 ms and 73 ms).  So networkx is a test dependency
only (the tests compare these trees with its own).

References
----------
.. [1] L. Kou, G. Markowsky, L. Berman, "A fast algorithm for Steiner trees", Acta Informatica 15, 1981.
.. [2] K. Mehlhorn, "A faster approximation algorithm for the Steiner problem in graphs", Information
   Processing Letters 27(3), 1988.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra, minimum_spanning_tree


def path_to_source(pred: np.ndarray, v: int) -> list[int]:
    """Vertices from ``v`` back to its Dijkstra source along scipy's predecessor array."""
    out = [int(v)]
    while pred[out[-1]] >= 0:
        out.append(int(pred[out[-1]]))
    return out


def _mst_and_prune(csr: sp.csr_matrix, edges: set, terminals: np.ndarray) -> np.ndarray:
    """MST of the union of expanded paths, then iterative removal of non-terminal leaves."""
    if not edges:
        return np.zeros((0, 2), np.int64)
    e = np.array(sorted(edges), np.int64)
    w = np.asarray(csr[e[:, 0], e[:, 1]]).ravel()
    n = csr.shape[0]
    sub = sp.coo_matrix((w, (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    t = minimum_spanning_tree(sub).tocoo()
    e = np.sort(np.stack([t.row, t.col], 1).astype(np.int64), axis=1)
    is_term = np.zeros(n, bool)
    is_term[terminals] = True
    while len(e):
        deg = np.bincount(e.ravel(), minlength=n)
        leaf = (deg == 1) & ~is_term
        drop = leaf[e[:, 0]] | leaf[e[:, 1]]
        if not drop.any():
            break
        e = e[~drop]
    return e


def steiner_tree(csr: sp.csr_matrix, terminals: np.ndarray, method: str = "mehlhorn") -> np.ndarray:
    """Approximate minimum Steiner tree of a connected graph.

    Parameters
    ----------
    csr : scipy.sparse.csr_matrix
        Symmetric weighted adjacency (positive weights) of one connected component.
    terminals : numpy.ndarray
        Vertex indices to connect.
    method : {"mehlhorn", "kou"}

    Returns
    -------
    numpy.ndarray
        int64 (k, 2) tree edges ``u < v`` (empty for fewer than two terminals).
    """
    terminals = np.unique(np.asarray(terminals, np.int64))
    if len(terminals) < 2:
        return np.zeros((0, 2), np.int64)
    n = csr.shape[0]
    edges: set = set()

    def add_path(path):
        for u, v in zip(path[:-1], path[1:]):
            edges.add((min(u, v), max(u, v)))

    if method == "mehlhorn":
        # 1. Voronoi regions of the terminals (multi-source Dijkstra).
        dist, pred, src = dijkstra(csr, directed=True, indices=terminals, min_only=True,
                                   return_predecessors=True)
        # 2. Terminal graph over region-crossing edges, weight d(u) + w(u, v) + d(v).
        coo = sp.triu(csr, k=1).tocoo()
        u, v, w = coo.row.astype(np.int64), coo.col.astype(np.int64), coo.data
        su, sv = src[u], src[v]
        ok = (su >= 0) & (sv >= 0) & (su != sv)
        u, v, su, sv = u[ok], v[ok], su[ok], sv[ok]
        cost = dist[u] + w[ok] + dist[v]
        pos = np.full(n, -1, np.int64)
        pos[terminals] = np.arange(len(terminals))
        ta, tb = np.minimum(pos[su], pos[sv]), np.maximum(pos[su], pos[sv])
        order = np.lexsort((cost, tb, ta))
        ta, tb, u, v, cost = ta[order], tb[order], u[order], v[order], cost[order]
        first = np.ones(len(ta), bool)
        first[1:] = (ta[1:] != ta[:-1]) | (tb[1:] != tb[:-1])
        ta, tb, u, v, cost = ta[first], tb[first], u[first], v[first], cost[first]
        k = len(terminals)
        # 3. Its minimum spanning tree (Kruskal in the paper; any MST is the same tree up to ties).
        tg = sp.coo_matrix((cost, (ta, tb)), shape=(k, k)).tocsr()
        mst = minimum_spanning_tree(tg).tocoo()
        lookup = {(int(a), int(b)): i for i, (a, b) in enumerate(zip(ta, tb))}
        # 4. Expansion back into graph edges.
        for a, b in zip(mst.row, mst.col):
            i = lookup[(min(a, b), max(a, b))]
            add_path(path_to_source(pred, int(u[i]))[::-1] + path_to_source(pred, int(v[i])))
    elif method == "kou":
        dist, pred = dijkstra(csr, directed=True, indices=terminals, return_predecessors=True)
        closure = dist[:, terminals]
        closure[~np.isfinite(closure)] = 0
        mst = minimum_spanning_tree(sp.csr_matrix(np.triu(closure, 1))).tocoo()
        for a, b in zip(mst.row, mst.col):
            add_path(path_to_source(pred[a], int(terminals[b])))
    else:
        raise ValueError(f"unknown Steiner method {method!r}")
    return _mst_and_prune(csr, edges, terminals)
