"""Tests of the graph stage on synthetic drawings with exact geometry (stages/synthetic.py).

The field is the real ``stages.field`` on the real ``stages.prep`` band; drawings are 64×64, so each
case takes well under a second once numba's cache is warm (the first run compiles the kernels).
"""

from __future__ import annotations

import copy
from functools import lru_cache
from pathlib import Path

import networkx as nx
import numpy as np
import pytest
import yaml

from stages import field, graph, prep, synthetic
from stages.artifact import Artifact, unpack_ragged
from stages.errors import InputError

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT / ".." / "shared"


def _cfg(stage: str) -> dict:
    return yaml.safe_load((ROOT / "conf" / stage / "default.yaml").read_text())


@lru_cache(maxsize=None)
def _inputs(name: str, **kw) -> tuple[Artifact, Artifact]:
    drawing = getattr(synthetic, name)(**kw)
    p = prep.run(_cfg("prep"), image_bytes=drawing.png_bytes(), image_name=name)
    return p, field.run(_cfg("field"), prep=p)


def _inputs_from_grey(grey: np.ndarray) -> tuple[Artifact, Artifact]:
    """Prep artifact made by hand (no hole repair), so that pinholes survive into the band."""
    mask = grey < 165 / 255
    p = Artifact(arrays={"grey": grey.astype(np.float32), "mask": mask})
    return p, field.run(_cfg("field"), prep=p)


def _graph(p: Artifact, f: Artifact, **cleanup) -> Artifact:
    cfg = copy.deepcopy(_cfg("graph"))
    cfg["cleanup"].update(cleanup)
    return graph.run(cfg, prep=p, field=f)


def _nx(a: Artifact) -> nx.Graph:
    g = nx.Graph()
    g.add_nodes_from(range(len(a["vertex_xy"])))
    g.add_edges_from(a["edges"].tolist())
    return g


def _line_frame(stroke: np.ndarray, xy: np.ndarray):
    """(along, across) coordinates of points relative to a straight stroke."""
    a, b = stroke[0], stroke[-1]
    d = (b - a) / np.linalg.norm(b - a)
    n = np.array([-d[1], d[0]])
    return (xy - a) @ d, (xy - a) @ n


def _is_path(g: nx.Graph) -> bool:
    deg = np.array([d for _, d in g.degree()])
    return nx.is_connected(g) and deg.max() <= 2 and (deg == 1).sum() == 2


# --------------------------------------------------------------------------------------------------
# Geometry and topology on the synthetic drawings
# --------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("angle", [17.0, 40.0, 133.0])
def test_straight_stroke_is_a_centred_path(angle):
    drawing = synthetic.line(angle=angle)
    a = _graph(*_inputs("line", angle=angle))
    g = _nx(a)
    assert len(a["vertex_xy"]) > 20
    assert _is_path(g)
    along, across = _line_frame(drawing.strokes[0], a["vertex_xy"])
    assert np.abs(across).max() <= 0.5
    # the chain spans the stroke (from cap to cap)
    length = np.linalg.norm(drawing.strokes[0][1] - drawing.strokes[0][0])
    assert along.min() < 1.5 and along.max() > length - 1.5
    # widths: away from the rounded caps the cross-section is the full stroke
    inner = (along > drawing.width) & (along < length - drawing.width)
    assert np.abs(a["vertex_width"][inner] - drawing.width).max() <= 1.0
    assert np.abs(a["vertex_width_raw"][inner] - drawing.width).max() <= 1.0


def test_axis_aligned_stroke_width_counts_the_outer_lanes():
    """Lanes sit on pixel centres 1 px apart: the bare diameter (reference) would be 1 px short."""
    drawing = synthetic.line(angle=0.0, width=3.0, size=63)  # centre line through pixel centres
    a = _graph(*_inputs("line", angle=0.0, width=3.0, size=63))
    assert _is_path(_nx(a))
    along, across = _line_frame(drawing.strokes[0], a["vertex_xy"])
    inner = (along > 3) & (along < 41)
    assert np.abs(across[inner]).max() < 0.05
    # three lanes, two gaps of 1 px: diameter 2 + half a lane spacing
    np.testing.assert_allclose(a["vertex_width_raw"][inner], 2.5, atol=0.05)


