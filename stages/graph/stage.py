"""Stage ``graph``: trace the frame field and build the graph of stroke cross-sections (paper §4.1, Fig. 7).

Following Bessmeltsev & Solomon 2019 as the authors' code uses it (shared/reference/
b19-frame-field-and-graph.md §A.2–A.3, authors-implementation.md §4):

1. :mod:`~stages.graph.trace` — streamlines of the PolyVector field from every band pixel, both ways
   (step 0.1 px, best-aligned root continuation, stop on leaving the band, singular pixels, merging,
   length cap).
2. :mod:`~stages.graph.cross_section` (its kernels) and :mod:`~stages.graph.raw_graph` — vertices =
   cross-sections of the streamlines of one root family (gaps ≤ ``max_gap``): centre, width, root,
   member streamlines; edges join vertices consecutive along a streamline.
3. :mod:`~stages.graph.cleanup` — merge near-duplicate vertices, trim dangling branches into
   singularities, drop insignificant components, contract thickness loops (≤ 4 enclosed background
   pixels; real holes stay), prune spurs inside the stroke and hooked tips, join dangling ends across
   singularities (Y junctions), cut ends back that lie inside another component's stroke (T stems
   overshooting the bar, tip fragments), smooth the widths by one sparse least-squares solve.

Choices, in short (each module's docstring has the reasons and measurements):

* **Where cross-sections are taken.**  The reference takes them only at streamline ends; we place
  them along the streamlines about ``station_spacing`` (1 px) apart, each one serving the whole bundle
  it crosses, so every stroke is a chain of vertices ~1 px apart (what the topology's coverage and the
  flow's resampling need).  The raw graph is then *not* a dense ladder: one cross-section covers all
  the ~30 lanes of a bundle.  What duplicates remain (lanes starting mid-stroke) are merged when
  adjacent, closer than 0.5 px and of the same root family; the few small cycles left are thickness
  loops, contracted like the reference's.
* **Vertex position** = midpoint of the cross-section (not the mean of the crossings, which lane density
  biases); **width** = diameter + half a lane spacing (never 0, within 0.75 px of the drawn width on
  synthetic strokes at all angles); ``max_gap`` = 1.5 px (1 px cuts axis-aligned strokes, whose lanes are
  exactly 1 px apart).
* **Extra clean-up** not in the authors' code, taken from B19: spur pruning
  (``removeBranchesFilter1``) and joins across singularities (``connectStuffAroundSingularities``);
  plus trimming of sideways-hooked tips at rounded stroke ends.  Without them a straight stroke's tip
  and a Y junction do not come out as a path and a valence-3 vertex.
* **Ends inside another stroke** (:func:`~stages.graph.ends.trim_covered_ends`, not in the
  references): a T stem's chain runs on across the bar to its far edge, and rounded tips trace as
  tiny separate components; both made spurious junctions on realvec_dev.  Such ends are cut back
  onto the other stroke's centre line, such fragments dropped.
* Components are dropped by width-padded bounding-box area only (the reference's "no vertex crosses
  two streamlines" rule deletes one-pixel-wide axis-aligned strokes).

Measured (tests/benchmarks/bench_graph.py, the four scanned drawings, 2 shared cores): 0.75–1.45 s CPU,
peak RSS ≤ 355 MB (2026-11-27); vertices are centred on the band to 0.10 px (median) / 0.3 px (90th percentile)
along their normals.

The artifact follows stages/INTERFACES.md "graph"; :func:`~stages.graph.graph_picture.render_graph` draws it over
the drawing.
"""

from __future__ import annotations

import time
from itertools import pairwise

import numpy as np

from stages.arrays import sorted_unique
from stages.artifact import Artifact
from stages.config import from_section
from stages.errors import InputError
from stages.graph import GraphConfig, cleanup, ends
from stages.graph.raw_graph import RawGraph, raw_graph, streamline_edges, take_cross_sections
from stages.graph.trace import SINGULAR, Streamlines, trace_streamlines


