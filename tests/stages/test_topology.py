"""Tests of the topology stage on drawings whose answer is known.

Graph artifacts come from tests/synthetic_graph.py (chains along the exact centre lines,
shaped like the traced graph at X, T and Y junctions); masks from the rendered grey.
"""

from __future__ import annotations

import json
from pathlib import Path

import networkx as nx
import numpy as np
import pytest
import yaml
from synthetic_graph import ladder, synthetic_inputs

from stages import synthetic
from stages.artifact import Artifact, unpack_ragged
from stages.errors import InputError
from stages.synthetic import Drawing, render
from stages.topology import render_topology, run
from stages.topology.steiner import steiner_tree

ROOT = Path(__file__).resolve().parents[2]
CFG = yaml.safe_load((ROOT / "conf" / "topology" / "default.yaml").read_text())


def _run(drawing, keypoints=None, **overrides):
    cfg = {**CFG, **overrides}
    inputs = synthetic_inputs(drawing, keypoints=keypoints)
    return run(cfg, **inputs), inputs


def _pairs(art) -> list[tuple[int, int]]:
    return [tuple(sorted(p["end_keypoints"])) for p in art.data["paths"]]


def _uncovered(art, inputs) -> int:
    mask = inputs["prep"]["mask"]
    covered = np.zeros(mask.size, bool)
    for px in unpack_ragged(art["coverage"], art["coverage_offsets"]):
        covered[px] = True
    return int((mask.ravel() & ~covered).sum())


def _fork(centre_keypoint: bool) -> Drawing:
    """A Y with a stem and two branches 20° either side of its axis (a clear stem)."""
    c = np.array([32.0, 34.0])
    strokes = [np.array([c, [32, 60]]), np.array([c, [22, 6]]), np.array([c, [42, 6]])]
    kps = [(32, 60, 1), (22, 6, 1), (42, 6, 1)] + ([(32, 34, 3)] if centre_keypoint else [])
    return Drawing(render((64, 64), strokes, 3.0), strokes, 3.0, kps)


# ---------------------------------------------------------------------------------------------
# Junctions and corners
# ---------------------------------------------------------------------------------------------

def test_line_is_one_path_between_its_endpoints():
    d = synthetic.line()
    art, _ = _run(d)
    assert _pairs(art) == [(0, 1)]
    p = art.data["paths"][0]
    assert p["end_types"] == [1, 1]
    np.testing.assert_allclose([p["xy"][0], p["xy"][-1]], [d.keypoints[0][:2], d.keypoints[1][:2]], atol=1e-5)


def test_x_gives_two_crossing_paths_between_opposite_ends():
    d = synthetic.cross()       # keypoints: stroke A ends 0, 1; stroke B ends 2, 3; centre 4
    art, _ = _run(d)
    paths = {tuple(sorted(p["end_keypoints"])): p for p in art.data["paths"]}
    assert (0, 1) in paths and (2, 3) in paths
    assert paths[(0, 1)]["through_keypoints"] == [4] and paths[(2, 3)]["through_keypoints"] == [4]
    assert paths[(0, 1)]["component"] != paths[(2, 3)]["component"]   # disjoint branches, no turn possible
    assert not {(0, 2), (0, 3), (1, 2), (1, 3)} & set(paths)
    # The keypoint maps to one key vertex per branch, and the halves end on it.
    kv = [k for k in art.data["key_vertices"] if k["keypoint"] == 4]
    assert len(kv) == 2 and kv[0]["component"] != kv[1]["component"]
    assert {(0, 4), (1, 4), (2, 4), (3, 4)} <= set(paths)


def test_t_gives_the_bar_and_the_stem_ending_on_it():
    d = synthetic.tee()         # bar ends 0, 1; stem end 2; T keypoint 3
    art, _ = _run(d)
    pairs = _pairs(art)
    assert (2, 3) in pairs                                  # the stem ends at the T keypoint
    stem = next(p for p in art.data["paths"] if tuple(sorted(p["end_keypoints"])) == (2, 3))
    end = stem["xy"][0 if stem["end_keypoints"][0] == 3 else -1]
    np.testing.assert_allclose(end, d.keypoints[3][:2], atol=1e-5)
    assert (0, 3) in pairs and (1, 3) in pairs              # the bar is split at the keypoint ...
    bar = [p for p in art.data["paths"] if tuple(sorted(p["end_keypoints"])) == (0, 1)]
    assert len(bar) == 1 and bar[0]["through_keypoints"] == [3]   # ... and also offered whole
    assert (0, 2) not in pairs and (1, 2) not in pairs      # the stem never turns into the bar