def test_single_lane_cross_section_has_positive_width():
    """A one-pixel-wide band has one lane per cross-section: width = half a pixel, never 0."""
    grey = np.ones((40, 60), np.float32)
    grey[20, 5:55] = 0.0
    a = _graph(*_inputs_from_grey(grey))
    assert len(a["vertex_xy"]) > 10
    assert (a["vertex_width_raw"] > 0).all()
    np.testing.assert_allclose(np.median(a["vertex_width_raw"]), 0.5, atol=0.05)


def test_circle_is_one_cycle():
    a = _graph(*_inputs("circle"))
    g = _nx(a)
    assert nx.is_connected(g)
    assert all(d == 2 for _, d in g.degree())
    assert len(nx.cycle_basis(g)) == 1
    r = np.linalg.norm(a["vertex_xy"] - 32.0, axis=1)
    assert np.abs(r - 20.0).max() <= 0.5


def test_x_crossing_gives_two_overlapping_branches_without_shared_vertex():
    drawing = synthetic.cross()
    a = _graph(*_inputs("cross"))
    g = _nx(a)
    comps = [sorted(c) for c in nx.connected_components(g)]
    assert len(comps) == 2
    centre = np.array([32.0, 32.0])
    used = set()
    for comp in comps:
        assert _is_path(g.subgraph(comp))
        xy = a["vertex_xy"][comp]
        # each branch follows one stroke...
        offs = [np.abs(_line_frame(s, xy)[1]).max() for s in drawing.strokes]
        k = int(np.argmin(offs))
        assert offs[k] <= 0.75
        used.add(k)
        # ... straight through the crossing
        assert np.linalg.norm(xy - centre, axis=1).min() <= 1.0
    assert used == {0, 1}


def test_t_junction_gives_two_components():
    drawing = synthetic.tee()
    a = _graph(*_inputs("tee"))
    g = _nx(a)
    comps = [sorted(c) for c in nx.connected_components(g)]
    assert len(comps) == 2
    for comp in comps:
        assert _is_path(g.subgraph(comp))
    # the stem's branch reaches the bar
    bar, stem = drawing.strokes
    stem_comp = min(comps, key=lambda c: np.abs(_line_frame(stem, a["vertex_xy"][c])[1]).max())
    assert np.linalg.norm(a["vertex_xy"][stem_comp] - stem[0], axis=1).min() <= 1.5


@pytest.mark.parametrize("width", [3.0, 5.0])
@pytest.mark.parametrize("angle", [0.0, 17.0, 40.0])
def test_t_stem_ends_on_the_bar_centre_line_not_beyond_it(angle, width):
    """Inside the bar the field's normal root continues the stem, so the stem's chain used to run on
    to the bar's far edge (1.5–2.8 px beyond its centre line); the covered end is cut back."""
    drawing = synthetic.tee(angle=angle, width=width)
    a = _graph(*_inputs("tee", angle=angle, width=width))
    g = _nx(a)
    bar, stem = drawing.strokes
    xy = a["vertex_xy"]
    leaves = [v for v, d in g.degree() if d == 1]
    stem_end = min(leaves, key=lambda v: np.linalg.norm(xy[v] - stem[0]))
    along, across = _line_frame(bar, xy[stem_end:stem_end + 1])
    # the stem lies on the positive side of the bar (y down, stem at angle + 90°)
    assert -0.75 <= across[0] <= 1.5


def test_covered_tip_fragment_is_dropped_and_a_separate_stroke_kept():
    """A tiny component inside another stroke's discs is that stroke's thickness (a rounded tip
    traced apart); one outside them is a stroke of its own."""
    from stages.graph.ends import trim_covered_ends

    main = np.stack([np.arange(0.0, 20.0), np.full(20, 10.0)], axis=1)          # width 4, ends at x = 19
    frag = np.array([[18.5, 11.0], [19.5, 10.5], [20.3, 10.0]])                  # inside its discs
    far = np.array([[10.0, 16.0], [11.0, 16.0], [12.0, 16.0]])                   # 6 px away: kept
    xy = np.concatenate([main, frag, far])
    width = np.full(len(xy), 4.0)
    e = [(k, k + 1) for k in range(19)] + [(20, 21), (21, 22), (23, 24), (24, 25)]
    edges, n = trim_covered_ends(xy, width, np.array(e), max_length=10.0, min_covered=0.75, margin=0.5)
    left = set(edges.ravel().tolist())
    assert n == 1
    assert not left & {20, 21, 22}
    assert {23, 24, 25} <= left and set(range(20)) <= left