def _flag_singular_curve_ends(raw: RawGraph, length: np.ndarray, end_reason: np.ndarray, reach: float) -> np.ndarray:
    """Flag the first/last vertex of every streamline that ended on a singular pixel (reference);
    ``length`` and ``end_reason`` as :class:`~stages.graph.trace.Streamlines`'."""
    flags = raw.flags.copy()
    if len(raw.member_vertex) == 0:
        return flags
    order = raw.member_order
    c = raw.member_curve[order]
    first = np.r_[True, c[1:] != c[:-1]]
    last = np.r_[c[1:] != c[:-1], True]
    for sel, end, near in ((first, 0, lambda p, cc: p <= reach),
                           (last, 1, lambda p, cc: length[cc] - 1 - p <= reach)):
        rows = order[sel]
        cc = raw.member_curve[rows]
        hit = (end_reason[cc, end] == SINGULAR) & near(raw.member_param[rows], cc)
        flags[raw.member_vertex[rows[hit]]] |= 1
    return flags


def edge_streamlines(known: np.ndarray, curve: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The streamline of each edge, looked up among the ``known`` streamline edges; −1 where absent.

    Parameters
    ----------
    known : numpy.ndarray
        int (K, 2) unique edges ``a < b`` in ascending (a, b) order, as
        :func:`~stages.graph.raw_graph.streamline_edges` gives them.
    curve : numpy.ndarray
        int (K,) the streamline of each known edge.
    edges : numpy.ndarray
        int (E, 2) edges, either orientation.

    Returns
    -------
    numpy.ndarray
        int32 (E,).
    """
    out = np.full(len(edges), -1, np.int32)
    if len(edges) == 0 or len(known) == 0:
        return out
    e = np.sort(np.asarray(edges, np.int64).reshape(-1, 2), axis=1)
    # one int64 key per edge, ascending as the known edges are (a sorted search; a dict of tuples
    # took 0.1 s on the elephant's 9k edges)
    span = np.int64(max(int(known.max()), int(e.max())) + 1)
    kk = known[:, 0].astype(np.int64) * span + known[:, 1]
    q = e[:, 0] * span + e[:, 1]
    at = np.minimum(np.searchsorted(kk, q), len(kk) - 1)
    hit = kk[at] == q
    out[hit] = np.asarray(curve)[at[hit]]
    return out


def stored_streamlines(lines: Streamlines, every: int) -> tuple[np.ndarray, np.ndarray]:
    """The streamlines subsampled for storage: every ``every``-th sample of each curve and its last one.

    The kept samples are indexed per curve, not picked by a mask over all samples: a mask took four
    int64 temporaries a sample (1.1 GB on a 4x4 page), this takes one index a kept sample, and that
    one in chunks of :data:`STORED_CHUNK` kept samples (the whole index and its five int64 temporaries
    were the graph's peak on a 4x4 page, +270 MB).

    Parameters
    ----------
    lines : Streamlines
        The traced curves (each curve's samples contiguous, curve after curve).
    every : int
        Keep every n-th sample (values < 1 count as 1).

    Returns
    -------
    xy : numpy.ndarray
        float32 (M, 2) the kept samples, curve after curve.
    offsets : numpy.ndarray
        int64 (C + 1,) ragged offsets of the curves into ``xy``.
    """
    every = max(1, int(every))
    length = lines.length.astype(np.int64)
    # samples 0, every, 2·every, … and the last one (once, when it is a multiple already)
    per = np.where(length > 0, -(-(length - 1) // every) + 1, 0)
    offsets = np.zeros(len(length) + 1, np.int64)
    np.cumsum(per, out=offsets[1:])
    xy = np.empty((int(offsets[-1]), 2), np.float32)
    # whole curves per chunk: the first curve of each chunk of about STORED_CHUNK kept samples
    cuts = np.unique(np.r_[0, np.searchsorted(offsets, np.arange(0, offsets[-1], STORED_CHUNK), side="right") - 1,
                           len(length)])
    for c0, c1 in pairwise(cuts):
        p, o0 = per[c0:c1], offsets[c0]
        rank = np.arange(o0, offsets[c1]) - np.repeat(offsets[c0:c1], p)
        take = np.repeat(lines.start[c0:c1].astype(np.int64), p) + np.minimum(rank * every,
                                                                               np.repeat(length[c0:c1] - 1, p))
        xy[o0:offsets[c1]] = lines.xy[take]
    return xy, offsets


#: Kept samples indexed at a time by :func:`stored_streamlines` (its int64 temporaries: 48 bytes each).
STORED_CHUNK = 1 << 20


def _drop_small(xy, width, edges, min_area):
    alive = cleanup.remove_small_components(xy, width, edges, min_area)
    return edges[alive[edges[:, 0]]] if len(edges) else edges


def build_graph(grey: np.ndarray, band: np.ndarray, c0: np.ndarray, c2: np.ndarray, roots: np.ndarray,
                singular: np.ndarray, conf: GraphConfig) -> tuple[dict, dict]:
    """The whole stage on plain arrays.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) grey image (only its shape is used).
    band : numpy.ndarray
        bool (H, W) narrow band.
    c0, c2 : numpy.ndarray
        complex (H, W) PolyVector coefficients.
    roots : numpy.ndarray
        complex (H, W, 2) roots, ``[..., 0]`` the larger-modulus one (seeds).
    singular : numpy.ndarray
        bool (H, W) singular pixels.
    conf : GraphConfig

    Returns
    -------
    arrays : dict
        The artifact arrays (stages/INTERFACES.md "graph").
    data : dict
        Counts, timings and clean-up statistics.
    """
    tc, sc, cc = conf.trace, conf.sections, conf.cleanup
    timings = {}
    notes: list[str] = []          # guards that bound (said by the engine; see Artifact.notes)
    t0 = time.perf_counter()
    lines = trace_streamlines(c0, c2, band, singular, roots[..., 0], step=tc.step,
                              max_half_samples=tc.max_half_samples, merge_distance=tc.merge_distance,
                              merge_cos=tc.merge_cos, self_merge_lag=tc.self_merge_lag, tie=tc.tie)
    t1 = time.perf_counter()
    timings["trace_s"] = t1 - t0
    # the samples end with the cross-sections' kernel: they (16 bytes each, 0.55 GB on a 4x4 page) are
    # dropped before the crossings are sorted and the clean-up runs (held to the end, they and those
    # sorts made the stage's peak)
    sections = take_cross_sections(c0, c2, band, singular, lines, step=tc.step,
                                   station_spacing=sc.station_spacing, cover_factor=sc.cover_factor,
                                   min_station_gap=sc.min_station_gap, max_gap=sc.max_gap,
                                   max_section_length=sc.max_section_length, ambiguity=sc.ambiguity,
                                   tie=tc.tie, lane_pad=sc.lane_pad)
    # the stored subsample after the kernel, not before: it (55 MB on a 4x4 page) is not held
    # beside the kernel's sample index, the stage's peak
    s_xy, s_off = stored_streamlines(lines, conf.store_every)
    stats = {"streamlines": int(len(lines.start)), "streamline_samples": int(len(lines.xy))}
    length, end_reason = lines.length, lines.end_reason
    del lines
    raw = raw_graph(sections)
    del sections
    t2 = time.perf_counter()
    timings["sections_s"] = t2 - t1
    stats.update({"raw_vertices": int(len(raw.xy)), "raw_edges": int(len(raw.edges)),
                  "failed_stations": raw.n_failed})

    flags = _flag_singular_curve_ends(raw, length, end_reason, reach=2 * sc.station_spacing / tc.step)
    # 1. near-duplicate cross-sections
    keep, mv = cleanup.merge_close_vertices(raw.xy, raw.root, raw.member_vertex, raw.member_curve,
                                            raw.member_param, raw.edges, cc.merge_distance, cc.merge_min_cos)
    xy, width, root = raw.xy[keep], raw.width[keep], raw.root[keep]
    merged_flags = np.zeros(len(keep), np.uint8)
    np.bitwise_or.at(merged_flags, mv, flags[raw.member_vertex])
    flags = merged_flags
    mc, mp = raw.member_curve, raw.member_param
    edges, ecurve = streamline_edges(mv, mc, mp, raw.member_order)
    streamline_e, streamline_c = edges, ecurve
    stats["merged_vertices"] = int(len(raw.xy) - len(keep))
    # clean-up steps 2-6 only delete or add edges; vertices left without edges go at the end
    # counts[v] = distinct streamlines crossing vertex v: unique (vertex, streamline) pairs as one
    # int64 key (a 1-D sort; the row-wise unique of millions of pairs took 1.2 s on the 2x elephant)
    span = np.int64(mc.max()) + 1 if len(mc) else np.int64(1)
    key = sorted_unique(mv.astype(np.int64) * span + mc)      # sorted as the rows (vertex, streamline)
    pairs = np.stack([key // span, key % span], axis=1)
    counts = np.bincount(pairs[:, 0], minlength=len(xy)).astype(np.int64)
    # 2. dangling branches into singularities
    removed = 0
    if cc.singular_branches:
        edges, flags, removed = cleanup.remove_singular_branches(len(xy), edges, flags)
    stats["singular_branch_edges_removed"] = removed
    # 3. insignificant components (before the loop search, the costly part)
    edges = _drop_small(xy, width, edges, cc.min_component_area)
    # 4. thickness loops
    edges, n_loops, cut = cleanup.contract_thickness_loops(xy, edges, band, cc.max_loop_background,
                                                           cc.max_cycle_vertices, cc.max_loop_searches)
    stats["loops_contracted"] = n_loops
    if cut:
        notes.append(f"thickness-loop search stopped after graph.cleanup.max_loop_searches "
                     f"({cc.max_loop_searches}) cycle searches: {n_loops} loops contracted, others kept")
    # 5. spurs inside the stroke
    edges, n_spurs = ends.prune_covered_spurs(xy, width, counts, edges, cc.spur_max_length,
                                                 cc.spur_min_covered)
    stats["spurs_pruned"] = n_spurs
    edges, n_tips = ends.trim_hooked_tips(xy, width, edges, cc.tip_hook_angle)
    stats["hooked_tips_trimmed"] = n_tips
    # 6. joins across singularities
    if cc.join_singular_distance > 0:
        added = ends.join_singular_ends(xy, width, edges, flags, band, singular, cc.join_singular_distance,
                                           cc.join_singular_min_hops)
    else:
        added = np.zeros((0, 2), np.int64)
    stats["singular_joins"] = int(len(added))
    edges = np.concatenate([edges, added]).astype(np.int64)
    # 6a. the caps of narrow loops
    caps = ends.close_loop_caps(xy, width, edges, band, cc.close_caps_widths, cc.close_caps_min_hops)
    stats["loop_caps_closed"] = int(len(caps))
    edges = np.concatenate([edges, caps]).astype(np.int64)
    # 6b. ends inside other components' strokes (after the joins: a Y's pieces are one component by now)
    edges, n_cov = ends.trim_covered_ends(xy, width, edges, cc.spur_max_length, cc.spur_min_covered,
                                             cc.cover_margin)
    stats["covered_ends_trimmed"] = n_cov
    edges = _drop_small(xy, width, edges, cc.min_component_area)
    deg = np.bincount(edges.ravel(), minlength=len(xy))
    final = np.flatnonzero(deg > 0)
    new_of = np.full(len(xy), -1, np.int64)
    new_of[final] = np.arange(len(final))
    e_fin = np.sort(new_of[edges], axis=1) if len(edges) else np.zeros((0, 2), np.int64)
    # each edge keeps a streamline it came from; −1 for the joins across singularities
    ec = edge_streamlines(streamline_e, streamline_c, edges)
    order = np.lexsort((e_fin[:, 1], e_fin[:, 0])) if len(e_fin) else np.zeros(0, np.int64)
    e_fin, ec = e_fin[order], ec[order]
    t3 = time.perf_counter()
    timings["cleanup_s"] = t3 - t2
    # 7. widths
    w_raw = width[final]
    w = cleanup.smooth_widths(w_raw, e_fin, conf.width_smoothing)
    timings["widths_s"] = time.perf_counter() - t3

    # members of the surviving vertices
    # `pairs` is sorted by (vertex, streamline) and `new_of` increases over the kept vertices, so the
    # kept members are already in (new vertex, streamline) order
    pv = new_of[pairs[:, 0]] if len(pairs) else np.zeros(0, np.int64)
    sel = pv >= 0
    pv, pcurve = pv[sel], pairs[sel, 1]
    bounds = np.searchsorted(pv, np.arange(len(final) + 1))
    members, members_off = pcurve.astype(np.int32), bounds.astype(np.int64)

    arrays = {
        "vertex_xy": xy[final].astype(np.float64),
        "vertex_width": w.astype(np.float64),
        "vertex_width_raw": w_raw.astype(np.float64),
        "vertex_root": root[final].astype(np.complex64),
        "vertex_flags": flags[final].astype(np.uint8),
        "edges": e_fin.astype(np.int32).reshape(-1, 2),
        "edge_curve": ec.astype(np.int32),
        "vertex_members": members,
        "vertex_members_offsets": members_off,
        "streamline_xy": s_xy.reshape(-1, 2),
        "streamline_xy_offsets": s_off,
    }
    deg = np.bincount(e_fin.ravel(), minlength=len(final))
    stats.update({"vertices": int(len(final)), "edges": int(len(e_fin)),
                  "degree_histogram": np.bincount(deg).tolist() if len(deg) else [],
                  "singular_vertices": int((arrays["vertex_flags"] & 1).sum())})
    data = {"counts": stats, "timings": {k: round(v, 4) for k, v in timings.items()}, "notes": notes}
    return arrays, data


def run(cfg: dict, **inputs: Artifact) -> Artifact:
    """Stage entry: the graph of the drawing.

    Parameters
    ----------
    cfg : dict
        The ``graph`` config section (see :class:`GraphConfig`).
    prep : Artifact
        ``grey`` (H, W), ``mask`` bool (H, W).
    field : Artifact
        ``c0``, ``c2`` complex (H, W), ``roots`` complex (H, W, 2), ``singular`` bool (H, W).

    Returns
    -------
    Artifact
        See stages/INTERFACES.md "graph".
    """
    conf = from_section(GraphConfig, cfg, "graph")
    for name in ("prep", "field"):
        if name not in inputs:
            raise InputError(f"graph stage needs the '{name}' artifact")
    prep, field = inputs["prep"], inputs["field"]
    try:
        grey = np.asarray(prep["grey"])
        band = np.asarray(prep["mask"]).astype(bool)
        c0, c2 = np.asarray(field["c0"]), np.asarray(field["c2"])
        roots, singular = np.asarray(field["roots"]), np.asarray(field["singular"]).astype(bool)
    except KeyError as exc:
        raise InputError(f"graph: input artifact lacks array {exc}") from None
    shape = band.shape
    if band.ndim != 2 or grey.shape != shape or c0.shape != shape or c2.shape != shape \
            or roots.shape != shape + (2,) or singular.shape != shape:
        raise InputError(f"graph: prep/field arrays disagree in shape (mask {shape}, c0 {c0.shape}, "
                         f"roots {roots.shape})")
    if not (np.all(np.isfinite(c0)) and np.all(np.isfinite(c2)) and np.all(np.isfinite(roots))):
        raise InputError("graph: field contains NaN or infinite values")
    t = time.perf_counter()
    arrays, data = build_graph(grey, band, c0, c2, roots, singular, conf)
    data["timings"]["total_s"] = round(time.perf_counter() - t, 4)
    return Artifact(arrays=arrays, data=data, notes=data.pop("notes"))
