"""Allowed paths between key vertices over a covering subgraph (paper §4.3 "Enumerating allowed paths").

For each pair of key vertices of a component's subgraph, the allowed paths are the simple paths
between them that contain no other key vertex and take only allowed turns at vertices of valence ≥ 3
(the Y-junction test, :func:`stages.topology.work_graph.turn_table`).  X and T junctions need no test:
their two strokes are disjoint branches of the graph.

The enumeration runs on the subgraph's *chains* (maximal runs of valence-2 vertices between
"nodes": key vertices, vertices of subgraph valence ≠ 2, and valence-2 vertices whose only turn is
forbidden), so its cost depends on the number of junctions, not of vertices.  Two safeguards keep it
bounded on messy subgraphs: at most ``max_paths_per_pair`` (the shortest) per pair of key vertices, and
a search budget per key vertex (best-first, so what a cut drops is the longest).  Any chain that no allowed path uses afterwards (a forbidden turn, or a
cut budget) gets its non-key end nodes promoted to synthetic key vertices (type 0) and the
enumeration is repeated, so the allowed paths always cover the whole subgraph.

Junction zones (a choice beyond the paper): the graph rarely puts a Y junction's keypoint exactly on
its valence-3 vertex — the key vertex lands on one branch a pixel or two away, or the junction is a
small cluster of valence-3 vertices.  Paths between other key vertices could then bypass it.  A path
whose interior comes within ``junction_zone_px`` (along the subgraph) of a junction key vertex must
therefore end at it, pass through it, or end elsewhere inside that zone (at a synthetic key vertex
promoted there).

Pass-through (a choice beyond the paper, see the package docstring): a junction key vertex (type 3)
of subgraph valence 2 — the keypoint of an X, or a T seen from its bar — is also passable: paths may
end there *or* run straight through it (at most ``max_pass_through`` of them), so an X yields both
its four half strokes and its two full strokes.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra


@dataclass
class Chain:
    """A maximal run of valence-2 subgraph vertices between two nodes, in one direction."""

    start: int
    end: int
    vertices: list[int]        # start ... end
    arcs: list[int]
    length: float
    uid: int                   # same for both directions
    reverse: int = -1          # index of the opposite direction


@dataclass
class EnumerationResult:
    paths: list[dict] = field(default_factory=list)   # {"vertices", "arcs", "through"}
    promoted: list[int] = field(default_factory=list)  # vertices that became synthetic key vertices
    budget_hit: bool = False


def _turn_allowed(g, turn_ptr, turn_ok, a_in: int, a_out: int) -> bool:
    v = g.indices[a_in]
    return bool(turn_ok[turn_ptr[a_in] + (a_out - g.indptr[v])])


def component_subgraph(g, sub_edge: np.ndarray, comp: int) -> tuple[int, int, np.ndarray, np.ndarray, np.ndarray]:
    """One component's covering subgraph: ``(v0, v1, sub_arc, sub_deg, in_sub)``.

    ``sub_arc`` bool (A,) marks the component's arcs of subgraph edges, ``sub_deg`` (v1 - v0,) is each
    vertex's subgraph valence and ``in_sub`` the vertices (global ids) with at least one such arc.
    """
    v0, v1 = int(g.comp_ptr[comp]), int(g.comp_ptr[comp + 1])
    a0, a1 = int(g.indptr[v0]), int(g.indptr[v1])
    sub_arc = np.zeros(len(g.indices), bool)
    sub_arc[a0:a1] = sub_edge[g.arc_edge[a0:a1]]
    tails = np.repeat(np.arange(v0, v1), np.diff(g.indptr[v0:v1 + 1]))
    sub_deg = np.bincount(tails[sub_arc[a0:a1]] - v0, minlength=v1 - v0)
    return v0, v1, sub_arc, sub_deg, np.nonzero(sub_deg > 0)[0] + v0


def subgraph_chains(g, sub_arc: np.ndarray, in_sub: np.ndarray, sub_deg: np.ndarray, v0: int, terminals,
                    gdeg: np.ndarray, turn_ptr, turn_ok, arc_len: np.ndarray) -> tuple[set, list[Chain], dict]:
    """The nodes of one component's covering subgraph (:func:`component_subgraph`) and the chains between them.

    Nodes are key vertices (``terminals``), vertices of subgraph valence ≠ 2, and valence-2 vertices of a
    valence ≥ 3 graph vertex (``gdeg``: graph valence) whose only turn is forbidden (they block paths).
    Returns ``(nodes, chains, by_start)`` (see :func:`_chains`).
    """
    nodes = set(int(v) for v in in_sub if sub_deg[v - v0] != 2 or v in terminals)
    for v in in_sub:
        v = int(v)
        if v in nodes or gdeg[v] < 3:
            continue
        a, b = [x for x in range(g.indptr[v], g.indptr[v + 1]) if sub_arc[x]]
        if not _turn_allowed(g, turn_ptr, turn_ok, int(g.arc_rev[a]), b):
            nodes.add(v)
    chains, by_start = _chains(g, sub_arc, nodes, arc_len)
    return nodes, chains, by_start


def _chains(g, sub_arc: np.ndarray, nodes: set, arc_len: np.ndarray) -> tuple[list[Chain], dict]:
    """Both directions of every chain; ``by_start[node]`` lists chain indices leaving a node."""
    chains: list[Chain] = []
    seen_arc = set()
    uid = 0
    for x in sorted(nodes):
        for a in range(g.indptr[x], g.indptr[x + 1]):
            if not sub_arc[a] or a in seen_arc:
                continue
            verts, arcs, length = [x], [a], arc_len[a]
            cur = int(g.indices[a])
            prev_arc = a
            while cur not in nodes:
                verts.append(cur)
                nxt = -1
                for b in range(g.indptr[cur], g.indptr[cur + 1]):
                    if sub_arc[b] and b != g.arc_rev[prev_arc]:
                        nxt = b
                        break
                if nxt < 0:                      # cannot happen: non-nodes have valence 2
                    break
                arcs.append(nxt)
                length += arc_len[nxt]
                prev_arc = nxt
                cur = int(g.indices[nxt])
            verts.append(cur)
            seen_arc.update(arcs)
            seen_arc.update(int(g.arc_rev[b]) for b in arcs)
            fwd = Chain(x, cur, verts, arcs, float(length), uid)
            bwd = Chain(cur, x, verts[::-1], [int(g.arc_rev[b]) for b in arcs[::-1]], float(length), uid)
            fwd.reverse, bwd.reverse = len(chains) + 1, len(chains)
            chains += [fwd, bwd]
            uid += 1
    by_start: dict[int, list[int]] = {}
    for i, c in enumerate(chains):
        by_start.setdefault(c.start, []).append(i)
    return chains, by_start


def _best_first_from(s: int, g, chains: list, by_start: dict, terminals: dict, through: set, gdeg,
                     turn_ptr, turn_ok, max_pass_through: int, max_per_pair: int, max_steps: int,
                     found: dict, zone_owner: dict) -> bool:
    """Allowed paths from key vertex ``s``, shortest first, into ``found`` (canonical vertex tuple →
    (length, chain sequence, flipped)).  Partial paths are a tree of parent pointers; a pair of key
    vertices stops collecting after ``max_per_pair`` paths.  Returns whether ``max_steps`` cut it."""
    store: list[tuple[int, int, int]] = []          # (chain, parent entry, passes)
    heap: list[tuple[float, int]] = []
    for ci in by_start.get(s, []):
        store.append((ci, -1, 0))
        heapq.heappush(heap, (chains[ci].length, len(store) - 1))
    per_pair: dict[int, int] = {}
    steps = 0
    while heap:
        steps += 1
        if steps > max_steps:
            return True
        length, nid = heapq.heappop(heap)
        ci, parent, passes = store[nid]
        y = chains[ci].end
        seq, visited = [ci], {s}
        q = parent
        while q >= 0:
            seq.append(store[q][0])
            visited.add(chains[store[q][0]].end)
            q = store[q][1]
        if y in visited and y != s:
            continue
        cont = True
        if y in terminals:
            seq.reverse()
            if per_pair.get(y, 0) < max_per_pair:
                verts = [s]
                for k in seq:
                    verts += chains[k].vertices[1:]
                key = min(tuple(verts), tuple(verts[::-1]))
                # Entering a junction's zone is fine for a path that ends (or passes) there.
                allowed_owners = {s, y, zone_owner.get(s, -1), zone_owner.get(y, -1)} | \
                    {v for v in verts[1:-1] if v in terminals}
                bypass = any(zone_owner.get(v, -1) not in (-1, *allowed_owners) for v in verts[1:-1])
                if key not in found and not bypass:
                    found[key] = (length, tuple(seq), key != tuple(verts))
                    per_pair[y] = per_pair.get(y, 0) + 1
            cont = y in through and passes < max_pass_through and y != s
            passes += 1
        if not cont:
            continue
        last_arc = chains[ci].arcs[-1]
        for cj in by_start.get(y, []):
            if cj == chains[ci].reverse:
                continue
            if gdeg[y] >= 3 and not _turn_allowed(g, turn_ptr, turn_ok, last_arc, chains[cj].arcs[0]):
                continue
            store.append((cj, nid, passes))
            heapq.heappush(heap, (length + chains[cj].length, len(store) - 1))
    return False


def _junction_zones(g, sub_arc: np.ndarray, v0: int, v1: int, arc_len: np.ndarray, junctions: set,
                    zone_px: float) -> dict:
    """Vertex → the junction key vertex whose zone (subgraph distance ≤ ``zone_px``) it lies in."""
    if not junctions or zone_px <= 0:
        return {}
    a0, a1 = int(g.indptr[v0]), int(g.indptr[v1])
    w = np.where(sub_arc[a0:a1], arc_len[a0:a1], 0.0)
    csr = sp.csr_matrix((w, g.indices[a0:a1] - v0, g.indptr[v0:v1 + 1] - a0), shape=(v1 - v0, v1 - v0))
    csr.eliminate_zeros()
    src = np.array(sorted(junctions), np.int64) - v0
    d, _, owner = dijkstra(csr, directed=True, indices=src, limit=zone_px, min_only=True,
                           return_predecessors=True)
    near = np.nonzero(np.isfinite(d))[0]
    return {int(v) + v0: int(owner[v]) + v0 for v in near}


def enumerate_allowed_paths(g, sub_edge: np.ndarray, comp: int, terminals: dict, passable: set,
                            turn_ptr, turn_ok, arc_len: np.ndarray, max_pass_through: int,
                            max_paths_per_pair: int, max_steps: int, junctions: set = frozenset(),
                            zone_px: float = 0.0, max_rounds: int = 20) -> EnumerationResult:
    """Allowed paths of one component's subgraph.

    Parameters
    ----------
    g : stages.topology.work_graph.WorkGraph
    sub_edge : numpy.ndarray
        bool (E,) edges of the covering subgraph.
    comp : int
        The component.
    terminals : dict
        Key vertices of the component (vertex → anything); synthetic key vertices promoted here are
        added to it with value ``None``.
    passable : set
        Junction key vertices that paths may run through (valence 2 in the subgraph is checked here).
    turn_ptr, turn_ok : numpy.ndarray
        Y-junction turn table.
    arc_len : numpy.ndarray
        Arc lengths.
    max_pass_through, max_paths_per_pair, max_steps : int
        See ``conf/topology/default.yaml``.
    junctions : set
        Junction key vertices (type 3): a path that passes within ``zone_px`` (subgraph distance) of
        one must end there or pass through it.

    Returns
    -------
    EnumerationResult
    """
    v0, v1, sub_arc, sub_deg, in_sub = component_subgraph(g, sub_edge, comp)
    gdeg = g.degree
    result = EnumerationResult()
    if len(in_sub) == 0:
        return result
    zone_owner = _junction_zones(g, sub_arc, v0, v1, arc_len, junctions, zone_px)

    for _ in range(max_rounds):
        nodes, chains, by_start = subgraph_chains(g, sub_arc, in_sub, sub_deg, v0, terminals, gdeg, turn_ptr,
                                                  turn_ok, arc_len)
        through = {v for v in passable if v in terminals and sub_deg[v - v0] == 2}
        found: dict[tuple, tuple] = {}
        budget_hit = False
        for s in sorted(terminals):
            if s in nodes:
                budget_hit |= _best_first_from(s, g, chains, by_start, terminals, through, gdeg, turn_ptr,
                                               turn_ok, max_pass_through, max_paths_per_pair, max_steps, found,
                                               zone_owner)
        # Keep the shortest few per pair of key vertices.
        by_pair: dict[tuple, list] = {}
        for key, (length, seq, flipped) in found.items():
            by_pair.setdefault((min(key[0], key[-1]), max(key[0], key[-1])), []).append((length, key, seq, flipped))
        paths = []
        used_uid = set()

        def keep(key: tuple, seq, flipped: bool) -> None:
            arcs = [a for k in seq for a in chains[k].arcs]
            if flipped:                                      # the key is the reversed walk
                arcs = [int(g.arc_rev[a]) for a in arcs[::-1]]
            used_uid.update(chains[k].uid for k in seq)
            paths.append({"vertices": list(key), "arcs": arcs, "through": [v for v in key[1:-1] if v in terminals]})

        for pair in sorted(by_pair):
            for length, key, seq, flipped in sorted(by_pair[pair], key=lambda x: (x[0], x[1]))[:max_paths_per_pair]:
                keep(key, seq, flipped)
        orphans = {c.uid: c for c in chains if c.uid not in used_uid}
        if orphans:
            # A chain that only paths beyond the per-pair cap use (a spiral's outer ring between two key
            # vertices that shorter routes also join) keeps the shortest allowed path through it:
            # promotion cannot help when both its ends are key vertices already.
            rescue: dict[int, tuple] = {}
            for key, (length, seq, flipped) in found.items():
                for k in seq:
                    uid = chains[k].uid
                    if uid in orphans and (uid not in rescue or (length, key) < rescue[uid][:2]):
                        rescue[uid] = (length, key, seq, flipped)
            for length, key, seq, flipped in sorted({r[1]: r for r in rescue.values()}.values(), key=lambda x: (x[0], x[1])):
                if not all(chains[k].uid in used_uid for k in seq):
                    keep(key, seq, flipped)
            orphans = {uid: c for uid, c in orphans.items() if uid not in used_uid}
        promote = set()
        for c in orphans.values():
            promote.update(v for v in (c.start, c.end) if v not in terminals)
        result.paths = paths
        result.budget_hit = result.budget_hit or budget_hit
        if not promote:
            break
        for v in sorted(promote):
            terminals[v] = None
            result.promoted.append(v)
    return result