def test_two_short_components_covering_each_other_keep_the_longer():
    """Inside a small filled blob the two field families trace two short crossing components, each
    in the other's discs: only the shorter goes (deleting both left the blob without a curve)."""
    from stages.graph.ends import trim_covered_ends

    a = np.stack([np.arange(0.0, 6.0), np.full(6, 3.0)], axis=1)
    b = np.stack([np.full(7, 2.6), np.arange(0.2, 7.2)], axis=1)
    xy = np.concatenate([a, b])
    width = np.full(len(xy), 7.0)
    e = [(k, k + 1) for k in range(5)] + [(k, k + 1) for k in range(6, 12)]
    edges, _ = trim_covered_ends(xy, width, np.array(e), max_length=10.0, min_covered=0.75, margin=0.5)
    assert set(edges.ravel().tolist()) == set(range(6, 13))


def test_y_junction_has_one_valence_three_vertex_near_its_centre():
    a = _graph(*_inputs("wye"))
    g = _nx(a)
    assert nx.is_connected(g)
    deg = np.array([d for _, d in g.degree()])
    assert (deg >= 3).sum() == 1 and deg.max() == 3
    assert (deg == 1).sum() == 3
    v = int(np.flatnonzero(deg == 3)[0])
    assert np.linalg.norm(a["vertex_xy"][v] - 32.0) <= 2.5


def test_y_junction_needs_the_join_across_the_singularity():
    """Without the join the traces stopped by the singularity leave the Y in pieces."""
    a = _graph(*_inputs("wye"), join_singular_distance=0.0)
    assert not nx.is_connected(_nx(a))


def _pinhole_stroke() -> np.ndarray:
    grey = synthetic.line(angle=17.0, width=7.0).grey.copy()
    grey[32:34, 32:34] = 1.0  # 4 background pixels inside the stroke
    return grey


def test_pinhole_loop_is_contracted():
    p, f = _inputs_from_grey(_pinhole_stroke())
    assert (~p["mask"][31:35, 31:35]).sum() == 4 and not p["mask"][32:34, 32:34].any()
    a = _graph(p, f)
    g = _nx(a)
    assert a.data["counts"]["loops_contracted"] >= 1
    assert nx.is_connected(g) and len(nx.cycle_basis(g)) == 0


def test_pinhole_loop_stays_when_contraction_is_disabled():
    a = _graph(*_inputs_from_grey(_pinhole_stroke()), max_loop_background=0)
    assert len(nx.cycle_basis(_nx(a))) >= 1


def _teardrop_loop() -> np.ndarray:
    """A thin closed loop with a tight round end (an eye drawn as a teardrop), 14 × 6 px, width 1.8."""
    t = np.linspace(0.0, 2 * np.pi, 200)
    x = 7.0 * np.cos(t)
    y = 3.0 * np.sin(t) * (1 - 0.4 * (np.cos(t) + 1))  # round at x = -7, pointed at x = +7
    return synthetic.render((48, 48), [np.c_[x + 24.0, y + 24.0]], 1.8)


def test_narrow_loop_cap_is_closed():
    """The streamlines do not follow the tight cap: its two sides end as leaves unless joined."""
    p, f = _inputs_from_grey(_teardrop_loop())
    open_ = _nx(_graph(p, f, close_caps_widths=0.0))
    assert len(nx.cycle_basis(open_)) == 0 and sum(d == 1 for _, d in open_.degree) >= 2
    a = _graph(p, f)
    closed = _nx(a)
    assert a.data["counts"]["loop_caps_closed"] >= 1
    assert nx.is_connected(closed) and len(nx.cycle_basis(closed)) == 1


def test_small_ring_keeps_its_real_hole():
    a = _graph(*_inputs("circle", radius=5.0))
    g = _nx(a)
    assert nx.is_connected(g) and len(nx.cycle_basis(g)) == 1


# --------------------------------------------------------------------------------------------------
# The artifact contract
# --------------------------------------------------------------------------------------------------

