"""Topology extraction, per connected component of the drawing graph (paper §4.2–4.3).

Steps, as in the paper's Fig. 8:

1. key vertices (:mod:`.key_vertices`), moved onto their keypoints;
2. a Steiner tree over them (:mod:`.steiner`);
3. coverage extension — loop A: constrained shortest walks between key vertices that visit
   ≥ ``min_new_vertices`` uncovered vertices and cover ≥ ``min_new_pixels`` new band pixels
   (:mod:`.constrained_path`); loop B (robustness against missed keypoints): the uncovered vertex
   farthest from the subgraph (> ``robust_far_px``) becomes a synthetic key vertex if its walk
   visits ≥ ``robust_min_new_vertices`` uncovered vertices and covers new pixels;
4. allowed paths between key vertices (:mod:`.allowed_paths`).
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
from scipy import ndimage
from scipy.sparse.csgraph import dijkstra

from stages.arrays import sorted_unique
from stages.geometry import arc_length, point_at_arc, turn_deg
from stages.topology import TopologyConfig
from stages.topology.allowed_paths import component_subgraph, enumerate_allowed_paths, subgraph_chains
from stages.topology.constrained_path import constrained_walk
from stages.topology.coverage import CoverageState, band_pixels, edge_coverage, gather
from stages.topology.key_vertices import find_key_vertices, snap_position
from stages.topology.steiner import path_to_source, steiner_tree
from stages.topology.work_graph import WorkGraph, arc_motions, build_work_graph, near_singularity_only, turn_table

SYNTHETIC = (-1, 0)      # (keypoint, type) of a key vertex that no keypoint asked for


class _Extractor:
    """State shared by the per-component steps (one drawing)."""

    def __init__(self, conf: TopologyConfig, g: WorkGraph, mask: np.ndarray):
        self.conf, self.g, self.mask = conf, g, mask
        self.n = g.n_vertices
        self.comp_of = np.repeat(np.arange(len(g.comp_ptr) - 1), np.diff(g.comp_ptr))
        self.tails = g.arc_tail()
        self.arc_key = self.tails * max(self.n, 1) + g.indices
        self.sub_edge = np.zeros(len(g.edges), bool)
        self.steiner_edge = np.zeros(len(g.edges), bool)
        self.is_term = np.zeros(self.n, bool)
        self.terminals: dict[int, dict[int, tuple[int, int]]] = {}
        self.stats = {"loop_a_paths": 0, "loop_a_rejected": 0, "loop_b_paths": 0, "loop_b_rejected": 0,
                      "lone_component_terminals": 0, "promoted_terminals": 0, "enumeration_budget_hit": 0,
                      "pass_through_rejected": 0, "uncovered_chains_offered": 0}

    # -- helpers ------------------------------------------------------------------------------
    def edge_ids(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Edge ids of vertex pairs that are graph edges."""
        a = np.searchsorted(self.arc_key, np.asarray(u, np.int64) * self.n + np.asarray(v, np.int64))
        return self.g.arc_edge[a]

    def local_csr(self, c: int) -> tuple[sp.csr_matrix, int]:
        g = self.g
        v0, v1 = int(g.comp_ptr[c]), int(g.comp_ptr[c + 1])
        a0, a1 = int(g.indptr[v0]), int(g.indptr[v1])
        csr = sp.csr_matrix((self.arc_len[a0:a1], g.indices[a0:a1] - v0, g.indptr[v0:v1 + 1] - a0),
                            shape=(v1 - v0, v1 - v0))
        return csr, v0

    def add_terminal(self, c: int, v: int, label=SYNTHETIC) -> None:
        self.terminals.setdefault(c, {})[int(v)] = label
        self.is_term[v] = True

    # -- pipeline -------------------------------------------------------------------------------
    def prepare(self, points, types, roots) -> None:
        conf, g = self.conf, self.g
        self.graph_xy = g.xy.copy()                 # positions before key vertices move
        depth = ndimage.distance_transform_edt(self.mask) if conf.keypoint_min_depth > 0 else None
        for v, k, t in find_key_vertices(g, self.comp_of, points, types, roots, self.mask,
                                         conf.keypoint_radius_px, conf.merge_graph_dist_px,
                                         conf.min_component_vertices):
            self.add_terminal(int(self.comp_of[v]), v, (k, t))
            # onto the keypoint (paper §4.2), unless it sits at the ink's edge (see snap_position)
            g.xy[v] = points[k] if depth is None or t == 1 else snap_position(
                depth, self.graph_xy[v], points[k], 0.5 * float(g.width[v]), conf.keypoint_min_depth)
        self.arc_len = g.arc_length()
        motions = arc_motions(g, conf.turn_probe_px, conf.turn_probe_max_px)
        self.turn_ptr, self.turn_ok = turn_table(g, motions, conf.turn_min_cos)
        self.search_turn_ok = near_singularity_only(g, self.turn_ptr, self.turn_ok)
        self.no_turn_test = np.ones_like(self.turn_ok)
        _, self.pixel_flat = band_pixels(self.mask)
        pix, ver = edge_coverage(g.xy, g.width, g.edges, self.comp_of, self.mask, conf.coverage_margin_px)
        self.cov = CoverageState(len(self.pixel_flat), self.n, pix, ver)

    def component(self, c: int) -> list[dict]:
        conf, g, cov = self.conf, self.g, self.cov
        v0, v1 = int(g.comp_ptr[c]), int(g.comp_ptr[c + 1])
        if v1 - v0 < conf.min_component_vertices:
            return []
        csr, _ = self.local_csr(c)
        cov.reset()
        term = self.terminals.setdefault(c, {})
        for v in term:
            cov.add([], [v])
        self._lone_terminals(c, csr, v0)
        tree = self._steiner(c, csr, v0)
        if len(tree):
            eids = self.edge_ids(tree[:, 0], tree[:, 1])
            self.sub_edge[eids] = True
            self.steiner_edge[eids] = True
            cov.add(eids, tree.ravel())
        self._loop_a(c)
        self._loop_b(c, csr, v0)
        passable = {v for v, (k, t) in term.items()
                    if (t == 3 and conf.pass_through_junctions) or (t == 1 and conf.pass_through_endpoints)}
        junctions = {v for v, (k, t) in term.items() if t == 3}
        res = enumerate_allowed_paths(g, self.sub_edge, c, term, passable, self.turn_ptr, self.turn_ok,
                                      self.arc_len, conf.max_pass_through, conf.max_paths_per_pair,
                                      conf.max_enumeration_steps, junctions, conf.junction_zone_px)
        for v in res.promoted:
            self.add_terminal(c, v)
        self.stats["promoted_terminals"] += len(res.promoted)
        self.stats["enumeration_budget_hit"] += int(res.budget_hit)
        for p in res.paths:
            p["component"] = c
        return res.paths

    def _lone_terminals(self, c: int, csr, v0: int) -> None:
        """Components with < 2 key vertices: start from their farthest vertices (authors' rule).

        No key vertex: the vertex farthest from the component's first one (a stroke tip, if any)
        becomes the first terminal.  One terminal: the vertex farthest from it becomes the second, if
        the path to it covers ≥ ``min_new_pixels`` new band pixels.
        """
        term = self.terminals[c]
        if not term:
            d = dijkstra(csr, directed=True, indices=0)
            d[~np.isfinite(d)] = -1
            s = int(np.argmax(d)) + v0
            self.add_terminal(c, s)
            self.cov.add([], [s])
            self.stats["lone_component_terminals"] += 1
        if len(term) == 1:
            t = next(iter(term))
            d, pred = dijkstra(csr, directed=True, indices=t - v0, return_predecessors=True)
            d[~np.isfinite(d)] = -1
            f = int(np.argmax(d))
            if d[f] <= 0:
                return
            path = np.array(path_to_source(pred, f), np.int64) + v0
            eids = self.edge_ids(path[:-1], path[1:])
            if self.cov.new_pixels(eids) >= self.conf.min_new_pixels:
                self.add_terminal(c, f + v0)
                self.stats["lone_component_terminals"] += 1

    def _steiner(self, c: int, csr, v0: int) -> np.ndarray:
        term = np.array(sorted(self.terminals[c]), np.int64) - v0
        return steiner_tree(csr, term, self.conf.steiner_method) + v0

    def _walk(self, c: int, uncovered, sources, need: int):
        """Constrained walk, first with the search's turn test, then (if none) without any.

        Coverage comes first: a region reachable only through a forbidden turn is still added to the
        subgraph; the allowed-path enumeration then ends paths at that junction instead.
        """
        for table in (self.search_turn_ok, self.no_turn_test):
            walk = constrained_walk(self.g, self.arc_len, self.turn_ptr, table, c, uncovered, sources,
                                    self.is_term, need)
            if walk is not None:
                return walk
        return None

    def _accept(self, walk, uncovered: np.ndarray, need: int, need_pixels: int) -> tuple[bool, np.ndarray, np.ndarray]:
        verts, arcs = walk
        distinct = np.unique(verts[uncovered[verts]])
        eids = np.unique(self.g.arc_edge[arcs])
        ok = len(distinct) >= need and self.cov.new_pixels(eids) >= need_pixels
        return ok, distinct, eids

    def _loop_a(self, c: int) -> None:
        """Add cheapest walks between key vertices while they cover enough (paper: 'at least four')."""
        conf, g, cov = self.conf, self.g, self.cov
        v0, v1 = int(g.comp_ptr[c]), int(g.comp_ptr[c + 1])
        need = conf.min_new_vertices
        ignored = np.zeros(self.n, bool)
        while True:
            unc = ~cov.vertex & ~ignored
            if unc[v0:v1].sum() < need or len(self.terminals[c]) == 0:
                return
            walk = self._walk(c, unc, self.is_term, need)
            if walk is None:
                return
            ok, distinct, eids = self._accept(walk, unc, need, conf.min_new_pixels)
            if ok:
                self.sub_edge[eids] = True
                cov.add(eids, walk[0])
                self.stats["loop_a_paths"] += 1
            else:
                # Their pixels are covered already (or the walk only counted them by circling):
                # they no longer count, so the search moves on.
                ignored[distinct] = True
                self.stats["loop_a_rejected"] += 1

    def _loop_b(self, c: int, csr, v0: int) -> None:
        """Robustness loop: far uncovered vertices become synthetic key vertices (authors' loop B)."""
        conf, g, cov = self.conf, self.g, self.cov
        v1 = int(g.comp_ptr[c + 1])
        rejected = np.zeros(v1 - v0, bool)
        source = np.zeros(self.n, bool)
        a0, a1 = int(g.indptr[v0]), int(g.indptr[v1])
        while True:
            used = np.zeros(v1 - v0, bool)
            used[self.tails[a0:a1][self.sub_edge[g.arc_edge[a0:a1]]] - v0] = True
            used[np.array([v - v0 for v in self.terminals[c]], np.int64)] = True
            d, pred, _ = dijkstra(csr, directed=True, indices=np.nonzero(used)[0], min_only=True,
                               return_predecessors=True)
            cand = ~cov.vertex[v0:v1] & ~rejected & np.isfinite(d) & (d > conf.robust_far_px)
            if not cand.any():
                return
            f = int(np.argmax(np.where(cand, d, -1.0)))
            source[:] = False
            source[f + v0] = True
            unc = ~cov.vertex
            walk = self._walk(c, unc, source, conf.robust_min_new_vertices)
            ok = False
            if walk is not None:
                ok, _, eids = self._accept(walk, unc, conf.robust_min_new_vertices, conf.robust_min_new_pixels)
            if ok:
                self.add_terminal(c, f + v0)
                self.sub_edge[eids] = True
                cov.add(eids, walk[0])
                self.stats["loop_b_paths"] += 1
            else:
                rejected[path_to_source(pred, f)] = True
                self.stats["loop_b_rejected"] += 1

    def subgraph_csr(self) -> sp.csr_matrix:
        """The covering subgraphs' adjacency over all vertices (arc lengths; arcs of other edges absent)."""
        g = self.g
        w = np.where(self.sub_edge[g.arc_edge], self.arc_len, 0.0)
        csr = sp.csr_matrix((w, g.indices, g.indptr), shape=(self.n, self.n))
        csr.eliminate_zeros()
        return csr

    def keypoint_branches(self) -> dict[int, int]:
        """Keypoint → number of covering-subgraph branches leaving it.

        Per keypoint and component, the zone is every subgraph vertex within ``junction_zone_px``
        (along the subgraph) of one of its key vertices; its branches are the subgraph edges with one
        end in the zone, summed over components.  A Y whose key vertex sits a pixel down one branch
        still has 3; an X (two components) 4; a junction keypoint that only a loop passes (its third
        stroke was traced as another component with no key vertex) 2.  The selection caps the
        required valence by it, instead of forcing a duplicate curve.

        Each zone is searched within its own component (a search over the whole graph per keypoint
        cost O(keypoints × vertices): 10 s of a 4×4 page's 20).
        """
        g, conf = self.g, self.conf
        csr = self.subgraph_csr()
        # Edges are sorted by their first vertex, so a component's edges are a contiguous range.
        e_ptr = np.searchsorted(g.edges[:, 0], g.comp_ptr)
        groups: dict[int, dict[int, list[int]]] = {}        # keypoint → component → its key vertices
        for c, term in self.terminals.items():
            for v, (k, t) in term.items():
                if k >= 0:
                    groups.setdefault(k, {}).setdefault(c, []).append(v)
        out = {}
        for k, by_comp in groups.items():
            n = 0
            for c, vs in by_comp.items():
                v0, v1 = int(g.comp_ptr[c]), int(g.comp_ptr[c + 1])
                p0, p1 = int(csr.indptr[v0]), int(csr.indptr[v1])
                local = sp.csr_matrix((csr.data[p0:p1], csr.indices[p0:p1] - v0, csr.indptr[v0:v1 + 1] - p0),
                                      shape=(v1 - v0, v1 - v0))
                d = dijkstra(local, directed=True, indices=np.array(vs) - v0, limit=conf.junction_zone_px,
                             min_only=True)
                inside = np.isfinite(d)
                e0, e1 = int(e_ptr[c]), int(e_ptr[c + 1])
                e = g.edges[e0:e1][self.sub_edge[e0:e1]] - v0
                n += int(np.count_nonzero(inside[e[:, 0]] != inside[e[:, 1]]))
            out[k] = n
        return out

    def interest_distance(self) -> np.ndarray:
        """Graph distance over the covering subgraphs to the nearest junction or key vertex."""
        csr = self.subgraph_csr()
        sub_deg = np.diff(csr.indptr)
        src = np.nonzero((sub_deg >= 3) | self.is_term)[0]
        if len(src) == 0:
            return np.zeros(self.n)
        return dijkstra(csr, directed=True, indices=src, min_only=True)


