"""The drawing graph as the topology stage works on it.

Vertices are relabelled so that every connected component is a contiguous range ``[v0, v1)``; the
symmetric adjacency is stored as *arcs* (directed edges) in CSR order, so a component's arcs are the
contiguous range ``[indptr[v0], indptr[v1])`` too.  Every search of the stage then runs on slices of
the same flat arrays, without building per-component graphs.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from stages.errors import InputError


@dataclass
class WorkGraph:
    """Component-contiguous drawing graph.

    Attributes
    ----------
    xy : numpy.ndarray
        float64 (V, 2) vertex positions (x, y); key vertices are moved onto their keypoints.
    width : numpy.ndarray
        float64 (V,) stroke width at each vertex (px).
    root : numpy.ndarray
        complex128 (V,) unit frame-field root the vertex's cross-section followed (0 if unknown).
    near_singularity : numpy.ndarray
        bool (V,) the graph's ``vertex_flags`` bit 0 (cross-section next to a singularity).
    orig : numpy.ndarray
        int64 (V,) vertex id in the graph artifact.
    comp_ptr : numpy.ndarray
        int64 (C + 1,): component ``c`` is vertices ``comp_ptr[c]:comp_ptr[c + 1]``.
    edges : numpy.ndarray
        int64 (E, 2), ``u < v``, relabelled; no self loops or duplicates.
    indptr, indices, arc_edge, arc_rev : numpy.ndarray
        CSR of the arcs: arc ``a`` goes from the vertex whose row holds it to ``indices[a]``; it is
        edge ``arc_edge[a]``; ``arc_rev[a]`` is the opposite arc.
    """

    xy: np.ndarray
    width: np.ndarray
    root: np.ndarray
    near_singularity: np.ndarray
    orig: np.ndarray
    comp_ptr: np.ndarray
    edges: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    arc_edge: np.ndarray
    arc_rev: np.ndarray

    @property
    def n_vertices(self) -> int:
        return len(self.xy)

    @cached_property
    def degree(self) -> np.ndarray:
        """int64 (V,) graph valence; computed once (the key vertices ask for it per keypoint, the
        enumeration per component: recomputed, it cost O(V) each time, O(V²) on a page)."""
        return np.diff(self.indptr)

    def arc_tail(self) -> np.ndarray:
        """int64 (A,) tail vertex of every arc."""
        return np.repeat(np.arange(self.n_vertices), self.degree)

    def arc_length(self) -> np.ndarray:
        """float64 (A,) Euclidean arc lengths at the current positions (+1e-9, like the authors)."""
        tail = self.arc_tail()
        return np.hypot(*(self.xy[self.indices] - self.xy[tail]).T) + 1e-9

    def csr(self, weights: np.ndarray | None = None) -> sp.csr_matrix:
        """Symmetric sparse adjacency with arc weights (default: lengths)."""
        w = self.arc_length() if weights is None else weights
        n = self.n_vertices
        return sp.csr_matrix((w, self.indices, self.indptr), shape=(n, n))


def build_work_graph(vertex_xy, vertex_width, vertex_root, edges, vertex_flags=None) -> WorkGraph:
    """Validate the graph artifact's arrays and build the component-contiguous :class:`WorkGraph`.

    Raises
    ------
    InputError
        On inconsistent lengths or edge indices out of range.
    """
    xy = np.asarray(vertex_xy, np.float64).reshape(-1, 2)
    n = len(xy)
    width = np.asarray(vertex_width, np.float64).reshape(-1)
    root = np.asarray(vertex_root).astype(np.complex128).reshape(-1)
    e = np.asarray(edges, np.int64).reshape(-1, 2)
    flags = np.zeros(n, np.uint8) if vertex_flags is None else np.asarray(vertex_flags).reshape(-1)
    if len(width) != n or len(root) != n or len(flags) != n:
        raise InputError(f"topology: graph has {n} vertices but {len(width)} widths, {len(root)} roots "
                         f"and {len(flags)} flags")
    if e.size and (e.min() < 0 or e.max() >= n):
        raise InputError("topology: graph edges reference vertices that do not exist")
    if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(width))):
        raise InputError("topology: graph vertex positions or widths are not finite")
    width = np.maximum(width, 0.0)
    mod = np.abs(root)
    root = np.where(mod > 1e-9, root / np.where(mod > 1e-9, mod, 1), 0)

    e = np.sort(e, axis=1)
    e = e[e[:, 0] != e[:, 1]]
    e = np.unique(e, axis=0) if len(e) else e
    adj = sp.csr_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    n_comp, labels = connected_components(adj, directed=False)
    perm = np.argsort(labels, kind="stable")          # new -> old
    inv = np.empty(n, np.int64)
    inv[perm] = np.arange(n)                          # old -> new
    comp_ptr = np.zeros(n_comp + 1, np.int64)
    np.cumsum(np.bincount(labels, minlength=n_comp), out=comp_ptr[1:])

    e = np.sort(inv[e], axis=1)
    order = np.lexsort((e[:, 1], e[:, 0]))
    e = e[order]
    m = len(e)
    tails = np.concatenate([e[:, 0], e[:, 1]])
    heads = np.concatenate([e[:, 1], e[:, 0]])
    eids = np.concatenate([np.arange(m), np.arange(m)])
    order = np.lexsort((heads, tails))
    tails, heads, eids = tails[order], heads[order], eids[order]
    indptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(tails, minlength=n), out=indptr[1:])
    # Arcs are sorted by (tail, head), so the opposite of (t, h) is found by binary search.
    key = tails * n + heads
    arc_rev = np.searchsorted(key, heads * n + tails)
    return WorkGraph(xy=xy[perm].copy(), width=width[perm], root=root[perm],
                     near_singularity=(flags[perm].astype(np.int64) & 1).astype(bool), orig=perm.astype(np.int64),
                     comp_ptr=comp_ptr, edges=e, indptr=indptr, indices=heads.astype(np.int64),
                     arc_edge=eids.astype(np.int64), arc_rev=arc_rev.astype(np.int64))


# ---------------------------------------------------------------------------------------------
# Y-junction turn test (paper §4.3, Fig. 10)
# ---------------------------------------------------------------------------------------------

def _motion(root_a: complex, root_b: complex, delta: complex) -> complex:
    """Motion along the traced curves for a step ``delta``: its projection on the two root lines."""
    m = 0j
    for r in (root_a, root_b):
        m += delta if r == 0 else r * (np.conj(r) * delta).real
    return 0.5 * m


def arc_motions(g: WorkGraph, probe_px: float, probe_max_px: float | None = None) -> np.ndarray:
    """Motion towards the head of every arc whose head has valence ≥ 3.

    For arc ``x → v`` the motion is summed over the steps walking from ``x`` back along the chain of
    valence-2 vertices, each step's displacement projected on the root lines of its two vertices, all
    oriented towards ``v``, until the walk has slid ``probe_px`` along the traced curves (the sum of
    the steps' projected lengths) or covered ``probe_max_px`` of arc length (at least one step).
    ``probe_max_px`` = None or ≤ ``probe_px`` stops at ``probe_px`` of arc length instead.  Steps
    *across* the traced curves (edges the graph added between two strokes of a merged band) project
    to nearly nothing: counting them as probe length left a Y reached over such an edge with no
    motion, and so with every turn allowed.
    Projecting on the roots measures the sliding over the traced curves rather than raw vertex jitter,
    and probing a few pixels away from ``v`` avoids the unreliable cross-sections right at a
    junction.

    Returns
    -------
    numpy.ndarray
        complex128 (A,), 0 for arcs into vertices of valence < 3.
    """
    deg = g.degree
    out = np.zeros(len(g.indices), np.complex128)
    z = g.xy[:, 0] + 1j * g.xy[:, 1]
    extend = probe_max_px is not None and probe_max_px > probe_px
    max_len = probe_max_px if extend else np.inf
    for v in np.nonzero(deg >= 3)[0]:
        for a_out in range(g.indptr[v], g.indptr[v + 1]):
            a = g.arc_rev[a_out]                      # the arc x -> v
            prev, cur = v, g.indices[a_out]
            m, length, slid = 0j, 0.0, 0.0
            while True:
                d = z[prev] - z[cur]
                step = _motion(g.root[cur], g.root[prev], d)
                m += step
                length += abs(d)
                slid += abs(step) if extend else abs(d)
                if slid >= probe_px or length >= max_len or deg[cur] != 2:
                    break
                s, t = g.indptr[cur], g.indptr[cur + 1]
                nxt = g.indices[s] if g.indices[s] != prev else g.indices[t - 1]
                if nxt == v:                           # a short cycle back to v
                    break
                prev, cur = cur, nxt
            out[a] = m
    return out


def turn_table(g: WorkGraph, motions: np.ndarray, min_cos: float) -> tuple[np.ndarray, np.ndarray]:
    """Allowed turns for every pair (arc into ``v``, arc out of ``v``).

    A turn ``u → v → w`` at a vertex of valence ≥ 3 is allowed when the motion into ``v`` and the
    motion out of it (:func:`arc_motions`) make an angle whose cosine is at least ``min_cos``: going
    from a Y's stem into a branch keeps moving forward over the traced curves, going from one branch
    into the other reverses.  Turns at vertices of valence < 3 are always allowed, and so is a turn
    whose motion is zero (no information).

    Returns
    -------
    turn_ptr : numpy.ndarray
        int64 (A,): the turns from arc ``a`` (into ``v``) are ``turn_ok[turn_ptr[a] + j]`` for the
        ``j``-th arc out of ``v``.
    turn_ok : numpy.ndarray
        bool.
    """
    deg = g.degree
    heads = g.indices
    sizes = deg[heads]
    turn_ptr = np.zeros(len(heads) + 1, np.int64)
    np.cumsum(sizes, out=turn_ptr[1:])
    turn_ok = np.ones(int(turn_ptr[-1]), bool)
    for v in np.nonzero(deg >= 3)[0]:
        outs = np.arange(g.indptr[v], g.indptr[v + 1])
        m_out = -motions[g.arc_rev[outs]]              # motion away from v along each out arc
        for a in g.arc_rev[outs]:                      # arcs into v
            m_in = motions[a]
            dot = (np.conj(m_in) * m_out).real
            ok = dot >= min_cos * np.abs(m_in) * np.abs(m_out)
            turn_ok[turn_ptr[a]:turn_ptr[a] + len(outs)] = ok
    return turn_ptr[:-1], turn_ok


def near_singularity_only(g: WorkGraph, turn_ptr: np.ndarray, turn_ok: np.ndarray) -> np.ndarray:
    """The turn table restricted to vertices flagged next to a singularity (others: every turn allowed).

    This is the authors' constrained search: it applies the Y-junction test only where the graph
    marks a singularity, i.e. at the valence-3 vertices that stand for real Y junctions.
    """
    sizes = g.degree[g.indices]
    owner = np.repeat(np.arange(len(g.indices)), sizes)
    return turn_ok | ~g.near_singularity[g.indices[owner]]