def test_artifact_follows_the_interface():
    p, f = _inputs("wye")
    a = _graph(p, f)
    v = len(a["vertex_xy"])
    assert a["vertex_xy"].dtype == np.float64 and a["vertex_xy"].shape == (v, 2)
    for name in ("vertex_width", "vertex_width_raw"):
        assert a[name].dtype == np.float64 and a[name].shape == (v,)
    assert a["vertex_root"].dtype == np.complex64
    np.testing.assert_allclose(np.abs(a["vertex_root"]), 1.0, atol=1e-5)
    assert a["vertex_flags"].dtype == np.uint8 and (a["vertex_flags"] & 1).any()
    e = a["edges"]
    assert e.dtype == np.int32 and e.shape[1] == 2 and (e[:, 0] < e[:, 1]).all()
    assert len(np.unique(e, axis=0)) == len(e) and e.max() < v
    assert a["edge_curve"].dtype == np.int32 and a["edge_curve"].shape == (len(e),)
    n_lines = len(a["streamline_xy_offsets"]) - 1
    assert (a["edge_curve"] < n_lines).all() and (a["edge_curve"] == -1).sum() >= 1  # the Y join
    members = unpack_ragged(a["vertex_members"], a["vertex_members_offsets"])
    assert len(members) == v and all(len(m) >= 1 for m in members)
    assert a["vertex_members"].dtype == np.int32 and a["vertex_members"].max() < n_lines
    # an edge from a streamline joins two vertices that both hold it
    for (i, j), c in zip(e, a["edge_curve"]):
        if c >= 0:
            assert c in members[i] and c in members[j]
    lines = unpack_ragged(a["streamline_xy"], a["streamline_xy_offsets"])
    assert a["streamline_xy"].dtype == np.float32 and all(len(s) >= 2 for s in lines)
    # streamlines stay in the band
    ij = np.floor(a["streamline_xy"][:, ::-1]).astype(int)
    assert p["mask"][ij[:, 0], ij[:, 1]].all()
    # vertices sit on the band
    ij = np.floor(a["vertex_xy"][:, ::-1]).astype(int)
    assert p["mask"][ij[:, 0], ij[:, 1]].mean() > 0.95
    # widths are smoothed, within the raw range
    assert a["vertex_width"].min() >= a["vertex_width_raw"].min() - 1e-9
    assert a["vertex_width"].max() <= a["vertex_width_raw"].max() + 1e-9
    assert np.std(np.diff(a["vertex_width"])) <= np.std(np.diff(a["vertex_width_raw"]))
    assert {"counts", "timings"} <= set(a.data)


def test_graph_is_deterministic():
    p, f = _inputs("cross")
    a, b = _graph(p, f), _graph(p, f)
    for k in a.arrays:
        np.testing.assert_array_equal(a[k], b[k])


def test_render_graph_draws_over_the_drawing():
    p, f = _inputs("circle")
    a = _graph(p, f)
    img = graph.render_graph(p["grey"], a.arrays, scale=3)
    assert img.dtype == np.uint8 and img.shape == (64 * 3, 64 * 3, 3)
    # coloured (non-grey) pixels where the graph is drawn, none in the far corner
    colour = np.ptp(img.astype(int), axis=2) > 60
    assert colour.sum() > 500 and not colour[:20, :20].any()
    # without the graph nothing is coloured
    empty = graph.render_graph(p["grey"], {}, scale=3)
    assert not (np.ptp(empty.astype(int), axis=2) > 60).any()


# --------------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------------

def test_empty_band_gives_an_empty_graph():
    grey = np.ones((20, 20), np.float32)
    p = Artifact(arrays={"grey": grey, "mask": np.zeros((20, 20), bool)})
    a = _graph(p, field.run(_cfg("field"), prep=p))
    assert len(a["vertex_xy"]) == 0 and len(a["edges"]) == 0
    assert len(a["streamline_xy_offsets"]) == 1 and len(a["vertex_members_offsets"]) == 1


@pytest.mark.parametrize("shape", [(1, 30), (30, 1), (2, 2)])
def test_strokes_on_the_image_border(shape):
    """Traces that reach the last row/column (stored as float32) must stay inside the image."""
    mask = np.zeros(shape, bool)
    mask[tuple(slice(1, -1) if n > 2 else slice(None) for n in shape)] = True
    grey = np.where(mask, 0.0, 1.0).astype(np.float32)
    p = Artifact(arrays={"grey": grey, "mask": mask})
    a = _graph(p, field.run(_cfg("field"), prep=p))
    xy = a["streamline_xy"]
    assert ((xy >= 0) & (xy < np.array(shape[::-1]))).all()