def test_without_pass_through_x_paths_stop_at_the_junction():
    art, _ = _run(synthetic.cross(), pass_through_junctions=False)
    assert sorted(_pairs(art)) == [(0, 4), (1, 4), (2, 4), (3, 4)]


def test_y_with_keypoint_gives_three_paths_meeting_at_the_centre():
    d = synthetic.wye()         # tips 0, 1, 2; centre 3
    art, _ = _run(d)
    assert sorted(_pairs(art)) == [(0, 3), (1, 3), (2, 3)]
    for p in art.data["paths"]:
        assert 3 in p["end_keypoints"] and p["through_keypoints"] == []


def test_y_junction_turn_test_forbids_branch_to_branch():
    art, _ = _run(_fork(centre_keypoint=False))   # stem tip 0, branch tips 1, 2
    assert sorted(_pairs(art)) == [(0, 1), (0, 2)]
    assert _uncovered(art, synthetic_inputs(_fork(False))) == 0
    # The test is what removes it: allowing every turn brings the branch-to-branch path back.
    art, _ = _run(_fork(centre_keypoint=False), turn_min_cos=-1.0)
    assert (1, 2) in _pairs(art)


def _merged_hairpin_inputs() -> dict:
    """A narrow Λ whose arms merge below its tip, traced as a Y reached over edges *across* the band.

    Corner 0 at the tip (32, 6); endpoints 1 and 2 at the feet.  The stem runs down the merged part
    to the Y vertex (32, 16); each arm leaves it by a 3 px edge across the band, whose vertices follow
    the band's (vertical) root, as the traced graph does where two strokes share one band.
    """
    strokes = [np.array([[32.0, 6.0], [32.0, 16.0]]), np.array([[32.0, 16.0], [29.0, 16.0], [22.0, 60.0]]),
               np.array([[32.0, 16.0], [35.0, 16.0], [42.0, 60.0]])]
    d = Drawing(render((64, 64), strokes, 3.0), strokes, 3.0, [(32, 6, 5), (22, 60, 1), (42, 60, 1)])
    inputs = synthetic_inputs(d)
    g = inputs["graph"]
    xy = np.asarray(g["vertex_xy"])
    root = np.asarray(g["vertex_root"]).copy()
    root[np.abs(xy[:, 1] - 16.0) < 0.6] = 1j
    inputs["graph"] = Artifact(arrays={**g.arrays, "vertex_root": root.astype(np.complex64)}, data=g.data)
    return inputs


def test_y_turn_test_sees_past_edges_across_a_merged_band():
    # Measured over 3 px of arc, the motion into the Y from either arm is the step across the band:
    # zero, so "no information" allowed the U-turn foot -> Y -> other foot, a candidate running down
    # both arms; chosen, it doubled an arm (cr_test_193_pencil).  The probe now runs on until it has
    # slid turn_probe_px along the traced curves.
    inputs = _merged_hairpin_inputs()
    art = run(CFG, **inputs)
    assert sorted(_pairs(art)) == [(0, 1), (0, 2)]
    assert _uncovered(art, inputs) == 0
    art = run({**CFG, "turn_probe_max_px": 0.0}, **inputs)     # plain 3 px of arc: the U-turn is back
    assert (1, 2) in _pairs(art)


def test_endpoint_beside_another_stroke_gets_one_key_vertex_on_its_own_tip():
    # A stem ending 2.5 px short of a bar (an end that almost touches): the bands merge, and the
    # bar's centre line is within the keypoint radius of the stem's endpoint.
    bar, stem = np.array([[8.0, 30.0], [56.0, 30.0]]), np.array([[32.0, 58.0], [32.0, 32.5]])
    kps = [(8, 30, 1), (56, 30, 1), (32, 58, 1), (32, 32.5, 1)]
    d = Drawing(render((64, 64), [bar, stem], 3.0), [bar, stem], 3.0, kps)
    art, inputs = _run(d)
    kv = [k for k in art.data["key_vertices"] if k["keypoint"] == 3]
    assert len(kv) == 1
    assert sorted(_pairs(art)) == [(0, 1), (2, 3)]          # the bar is not cut at the stem's end
    assert _uncovered(art, inputs) == 0