def _branch(xy: np.ndarray, vs, i: int, step: int, probe: float) -> tuple[np.ndarray, tuple]:
    """Leaving vertex ``i`` of a path in direction ``step`` (±1): the unit direction to the point
    ``probe`` px of arc away, and the vertices passed within that arc (identifies the graph branch)."""
    idx = np.arange(i, len(vs)) if step > 0 else np.arange(i, -1, -1)
    pts = xy[idx]
    s = arc_length(pts)
    if len(pts) < 2 or s[-1] <= 1e-9:
        return np.zeros(2), ()
    t = min(probe, s[-1])
    q = point_at_arc(pts, s, t)
    d = q - pts[0]
    return d / max(np.hypot(*d), 1e-12), tuple(int(vs[j]) for j in idx[s <= t])


def straight_pass_through(raw: list[dict], ex: "_Extractor", conf: TopologyConfig) -> list[dict]:
    """Keep a path through a junction keypoint only where it goes straight on, unambiguously.

    At an X or a T the crossing stroke continues straight through the keypoint; at a Y no branch
    continues another (paper §4.3: no path may turn from one branch into another).  The graph often
    traces a Y as a chain through two of its branches plus the third as another component, so the
    chain's key vertex has valence 2, is passable, and a path turning from branch to branch through
    it was offered — shorter after the flow rounds the turn, so the selection took it (synthetic wye
    at 45°: 2 curves, one turning).  A path through junction keypoint k is kept iff its turn there
    (directions over ``pass_through_probe_px`` on each side) is at most ``pass_through_max_turn_deg``
    and every *other* graph branch at k (those of the candidates ending at k, told apart by the
    vertices they pass within the probe) turns off the path's own two by at least
    ``pass_through_margin_deg`` more: a fork whose stem continues into either branch equally well
    is a Y, not a crossing.
    """
    g = ex.g
    probe, max_turn, margin = conf.pass_through_probe_px, conf.pass_through_max_turn_deg, conf.pass_through_margin_deg
    junction_kp = {v: k for term in ex.terminals.values() for v, (k, t) in term.items() if t == 3}
    # Graph branches leaving every junction keypoint, from the candidates that end there.
    branches: dict[int, dict[tuple, np.ndarray]] = {}
    for p in raw:
        vs = p["vertices"]
        xy = g.xy[np.asarray(vs)]
        for i, step in ((0, 1), (len(vs) - 1, -1)):
            k = junction_kp.get(int(vs[i]))
            if k is not None:
                d, key = _branch(xy, vs, i, step, probe)
                branches.setdefault(k, {})[key] = d
    keep = []
    for p in raw:
        vs = p["vertices"]
        xy = g.xy[np.asarray(vs)]
        ok = True
        for v in p["through"]:
            k = junction_kp.get(int(v))
            if k is None:
                continue
            i = vs.index(v)
            (d_in, key_in), (d_out, key_out) = _branch(xy, vs, i, -1, probe), _branch(xy, vs, i, 1, probe)
            turn = turn_deg(d_in, d_out)
            others = [e for key, e in branches.get(k, {}).items() if key not in (key_in, key_out)]
            if turn > max_turn or any(min(turn_deg(d_in, e), turn_deg(-e, d_out)) < turn + margin
                                      for e in others):
                ok = False
                break
        if ok:
            keep.append(p)
        else:
            ex.stats["pass_through_rejected"] += 1
    return keep