def test_random_drawings_touching_the_border_do_not_fail():
    rng = np.random.default_rng(7)
    for _ in range(20):
        h, w = rng.integers(3, 40, 2)
        strokes = [rng.uniform(-4, [w + 4, h + 4], size=(3, 2)) for _ in range(2)]
        grey = synthetic.render((int(h), int(w)), strokes, float(rng.uniform(1, 5)))
        a = _graph(*_inputs_from_grey(grey))
        deg = np.bincount(a["edges"].ravel(), minlength=len(a["vertex_xy"]))
        assert (deg > 0).all()


def test_missing_or_mismatched_inputs_raise_input_error():
    p, f = _inputs("line")
    with pytest.raises(InputError):
        graph.run(_cfg("graph"), prep=p)
    bad = Artifact(arrays={**f.arrays, "c0": f["c0"][:-1]})
    with pytest.raises(InputError):
        graph.run(_cfg("graph"), prep=p, field=bad)
    nan = Artifact(arrays={**f.arrays, "c2": np.full_like(f["c2"], np.nan)})
    with pytest.raises(InputError):
        graph.run(_cfg("graph"), prep=p, field=nan)
    no_roots = Artifact(arrays={k: v for k, v in f.arrays.items() if k != "roots"})
    with pytest.raises(InputError):
        graph.run(_cfg("graph"), prep=p, field=no_roots)


def test_config_must_match_the_yaml_keys():
    p, f = _inputs("line")
    cfg = _cfg("graph")
    cfg["trace"]["steps"] = 0.1
    with pytest.raises(InputError):
        graph.run(cfg, prep=p, field=f)
    cfg = _cfg("graph")
    del cfg["store_every"]
    with pytest.raises(InputError):
        graph.run(cfg, prep=p, field=f)


@pytest.mark.parametrize("cap", [0, 2_000_000])
def test_trace_length_cap_is_bounded(cap):
    """The tracing kernel reserves room for 2 · max_half_samples samples per seed: a cap past
    1,000,000 (100,000 px at 0.1 px) would reserve gigabytes, so it is refused in one line."""
    p, f = _inputs("line")
    cfg = _cfg("graph")
    cfg["trace"]["max_half_samples"] = cap
    with pytest.raises(InputError, match="graph.trace.max_half_samples must be in"):
        graph.run(cfg, prep=p, field=f)


def test_trace_does_not_depend_on_its_buffer_size(monkeypatch):
    """The kernel grows its sample buffers before a seed (not per step): from the smallest start,
    through many growths, it traces exactly what a buffer that never grows traces."""
    from stages.graph import trace

    p, f = _inputs("line", angle=23.0, width=6.0)
    kw = dict(_cfg("graph")["trace"], max_half_samples=600)
    kernel = trace._trace_all

    def traced(cap):
        monkeypatch.setattr(trace, "_trace_all", lambda *args: kernel(*args[:-1], cap))
        return trace.trace_streamlines(f["c0"], f["c2"], p["mask"], f["singular"], f["roots"][..., 0], **kw)

    small, large = traced(1), traced(4_000_000)
    assert len(small.xy) > 10_000      # the 1-sample start grew a dozen times
    for name in ("xy", "tangent", "curve", "start", "length", "end_reason"):
        np.testing.assert_array_equal(getattr(small, name), getattr(large, name))


# --------------------------------------------------------------------------------------------------
# Real drawing (shared data)
# --------------------------------------------------------------------------------------------------

@pytest.mark.shared
@pytest.mark.slow
def test_scanned_drawing_crop_graph_is_centred_on_the_strokes():
    path = SHARED / "data" / "drawings" / "scanned" / "kitten.png"
    if not path.exists():
        pytest.skip("shared data absent")
    from PIL import Image
    import io

    img = Image.open(path).convert("L").crop((150, 280, 330, 420))  # eyes and brows
    buf = io.BytesIO()
    img.save(buf, "PNG")
    p = prep.run(_cfg("prep"), image_bytes=buf.getvalue(), image_name="kitten-crop")
    f = field.run(_cfg("field"), prep=p)
    a = _graph(p, f)
    xy = a["vertex_xy"]
    assert len(xy) > 200
    ij = np.floor(xy[:, ::-1]).astype(int)
    assert p["mask"][ij[:, 0], ij[:, 1]].mean() > 0.97
    # centred: a vertex is about as far from the band's edge as its half width
    from scipy.ndimage import distance_transform_edt

    inside = distance_transform_edt(p["mask"])[ij[:, 0], ij[:, 1]]
    ok = np.abs(inside - a["vertex_width"] / 2) <= 1.5
    assert ok.mean() > 0.85
    deg = np.bincount(a["edges"].ravel(), minlength=len(xy))
    assert (deg == 2).mean() > 0.8


