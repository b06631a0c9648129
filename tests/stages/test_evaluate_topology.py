"""Topology metrics by valence on hand-built curve sets (stages/evaluate/curve_topology.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from pipeline.engine.config import CONF_DIR as REPO_CONF
from stages.config import from_section
from stages.evaluate.curve_topology import TopologyParams, benchmark_gap_statistics, compare_topology, curve_topology
from stages.evaluate.matching import match_one_to_one, prf1
from tests.conftest import shared_path

P = from_section(TopologyParams, yaml.safe_load((REPO_CONF / "bench" / "default.yaml").read_text())["topology"],
                 "bench.topology")
W = 2.0  # stroke width: meet radius r = 2, match radius 5

BAR = np.array([[10.0, 50.0], [90.0, 50.0]])


def topo(*curves, width=W):
    return curve_topology([np.asarray(c, dtype=float) for c in curves], width, P)


def _has(points, xy, tol=1.0):
    return len(points) > 0 and np.min(np.hypot(*(np.asarray(points) - xy).T)) <= tol


def test_tee_drawn_as_two_curves_is_one_junction_and_three_free_ends():
    t = topo(BAR, [[50, 50.5], [50, 90]])
    assert len(t.junctions) == 1 and _has(t.junctions, (50, 50))
    assert t.junction_valence.tolist() == [3]
    assert len(t.free_ends) == 3
    for xy in ((10, 50), (90, 50), (50, 90)):
        assert _has(t.free_ends, xy)
    assert len(t.gaps) == 0 and t.dangling == [] and t.duplicated_length == 0


def test_three_pixel_gap_is_a_junction_gap_not_a_junction():
    t = topo(BAR, [[50, 53], [50, 90]])
    assert len(t.junctions) == 0
    assert len(t.free_ends) == 4
    assert t.gaps.shape == (1, 3)
    assert t.gaps[0, :2] == pytest.approx([50, 53]) and t.gaps[0, 2] == pytest.approx(3.0)


def test_gap_beyond_the_limit_is_just_a_free_end():
    t = topo(BAR, [[50, 60], [50, 90]])  # 10 px > gap_max = max(6, 3 w)
    assert len(t.gaps) == 0 and len(t.free_ends) == 4


def test_crossing_is_a_junction_but_a_shallow_touch_is_not():
    x = topo(BAR, [[50, 10], [50, 90]])
    assert len(x.junctions) == 1 and _has(x.junctions, (50, 50)) and x.junction_valence.tolist() == [4]
    assert len(x.free_ends) == 4
    d = np.array([np.cos(np.radians(20)), np.sin(np.radians(20))])
    shallow = topo(BAR, [[50, 50] - 30 * d, [50, 50] + 30 * d])  # crosses at 20° < 37°
    assert len(shallow.junctions) == 0


def test_corner_of_two_curves_and_closed_loop_are_continuations():
    corner = topo([[10, 10], [50, 10]], [[50, 10], [50, 60]])
    assert len(corner.continuations) == 1 and len(corner.junctions) == 0 and len(corner.free_ends) == 2
    sloppy = topo([[10, 10], [52, 10]], [[50.5, 11.5], [50, 60]])  # overshoot of 2 px: still an L
    assert len(sloppy.junctions) == 0 and len(sloppy.free_ends) == 2
    th = np.linspace(0, 2 * np.pi, 100)
    loop = topo(np.c_[50 + 30 * np.cos(th), 50 + 30 * np.sin(th)])
    assert len(loop.free_ends) == 0 and len(loop.continuations) == 1 and len(loop.junctions) == 0


def test_overshooting_stroke_end_makes_a_tee():
    # a stroke crossing the end region of another, 8 px (> 2r of arc) from that end: T, not L
    t = topo([[10, 10], [58, 10]], [[50, 10.5], [50, 60]])
    assert len(t.junctions) == 1 and len(t.free_ends) == 3


def test_wye_and_self_touching_six():
    y = topo([[50, 50], [50, 90]], [[50, 50], [20, 20]], [[50, 50], [80, 20]])
    assert len(y.junctions) == 1 and y.junction_valence.tolist() == [3] and len(y.free_ends) == 3
    th = np.linspace(0, 2 * np.pi, 100)
    six = np.r_[[[80, 90]], np.c_[50 + 30 * np.cos(th), 50 - 30 * np.sin(th)]]  # tail, then a loop back
    s = topo(six)
    assert len(s.junctions) == 1 and _has(s.junctions, (80, 50), tol=2) and len(s.free_ends) == 1


def test_short_dangling_branch_at_a_junction():
    spur = topo(BAR, [[50, 50], [50, 90]], [[30, 50], [30, 56]])
    assert spur.dangling == [2]
    assert len(spur.gaps) == 0  # the spur points away from the bar it hangs on
    long_branch = topo(BAR, [[50, 50], [50, 90]], [[30, 50], [30, 80]])
    assert long_branch.dangling == []


def test_duplicated_overlapping_piece_is_measured_once():
    assert topo(BAR).duplicated_length == 0
    dup = topo(BAR, BAR + [0, 1])
    # 80 px doubled; the 2r-wide exclusion around the two meeting points at each end removes 2 x 4 px
    assert dup.duplicated_length == pytest.approx(72.0, abs=1.0)
    partial = topo(BAR, [[30, 51], [60, 51]])
    assert partial.duplicated_length == pytest.approx(30.0 - 8.0, abs=1.0)


def test_degenerate_inputs():
    assert topo().counts()["curves"] == 0
    t = topo([[5, 5]], [[1, 1], [1, 1]], [[np.nan, 0], [3, 3]], BAR)
    assert t.n_curves == 1 and len(t.free_ends) == 2


def test_compare_topology_scores():
    gt = topo(BAR, [[50, 50], [50, 90]])
    shifted = topo(BAR + [0, 2], [[50, 52], [50, 90]])
    res = compare_topology(shifted, gt, W, P)
    assert res["endpoint_f1"] == 1.0 and res["junction_f1"] == 1.0
    missing_stem = compare_topology(topo(BAR), gt, W, P)
    assert missing_stem["junction_f1"] == 0.0 and missing_stem["junction_recall"] == 0.0
    assert missing_stem["endpoint_precision"] == 1.0 and missing_stem["endpoint_recall"] == pytest.approx(2 / 3)
    assert missing_stem["gt_junctions"] == 1 and missing_stem["junctions"] == 0


def test_one_to_one_matching_maximises_pairs():
    # nearest-first greedy would pair (0,0) with (2,0) and leave two points unmatched
    pairs = match_one_to_one(np.array([[0.0, 0], [4, 0]]), np.array([[2.0, 0], [-2.5, 0]]), radius=3)
    assert sorted(map(tuple, pairs.tolist())) == [(0, 1), (1, 0)]
    assert len(match_one_to_one(np.zeros((0, 2)), np.ones((3, 2)), 5)) == 0
    assert prf1(0, 0, 0) == (1.0, 1.0, 1.0)
    assert prf1(0, 2, 0)[2] == 0.0
    assert prf1(3, 1, 2) == pytest.approx((0.75, 0.6, 6 / 9))


def test_benchmark_gap_statistics():
    # stem end 3 px below the bar: its nearest other end is far, the bar itself 3 px away
    s, n = benchmark_gap_statistics([BAR, np.array([[50, 53.0], [50, 90]])], long_edge=100)
    # bar ends: nearest other end (50, 53) at 40.1 px, no point of the stem nearer; the stem's far
    # end: 56.6 px to the bar's ends, but 40 px to the bar itself
    ends = [np.hypot(40, 3), np.hypot(40, 3), 3.0, 40.0]
    assert s == pytest.approx(sum(ends) / 100, rel=1e-6)
    assert n == 4


@pytest.mark.shared
def test_ground_truth_extraction_agrees_with_dataset_labels():
    # the labels of realvec_dev follow a related rule (metrics.md §4.2): agreement should be high
    root = shared_path("data", "realvec_dev")
    f1s = []
    for name in ("cr_test_161_clean", "qd_bear_00_clean", "tu_angel_161_pencil", "qd_cat_01_pencil"):
        d = json.loads((root / f"{name}.json").read_text())
        t = curve_topology([np.array(s) for s in d["strokes"]], d["width"], P)
        for mine, theirs in ((t.free_ends, d["endpoints"]), (t.junctions, d["junctions"])):
            theirs = np.asarray(theirs, dtype=float).reshape(-1, 2)
            tp = len(match_one_to_one(mine, theirs, max(5, d["width"])))
            f1s.append(prf1(tp, len(mine) - tp, len(theirs) - tp)[2])
    assert np.mean(f1s) > 0.85