def offer_uncovered_chains(raw: list[dict], ex: "_Extractor") -> list[dict]:
    """Offer each chain of the covering subgraph that no kept candidate runs over as a candidate itself.

    The enumeration counts a chain as used by any allowed path over it, and :func:`straight_pass_through`
    rejects paths only afterwards. Where every path over a chain turned through a junction keypoint — a
    stroke's loop between a junction and a key vertex that shorter routes join too, so the direct path
    was beyond the per-pair cap — the chain's ink had no candidate and no selection could cover it
    (``val_qd_broccoli_1_clean``: a 223-px loop lost). The chain between its two nodes is offered as it
    is (split where a turn is forbidden, as the enumeration splits it); a node that is not a key vertex
    becomes a synthetic one (as the enumeration promotes them).
    """
    g = ex.g
    covered = np.zeros(len(g.edges), bool)
    for p in raw:
        covered[g.arc_edge[np.asarray(p["arcs"], np.int64)]] = True
    orphan = ex.sub_edge & ~covered
    if not orphan.any():
        return raw
    out = list(raw)
    gdeg = g.degree
    for c in np.unique(ex.comp_of[g.edges[orphan, 0]]).tolist():
        v0, _, sub_arc, sub_deg, in_sub = component_subgraph(g, ex.sub_edge, c)
        term = ex.terminals.setdefault(c, {})
        _, chains, _ = subgraph_chains(g, sub_arc, in_sub, sub_deg, v0, term, gdeg, ex.turn_ptr, ex.turn_ok,
                                       ex.arc_len)
        for ch in chains[::2]:                                   # one direction of each
            if not orphan[g.arc_edge[np.asarray(ch.arcs)]].any():
                continue
            for v in (ch.start, ch.end):
                if v not in term:
                    ex.add_terminal(c, v)
            out.append({"vertices": list(ch.vertices), "arcs": list(ch.arcs), "through": [], "component": c})
            ex.stats["uncovered_chains_offered"] += 1
    return out