def test_paths_run_through_an_endpoint_on_a_passing_stroke_without_moving_to_it():
    # A detector endpoint 1.5 px off a line's centre, with no tip near: its key vertex is on the line.
    line = np.array([[8.0, 30.0], [56.0, 30.0]])
    d = Drawing(render((64, 64), [line], 3.0), [line], 3.0, [(8, 30, 1), (56, 30, 1), (32, 31.5, 1)])
    art, _ = _run(d)
    whole = [p for p in art.data["paths"] if sorted(p["end_keypoints"]) == [0, 1]]
    assert len(whole) == 1 and whole[0]["through_keypoints"] == [2]
    assert np.abs(np.array(whole[0]["xy"])[:, 1] - 30.0).max() < 1e-6   # not pulled onto the keypoint
    halves = [p for p in art.data["paths"] if 2 in p["end_keypoints"]]
    assert len(halves) == 2 and all(np.allclose(p["xy"][p["end_keypoints"].index(2) * -1], [32, 31.5])
                                    for p in halves)
    art, _ = _run(d, pass_through_endpoints=False)
    assert sorted(_pairs(art)) == [(0, 2), (1, 2)]


def test_zigzag_splits_at_its_corners():
    d = synthetic.zigzag()      # ends 0, 1; corners 2..6 in order along the stroke
    art, _ = _run(d)
    order = [0, 2, 3, 4, 5, 6, 1]
    expected = sorted(tuple(sorted(p)) for p in zip(order[:-1], order[1:]))
    assert sorted(_pairs(art)) == expected
    assert all(p["through_keypoints"] == [] for p in art.data["paths"])
    for p in art.data["paths"]:
        types = sorted(p["end_types"])
        assert types in ([1, 5], [5, 5])


def test_closed_loop_without_keypoints_is_covered():
    d = synthetic.circle()
    art, inputs = _run(d)
    assert len(art.data["paths"]) >= 1
    assert all(p["end_types"] == [0, 0] and p["end_keypoints"] == [-1, -1] for p in art.data["paths"])
    assert _uncovered(art, inputs) == 0
    assert art.data["counts"]["loop_a_paths"] >= 1         # the second half came from the coverage loop


def test_loop_with_one_corner_keypoint_is_covered():
    d = synthetic.circle()
    x, y = d.strokes[0][0]
    art, inputs = _run(d, keypoints=[(x, y, 5)])
    assert _uncovered(art, inputs) == 0
    assert all(0 in p["end_keypoints"] for p in art.data["paths"])