def test_streamline_edges_equal_the_three_key_lexsort():
    """Edges of consecutive crossings, unique, each with its lowest streamline: the one-key stable sort
    gives what sorting by (i, j, streamline) gives, on crossings in any order and with duplicates."""
    from stages.graph.raw_graph import member_order, streamline_edges
    rng = np.random.default_rng(7)
    n = 5000
    mv, mc = rng.integers(0, 300, n), rng.integers(0, 80, n)
    mp = rng.integers(0, 40, n).astype(np.float64)            # ties in the parameter too
    order = member_order(mc, mp)
    v, c = mv[order], mc[order]
    link = (c[1:] == c[:-1]) & (v[1:] != v[:-1])
    a, b, cc = v[:-1][link], v[1:][link], c[:-1][link]
    e = np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)
    o = np.lexsort((cc, e[:, 1], e[:, 0]))
    e, cc = e[o], cc[o]
    first = np.r_[True, np.any(e[1:] != e[:-1], axis=1)]
    edges, ecurve = streamline_edges(mv, mc, mp)
    np.testing.assert_array_equal(edges, e[first])
    np.testing.assert_array_equal(ecurve, cc[first])
    np.testing.assert_array_equal(streamline_edges(mv, mc, mp, order)[0], edges)


def test_cross_section_argsort_is_a_stable_argsort():
    """The kernel's own argsort of a cross-section's crossings (no compiled quicksort) orders like a
    stable sort, ties included, also on the two-run shape a cross-section gives (one side ascending,
    the other descending) and on sizes that are not powers of two."""
    from stages.graph.cross_section import _argsort_stable

    rng = np.random.default_rng(3)
    for n in (0, 1, 2, 3, 7, 16, 40, 129, 1000):
        a = np.round(rng.normal(size=n + 3), 1)   # rounded: ties
        np.testing.assert_array_equal(_argsort_stable(a, n), np.argsort(a[:n], kind="stable"))
        half = n // 2
        two_runs = np.concatenate([[0.0], np.round(np.linspace(0.1, 3, half), 1),
                                   -np.round(np.linspace(0.1, 3, n - half), 1)])[:n]
        np.testing.assert_array_equal(_argsort_stable(two_runs, n), np.argsort(two_runs, kind="stable"))


def test_cross_section_cell_index_groups_every_sample_by_its_sub_cell():
    """The cross-sections' sample lookup: each band pixel's SUB × SUB cells, every sample once, in the
    cell its coordinates fall in, ascending ids within a cell."""
    from stages.graph.cross_section import SUB, _cell_index

    band = np.zeros((5, 7), bool)
    band[1:4, 2:6] = True
    rng = np.random.default_rng(5)
    rows, cols = np.nonzero(band)
    pick = rng.integers(0, len(rows), 400)
    sx = (cols[pick] + rng.random(400)).astype(np.float32)
    sy = (rows[pick] + rng.random(400)).astype(np.float32)
    sx[:4] = [2.0, 2.999999, 5.75, 3.25]                        # on sub-cell borders
    sy[:4] = [1.0, 3.999999, 2.5, 1.25]
    bidx, start, samples = _cell_index(sx, sy, band)
    assert (bidx.reshape(band.shape) >= 0).sum() == band.sum() and start[-1] == 400
    np.testing.assert_array_equal(np.sort(samples), np.arange(400))
    x, y = sx.astype(np.float64), sy.astype(np.float64)
    cell = (bidx[y.astype(int) * 7 + x.astype(int)] * SUB * SUB
            + np.minimum((y % 1 * SUB).astype(int), SUB - 1) * SUB + np.minimum((x % 1 * SUB).astype(int), SUB - 1))
    for c in range(len(start) - 1):
        members = samples[start[c]:start[c + 1]]
        np.testing.assert_array_equal(members, np.flatnonzero(cell == c))