def candidate_paths(conf: TopologyConfig, mask: np.ndarray, roots: np.ndarray, vertex_xy, vertex_width,
                     vertex_root, edges, points: np.ndarray, types: np.ndarray, vertex_flags=None) -> dict:
    """Candidate paths of one drawing.

    Parameters
    ----------
    conf : TopologyConfig
    mask : numpy.ndarray
        bool (H, W) narrow band.
    roots : numpy.ndarray
        complex (H, W, 2) frame-field roots.
    vertex_xy, vertex_width, vertex_root, edges
        The graph artifact's arrays; ``vertex_flags`` too (optional, bit 0 = next to a singularity).
    points, types : numpy.ndarray
        Keypoints (x, y) and their codes.

    Returns
    -------
    dict
        ``paths`` (list of dicts, see stages/INTERFACES.md), ``key_vertices``, ``steiner_edges``,
        ``steiner_segments`` (S, 4), ``coverage`` (list of flat pixel-index arrays), ``counts``,
        ``timings``.
    """
    t0 = time.perf_counter()
    timings = {}
    g = build_work_graph(vertex_xy, vertex_width, vertex_root, edges, vertex_flags)
    ex = _Extractor(conf, g, mask)
    ex.prepare(np.asarray(points, np.float64).reshape(-1, 2), np.asarray(types).reshape(-1), roots)
    timings["prepare_s"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    raw = []
    n_comp = len(g.comp_ptr) - 1
    for c in range(n_comp):
        raw += ex.component(c)
    raw = straight_pass_through(raw, ex, conf)
    raw = offer_uncovered_chains(raw, ex)
    timings["components_s"] = time.perf_counter() - t1
    dist = ex.interest_distance()

    paths, coverage = [], []
    for pid, p in enumerate(raw):
        vs = np.array(p["vertices"], np.int64)
        c = p["component"]
        term = ex.terminals[c]
        ends = [term[int(vs[0])], term[int(vs[-1])]]
        eids = ex.edge_ids(vs[:-1], vs[1:])
        px = sorted_unique(gather(ex.cov.pix_flat, ex.cov.pix_off, eids))
        coverage.append(ex.pixel_flat[px])
        xy = g.xy[vs].copy()
        # A stroke running past an endpoint keypoint keeps its own position there (only the stroke
        # that ends is pinned to the keypoint).
        passed = [i for i, v in enumerate(vs[1:-1], 1) if term.get(int(v), SYNTHETIC)[1] == 1]
        xy[passed] = ex.graph_xy[vs[passed]]
        paths.append({
            "id": pid, "component": int(c),
            "vertices": g.orig[vs].tolist(),
            "xy": xy.tolist(),
            "widths": g.width[vs].tolist(),
            "interest_dist": np.where(np.isfinite(dist[vs]), dist[vs], 0.0).tolist(),
            "end_types": [int(ends[0][1]), int(ends[1][1])],
            "end_keypoints": [int(ends[0][0]), int(ends[1][0])],
            "through_keypoints": [int(term[int(v)][0]) for v in p["through"]],
            "length": float(np.hypot(*np.diff(g.xy[vs], axis=0).T).sum()),
        })
    key_vertices = [{"vertex": int(g.orig[v]), "keypoint": int(k), "type": int(t), "xy": g.xy[v].tolist(),
                     "component": int(c)}
                    for c in sorted(ex.terminals) for v, (k, t) in sorted(ex.terminals[c].items())]
    branches = [{"keypoint": k, "branches": n} for k, n in sorted(ex.keypoint_branches().items())]
    st = g.edges[ex.steiner_edge]
    covered = np.zeros(len(ex.pixel_flat), bool)
    for c_px in coverage:
        covered[np.searchsorted(ex.pixel_flat, c_px)] = True
    sizes = np.diff(g.comp_ptr)
    counts = {
        "components": int(n_comp),
        "components_processed": int((sizes >= conf.min_component_vertices).sum()),
        "vertices": int(g.n_vertices), "edges": int(len(g.edges)),
        "keypoints": int(len(points)),
        "key_vertices": int(sum(1 for kv in key_vertices if kv["keypoint"] >= 0)),
        "synthetic_key_vertices": int(sum(1 for kv in key_vertices if kv["keypoint"] < 0)),
        "steiner_edges": int(len(st)),
        "subgraph_edges": int(ex.sub_edge.sum()),
        "candidates": len(paths),
        "band_pixels": int(len(ex.pixel_flat)),
        "band_pixels_covered": int(covered.sum()),
        **ex.stats,
    }
    timings["total_s"] = time.perf_counter() - t0
    return {"paths": paths, "key_vertices": key_vertices, "keypoint_branches": branches,
            "steiner_edges": np.sort(g.orig[st], axis=1).tolist(),
            "steiner_segments": np.concatenate([g.xy[st[:, 0]], g.xy[st[:, 1]]], axis=1) if len(st)
            else np.zeros((0, 4)),
            "coverage": coverage, "counts": counts, "timings": timings}