def test_a_chain_only_longer_paths_use_keeps_one_past_the_per_pair_cap():
    """Two corners on a circle join by a short and a long arc: with one path kept per pair of key
    vertices the long arc used to have no candidate at all (both its ends are key vertices, so no
    synthetic key vertex could be promoted) and a whole stroke was missing from the output."""
    d = synthetic.circle()
    ring = d.strokes[0]
    a, b = ring[0], ring[len(ring) * 100 // 360]
    art, inputs = _run(d, keypoints=[(a[0], a[1], 5), (b[0], b[1], 5)], max_paths_per_pair=1)
    assert _uncovered(art, inputs) == 0
    assert art.data["counts"]["band_pixels_covered"] == art.data["counts"]["band_pixels"]
    assert sorted(_pairs(art)) == [(0, 1), (0, 1)]


def test_loop_hanging_from_a_junction_is_a_closed_path():
    """A lollipop: the coverage loop walks round the loop back to its junction key vertex."""
    t = np.linspace(0, 2 * np.pi, 120)
    loop = np.stack([32 + 14 * np.sin(t), 30 - 14 * (1 - np.cos(t))], axis=1)
    loop[-1] = loop[0]
    stem = np.array([[32, 30], [32, 60.0]])
    d = Drawing(render((64, 64), [loop, stem], 3.0), [loop, stem], 3.0, [(32, 30, 3), (32, 60, 1)])
    art, inputs = _run(d)
    assert sorted(_pairs(art)) == [(0, 0), (0, 1)]
    closed = next(p for p in art.data["paths"] if p["end_keypoints"] == [0, 0])
    assert closed["vertices"][0] == closed["vertices"][-1] and closed["length"] > 80
    assert art.data["counts"]["loop_a_paths"] == 1 and _uncovered(art, inputs) == 0


def test_missed_endpoint_becomes_a_synthetic_key_vertex():
    d = synthetic.wye()
    kps = [k for i, k in enumerate(d.keypoints) if i != 2]     # drop one tip: a missed keypoint
    art, inputs = _run(d, keypoints=kps)
    assert art.data["counts"]["loop_b_paths"] == 1
    synth = [k for k in art.data["key_vertices"] if k["keypoint"] == -1]
    assert len(synth) == 1
    np.testing.assert_allclose(synth[0]["xy"], d.strokes[2][1], atol=1.5)
    assert _uncovered(art, inputs) == 0


@pytest.mark.parametrize("make", [synthetic.line, synthetic.cross, synthetic.tee, synthetic.wye, synthetic.vee,
                                  synthetic.zigzag, synthetic.circle, synthetic.example_drawing,
                                  lambda: _fork(False), lambda: ladder(12)],
                         ids=["line", "cross", "tee", "wye", "vee", "zigzag", "circle", "example", "fork", "ladder"])
def test_every_band_pixel_is_covered_by_some_path(make):
    d = make()
    art, inputs = _run(d)
    assert _uncovered(art, inputs) == 0
    assert art.data["counts"]["band_pixels_covered"] == art.data["counts"]["band_pixels"]


# ---------------------------------------------------------------------------------------------
# Artifact contract, rendering, bad input
# ---------------------------------------------------------------------------------------------

def test_artifact_follows_the_contract():
    d = synthetic.tee()
    art, inputs = _run(d)
    json.dumps(art.data)
    cov = unpack_ragged(art["coverage"], art["coverage_offsets"])
    assert art["coverage"].dtype == np.int32 and len(cov) == len(art.data["paths"])
    mask = inputs["prep"]["mask"].ravel()
    nv = len(inputs["graph"]["vertex_xy"])
    for p, px in zip(art.data["paths"], cov):
        assert set(p) >= {"id", "component", "vertices", "xy", "widths", "interest_dist", "end_types",
                          "end_keypoints"}
        n = len(p["vertices"])
        assert len(p["xy"]) == len(p["widths"]) == len(p["interest_dist"]) == n >= 2
        assert all(0 <= v < nv for v in p["vertices"])
        assert p["interest_dist"][0] == 0 and p["interest_dist"][-1] == 0
        assert min(p["interest_dist"]) >= 0
        assert np.all(mask[px]) and np.all(np.diff(px) > 0)
        for k, xy in zip(p["end_keypoints"], (p["xy"][0], p["xy"][-1])):
            np.testing.assert_allclose(xy, d.keypoints[k][:2], atol=1e-5)
    assert [p["id"] for p in art.data["paths"]] == list(range(len(art.data["paths"])))
    for kv in art.data["key_vertices"]:
        assert set(kv) >= {"vertex", "keypoint", "type", "xy", "component"}
    assert len(art.data["steiner_edges"]) == len(art["steiner_segments"]) > 0


def test_interest_distance_grows_away_from_the_ends():
    art, _ = _run(synthetic.line())
    dist = np.array(art.data["paths"][0]["interest_dist"])
    mid = len(dist) // 2
    assert dist[mid] == pytest.approx(22.0, abs=1.0)
    assert np.all(np.diff(dist[:mid]) > 0)


def test_render_shows_key_vertices_and_paths():
    d = synthetic.tee()
    art, _ = _run(d)
    rgb = render_topology(d.grey, art, scale=4)
    assert rgb.shape == (d.grey.shape[0] * 4, d.grey.shape[1] * 4, 3) and rgb.dtype == np.uint8
    flat = rgb.reshape(-1, 3)
    assert np.any(np.all(flat == (30, 90, 255), axis=1))      # an endpoint disc
    assert np.any(np.all(flat == (255, 140, 0), axis=1))      # the junction disc
    assert len(np.unique(flat, axis=0)) > 20


def test_empty_graph_gives_no_paths():
    d = synthetic.line()
    inputs = synthetic_inputs(d)
    g = inputs["graph"]
    for name in ("vertex_xy", "vertex_width", "vertex_root", "vertex_flags", "edges"):
        g.arrays[name] = g.arrays[name][:0]
    art = run(CFG, **inputs)
    assert art.data["paths"] == [] and len(art["coverage_offsets"]) == 1


def test_bad_input_raises_input_error():
    inputs = synthetic_inputs(synthetic.line())
    with pytest.raises(InputError):
        run({**CFG, "unknown_key": 1}, **inputs)
    with pytest.raises(InputError):
        run(CFG, prep=inputs["prep"], graph=inputs["graph"], keypoints=inputs["keypoints"])
    inputs["graph"].arrays["edges"] = np.array([[0, 10_000]], np.int32)
    with pytest.raises(InputError):
        run(CFG, **inputs)


# ---------------------------------------------------------------------------------------------
# Building blocks and scale
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("method", ["mehlhorn", "kou"])
def test_steiner_tree_is_a_pruned_tree_as_good_as_networkx(method):
    import scipy.sparse as sp

    rng = np.random.default_rng(3)
    g = nx.random_geometric_graph(150, 0.15, seed=3)
    g = g.subgraph(max(nx.connected_components(g), key=len)).copy()
    g = nx.convert_node_labels_to_integers(g)
    pos = nx.get_node_attributes(g, "pos")
    for u, v in g.edges:
        g[u][v]["weight"] = float(np.hypot(*(np.subtract(pos[u], pos[v])))) + 1e-9
    terminals = rng.choice(g.number_of_nodes(), 12, replace=False)
    csr = sp.csr_matrix(nx.to_scipy_sparse_array(g, weight="weight", format="csr"))
    tree = steiner_tree(csr, terminals, method)
    t = nx.Graph()
    t.add_weighted_edges_from((int(u), int(v), g[int(u)][int(v)]["weight"]) for u, v in tree)
    assert nx.is_tree(t) and set(terminals.tolist()) <= set(t.nodes)
    assert all(n in set(terminals.tolist()) for n in t.nodes if t.degree(n) == 1)
    ref = nx.algorithms.approximation.steiner_tree(g, terminals.tolist(), weight="weight", method=method)
    ours, theirs = t.size(weight="weight"), ref.size(weight="weight")
    assert ours <= 1.05 * theirs


def test_many_cycles_and_terminals_do_not_give_up():
    """A ladder (one component, many cycles, no keypoint inside) and a zigzag with 120 corners."""
    art, inputs = _run(ladder(30))
    assert art.data["counts"]["loop_a_paths"] >= 29          # every rung closes a cycle the tree misses
    assert _uncovered(art, inputs) == 0
    n = 121
    pts = np.stack([10 + 10.0 * np.arange(n), np.where(np.arange(n) % 2 == 0, 46.0, 18.0)], axis=1)
    kps = [(*pts[0], 1), (*pts[-1], 1)] + [(*p, 5) for p in pts[1:-1]]
    z = Drawing(render((64, int(pts[-1, 0]) + 10), [pts], 3.0), [pts], 3.0, kps)
    art, inputs = _run(z)
    assert len(art.data["key_vertices"]) == n
    assert len(art.data["paths"]) == n - 1
    assert _uncovered(art, inputs) == 0


# ---------------------------------------------------------------------------------------------
# Integration: through the real prep → field → graph stages
# ---------------------------------------------------------------------------------------------

def _real_inputs(drawing, keypoints=None):
    from stages import field as field_stage
    from stages import graph as graph_stage
    from stages import prep as prep_stage

    conf = {n: yaml.safe_load((ROOT / "conf" / n / "default.yaml").read_text()) for n in ("prep", "field", "graph")}
    prep = prep_stage.run(conf["prep"], image_bytes=drawing.png_bytes(), image_name="synthetic.png")
    field = field_stage.run(conf["field"], prep=prep)
    graph = graph_stage.run(conf["graph"], prep=prep, field=field)
    kps = synthetic_inputs(drawing, keypoints=keypoints)["keypoints"]
    return {"prep": prep, "field": field, "graph": graph, "keypoints": kps}


def _run_real(drawing, keypoints=None):
    inputs = _real_inputs(drawing, keypoints)
    return run(CFG, **inputs), inputs


def test_real_graph_x_t_y():
    art, inputs = _run_real(synthetic.cross())
    through = {tuple(sorted(p["end_keypoints"])) for p in art.data["paths"] if p["through_keypoints"] == [4]}
    assert through == {(0, 1), (2, 3)}
    assert _uncovered(art, inputs) == 0

    art, inputs = _run_real(synthetic.tee())
    pairs = _pairs(art)
    assert {(2, 3), (0, 3), (1, 3)} <= set(pairs) and not {(0, 2), (1, 2)} & set(pairs)
    assert _uncovered(art, inputs) == 0

    art, inputs = _run_real(synthetic.wye())
    assert sorted(_pairs(art)) == [(0, 3), (1, 3), (2, 3)]
    assert _uncovered(art, inputs) == 0


@pytest.mark.parametrize("angle", [0.0, 30.0, 45.0])
def test_real_graph_y_keypoint_is_never_passed_through(angle):
    # The graph traces these wyes as a chain through two branches plus the third one apart: the
    # chain's key vertex is passable, but turning from branch to branch there is not going straight.
    art, inputs = _run_real(synthetic.wye(angle=angle, width=2.0 if angle < 45 else 3.0))
    assert all(p["through_keypoints"] == [] for p in art.data["paths"])
    assert {(0, 3), (1, 3), (2, 3)} <= set(_pairs(art))
    assert _uncovered(art, inputs) == 0
    # A fork whose stem continues into both branches alike is a Y as well; an X still passes.
    art, _ = _run_real(_fork(centre_keypoint=True))
    assert all(p["through_keypoints"] == [] for p in art.data["paths"])
    art, _ = _run_real(synthetic.cross(angle1=10.0, angle2=55.0))
    assert sum(p["through_keypoints"] == [4] for p in art.data["paths"]) == 2


def test_real_graph_turn_test_and_corners():
    art, inputs = _run_real(_fork(centre_keypoint=False))
    assert sorted(_pairs(art)) == [(0, 1), (0, 2)]
    assert _uncovered(art, inputs) == 0

    art, inputs = _run_real(synthetic.zigzag())
    order = [0, 2, 3, 4, 5, 6, 1]
    assert sorted(_pairs(art)) == sorted(tuple(sorted(p)) for p in zip(order[:-1], order[1:]))
    assert _uncovered(art, inputs) == 0


def test_real_graph_example_without_keypoints_is_covered():
    art, inputs = _run_real(synthetic.example_drawing())
    assert _uncovered(art, inputs) == 0
    assert all(p["end_types"] == [0, 0] for p in art.data["paths"])


def test_coverage_by_pixel_boxes_equals_the_kd_tree_query():
    """The band's capsule coverage scans each capsule's pixel box (in chunks); it must give exactly the
    members the KD-tree query gives, for any chunk size, segments leaving the image included."""
    from scipy.spatial import cKDTree

    from stages.topology.coverage import band_capsule_members, band_pixels, capsule_members

    rng = np.random.default_rng(3)
    mask = rng.random((60, 80)) < 0.4
    a = rng.uniform(-5, 85, (300, 2))
    b = a + rng.normal(0, 3, (300, 2))
    ra, rb = rng.uniform(0.3, 6, 300), rng.uniform(0.3, 6, 300)
    pts, _ = band_pixels(mask)
    flat, off = capsule_members(pts, cKDTree(pts), a, b, ra, rb)
    assert len(flat) > 1000
    for chunk in (1, 500, 10**7):
        f2, o2 = band_capsule_members(mask, a, b, ra, rb, chunk=chunk)
        assert np.array_equal(f2, flat) and np.array_equal(o2, off)
    empty, offsets = band_capsule_members(np.zeros((5, 5), bool), a, b, ra, rb)
    assert len(empty) == 0 and len(offsets) == 301 and not offsets.any()


def _bow(p0, p1, bulge, n: int = 24) -> np.ndarray:
    """A quadratic arc from p0 to p1 whose middle is pushed by ``bulge``."""
    t = np.linspace(0, 1, n)[:, None]
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    mid = (p0 + p1) / 2 + np.asarray(bulge, float)
    return (1 - t) ** 2 * p0 + 2 * t * (1 - t) * mid + t ** 2 * p1


def test_a_chain_whose_only_paths_turn_through_a_junction_is_still_offered():
    """A teardrop: junction 0 at its sharp bottom, corner 1 at its top, a short and a long side.

    With one path per pair the long side is reached only by the loop 1 → short → 0 → long → 1, which
    turns sharply through junction 0 and is rejected by the pass-through test; the long side must still
    be a candidate (val_qd_broccoli_1_clean lost a 223-px loop this way)."""
    j, b = (40.0, 70.0), (40.0, 14.0)
    strokes = [_bow(j, b, (-20, 0)), _bow(j, b, (44, 0))]
    kps = [(*j, 3), (*b, 5)]
    d = Drawing(render((96, 96), strokes, 3.0), strokes, 3.0, kps)
    art, inputs = _run(d, keypoints=kps, max_paths_per_pair=1)
    assert art.data["counts"]["pass_through_rejected"] >= 1
    assert _uncovered(art, inputs) == 0
    assert sorted(round(p["length"]) > 70 for p in art.data["paths"]) == [False, True]   # both sides
    assert art.data["counts"]["uncovered_chains_offered"] == 1