@pytest.mark.parametrize("angle", [0.0, 23.0, 61.0])
def test_cross_section_finds_every_streamline_segment_it_crosses(angle):
    """The cross-section kernel looks for crossing streamline segments only in the sub-cells near each
    step: on a wide straight stroke it finds exactly the crossings a search over every sample finds."""
    from stages.graph import cross_section as cs
    from stages.graph.trace import trace_streamlines

    p, f = _inputs("line", angle=angle, width=6.0)
    t, s = _cfg("graph")["trace"], _cfg("graph")["sections"]
    band = p["mask"]
    c0 = np.where(band, f["c0"], 0).astype(np.complex128)
    c2 = np.where(band, f["c2"], 0).astype(np.complex128)
    lines = trace_streamlines(c0, c2, band, f["singular"], f["roots"][..., 0], step=t["step"],
                              max_half_samples=t["max_half_samples"], merge_distance=t["merge_distance"],
                              merge_cos=t["merge_cos"], self_merge_lag=t["self_merge_lag"], tie=t["tie"])
    sx, sy = np.ascontiguousarray(lines.xy[:, 0]), np.ascontiguousarray(lines.xy[:, 1])
    bidx, cstart, csamples = cs._cell_index(sx, sy, band)
    k = int(np.argmax(lines.length))
    g = int(lines.start[k] + lines.length[k] // 2)
    tangent = complex(*lines.tangent[g].astype(np.float64))
    root = tangent                       # the followed root: the cross-section goes across it
    max_steps = int(np.ceil(s["max_section_length"] / t["step"]))
    buf = [np.empty(4096, np.int64), np.empty(4096), np.empty(4096)]
    poly = [np.empty((2, max_steps + 2)) for _ in range(3)]
    ncr, n0, n1, _, _ = cs._section(c0, c2, band, np.ascontiguousarray(f["singular"]), sx, sy,
                                    lines.start, lines.length, bidx, cstart, csamples, k, g, root, t["step"],
                                    s["max_gap"], max_steps, t["tie"], *buf, *poly)
    found = sorted((int(c), round(float(q), 4)) for c, q in zip(buf[0][1:ncr], buf[1][1:ncr]))
    # every sample's segment against every step of the cross-section, vectorised
    li = np.arange(len(sx)) - lines.start[lines.curve]
    ok = li + 1 < lines.length[lines.curve]
    ax, ay = sx[:-1][ok[:-1]], sy[:-1][ok[:-1]]
    bx, by = sx[1:][ok[:-1]] - ax, sy[1:][ok[:-1]] - ay
    cid, lid = lines.curve[:-1][ok[:-1]], li[:-1][ok[:-1]]
    brute = []
    for side, n in ((0, n0), (1, n1)):
        px, py = poly[1][side, :n], poly[2][side, :n]
        for i in range(n - 1):
            ex, ey = px[i + 1] - px[i], py[i + 1] - py[i]
            den = ex * by - ey * bx
            wx, wy = ax - px[i], ay - py[i]
            with np.errstate(divide="ignore", invalid="ignore"):
                a = (wx * by - wy * bx) / den
                b = (wx * ey - wy * ex) / den
            hit = (den != 0) & (a >= 0) & (a < 1) & (b >= 0) & (b < 1)
            hit &= ~((cid == k) & (np.abs(lid + b - (g - lines.start[k])) < 1.5))
            brute += [(int(c), round(float(q), 4)) for c, q in zip(cid[hit], (lid + b)[hit])]
    assert len(found) >= 7
    assert found == sorted(brute)


def test_each_edge_keeps_the_streamline_it_came_from():
    """The streamline of each final edge is looked up among the streamline edges whichever way the
    edge is written; the joins added across singularities (not among them) get −1."""
    from stages.graph.stage import edge_streamlines

    rng = np.random.default_rng(5)
    for _ in range(50):
        n = int(rng.integers(2, 40))
        known = np.unique(np.sort(rng.integers(0, n, (int(rng.integers(0, 60)), 2)), axis=1), axis=0)
        known = known[known[:, 0] < known[:, 1]]
        curve = rng.integers(0, 100, len(known))
        edges = rng.integers(0, n + 3, (int(rng.integers(0, 40)), 2))
        lookup = {(int(a), int(b)): int(c) for (a, b), c in zip(known, curve)}
        want = [lookup.get((int(min(a, b)), int(max(a, b))), -1) for a, b in edges]
        got = edge_streamlines(known, curve, edges)
        assert got.dtype == np.int32 and got.tolist() == want
