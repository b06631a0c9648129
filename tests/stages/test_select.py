"""Tests of the path-selection stage (binary program with CBC and its fallback) on hand-made inputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from stages import select
from stages.artifact import Artifact, pack_ragged
from stages.config import from_section
from stages.errors import InputError
from stages.select import stage as select_code  # where select_paths looks solve_mip up

ROOT = Path(__file__).resolve().parents[2]
CFG = yaml.safe_load((ROOT / "conf" / "select" / "default.yaml").read_text())


def _inputs(paths, coverage, energies, key_types):
    """Topology and flow artifacts: ``paths`` = list of (end_keypoints, through_keypoints)."""
    plist = [{"id": 10 + j, "component": 0, "vertices": [], "xy": [[0, 0], [1, 1]], "widths": [1, 1],
              "interest_dist": [0, 0], "end_types": [key_types.get(k, 0) for k in ends],
              "end_keypoints": list(ends), "through_keypoints": list(through)}
             for j, (ends, through) in enumerate(paths)]
    flat, off = pack_ragged([np.asarray(c, np.int32) for c in coverage], np.int32)
    kv = [{"vertex": k, "keypoint": k, "type": t, "xy": [0, 0], "component": 0} for k, t in key_types.items()]
    topo = Artifact(arrays={"coverage": flat, "coverage_offsets": off}, data={"paths": plist, "key_vertices": kv})
    return {"prep": Artifact(data={"height": 10, "width": 10}), "topology": topo,
            "flow": Artifact(data={"energies": list(map(float, energies)),
                                   "energies_initial": list(map(float, energies))})}


def _run(paths, coverage, energies, key_types, **over):
    return select.run({**CFG, **over}, **_inputs(paths, coverage, energies, key_types))


def test_picks_the_cheaper_of_two_overlapping_candidates():
    # Two candidates between the same endpoints covering the same stroke (plus a pixel each).
    art = _run([((0, 1), ()), ((0, 1), ())], [range(0, 40), range(1, 41)], [50.0, 42.0], {0: 1, 1: 1})
    assert art.data["status"] == "optimal"
    # 0 covers pixel 0 only, 1 covers pixel 40 only: both needed.
    assert art.data["chosen"] == [10, 11]
    art = _run([((0, 1), ()), ((0, 1), ())], [range(0, 40), range(0, 40)], [50.0, 42.0], {0: 1, 1: 1})
    assert art.data["chosen"] == [11]
    assert art.data["objective"] == pytest.approx(42.0 + CFG["curve_cost"])
    assert art.notes == []                                   # proven optimal: nothing to say


def test_valence_of_a_corner_forces_a_second_path():
    # Path 0 covers everything, path 1 (expensive, subset coverage) is needed for the corner's valence 2.
    paths = [((0, 1), ()), ((1, 2), ())]
    art = _run(paths, [range(0, 30), range(10, 20)], [10.0, 100.0], {0: 1, 1: 5, 2: 1})
    assert art.data["chosen"] == [10, 11]
    # As an endpoint, keypoint 1 needs only one path; keypoint 2 then still needs path 1.
    art = _run(paths, [range(0, 30), range(10, 20)], [10.0, 100.0], {0: 1, 1: 1})
    assert art.data["chosen"] == [10]


def test_junction_valence_counts_through_paths_twice():
    # An X: two full strokes through keypoint 4, or four halves ending at it.
    paths = [((0, 1), (4,)), ((2, 3), (4,)), ((0, 4), ()), ((4, 1), ()), ((2, 4), ()), ((4, 3), ())]
    cov = [range(0, 20), range(20, 40), range(0, 10), range(10, 20), range(20, 30), range(30, 40)]
    types = {0: 1, 1: 1, 2: 1, 3: 1, 4: 3}
    art = _run(paths, cov, [19.0, 19.0, 10.0, 10.0, 10.0, 10.0], types, curve_cost=0.0)
    assert sorted(art.data["chosen"]) == [10, 11]
    art = _run(paths, cov, [21.0, 21.0, 10.0, 10.0, 10.0, 10.0], types, curve_cost=0.0)
    assert sorted(art.data["chosen"]) == [12, 13, 14, 15]


def test_a_stroke_passing_an_endpoint_does_not_end_there():
    # A line 0–1 with an endpoint keypoint 2 on it (a stroke starts beside the line), and that
    # stroke 2–3.  The line's halves end at 2 and together cost less than the whole line passing it.
    paths = [((0, 1), (2,)), ((0, 2), ()), ((2, 1), ()), ((2, 3), ())]
    cov = [range(0, 40), range(0, 20), range(20, 40), range(40, 50)]
    types = {0: 1, 1: 1, 2: 1, 3: 1}
    art = _run(paths, cov, [40.0, 19.0, 19.0, 10.0], types)
    assert sorted(art.data["chosen"]) == [10, 13]            # three ends at 2 would cost 2 × penalty
    assert art.data["objective"] == pytest.approx(50.0 + 2 * CFG["curve_cost"])
    art = _run(paths, cov, [40.0, 19.0, 19.0, 10.0], types, excess_penalty=0.0, curve_cost=0.0)
    assert sorted(art.data["chosen"]) == [11, 12, 13]
    # Passing by gives the endpoint no valence: the stroke that ends there is still required.
    art = _run(paths[:1] + paths[3:], [range(0, 40), range(10, 20)], [40.0, 30.0], types)
    assert sorted(art.data["chosen"]) == [10, 11]


def test_corner_ends_beyond_two_are_charged_and_branches_cap_junctions():
    p = from_section(select.SelectConfig, {**CFG, "cap_branches": True}, "select")
    paths = [{"end_keypoints": [0, 1]}, {"end_keypoints": [1, 2]}, {"end_keypoints": [1, 3]},
             {"end_keypoints": [4, 5], "through_keypoints": [6]}, {"end_keypoints": [7, 6]}]
    types = {0: 1, 1: 5, 2: 1, 3: 1, 4: 1, 5: 1, 6: 3, 7: 1}
    prob = select.build_problem(paths, [np.arange(3) + 3 * j for j in range(5)], np.ones(5), types, p,
                                branches={6: 2})
    assert prob.penalty(np.ones(5, bool)) == pytest.approx(p.excess_penalty)   # three ends at corner 1
    assert prob.penalty(np.array([1, 1, 0, 1, 1], bool)) == 0.0
    # Junction 6 has only two branches (a loop passes it): valence 2, not 3.
    assert prob.valence_capped[list(prob.keypoints).index(6)] == 2


def test_curve_cost_prefers_one_through_path_to_two_halves():
    # An X: the halves cost exactly as much as the through paths, until every curve costs extra.
    paths = [((0, 1), (4,)), ((2, 3), (4,)), ((0, 4), ()), ((4, 1), ()), ((2, 4), ()), ((4, 3), ())]
    cov = [range(0, 20), range(20, 40), range(0, 10), range(10, 20), range(20, 30), range(30, 40)]
    types = {0: 1, 1: 1, 2: 1, 3: 1, 4: 3}
    energies = [20.0, 20.0, 9.9, 10.0, 9.9, 10.0]
    assert sorted(_run(paths, cov, energies, types, curve_cost=0.0).data["chosen"]) == [12, 13, 14, 15]
    assert sorted(_run(paths, cov, energies, types, curve_cost=1.0).data["chosen"]) == [10, 11]


def test_every_covered_pixel_stays_covered():
    rng = np.random.default_rng(0)
    cov = [np.unique(rng.integers(0, 60, 25)) for _ in range(12)]
    paths = [((2 * j, 2 * j + 1), ()) for j in range(12)]
    energies = rng.uniform(5, 50, 12)
    art = _run(paths, cov, energies, {})
    chosen = [c - 10 for c in art.data["chosen"]]
    covered = set(np.concatenate([cov[j] for j in chosen]))
    assert covered == set(np.concatenate(cov))
    assert len(chosen) < 12


def test_identical_pixel_sets_give_one_constraint():
    p = from_section(select.SelectConfig, CFG, "select")
    prob = select.build_problem([{"end_keypoints": [-1, -1]}] * 3,
                                [np.arange(0, 10), np.arange(5, 10), np.arange(5, 12)], np.ones(3), {}, p)
    # Pixel sets: {0}: 0-4, {0,1,2}: 5-9, {2}: 10-11.
    assert prob.cover.shape[0] == 3
    assert sorted(prob.cover_pixels.tolist()) == [2, 5, 5]


def test_infeasible_program_uses_the_documented_fallback_not_all_curves():
    # A junction with only two path ends cannot have valence 3: infeasible without the cap.
    paths = [((0, 1), ()), ((1, 2), ()), ((0, 2), ()), ((0, 2), ())]
    cov = [range(0, 10), range(10, 20), range(0, 20), range(0, 10)]
    types = {0: 1, 1: 3, 2: 1}
    art = _run(paths, cov, [10.0, 10.0, 100.0, 30.0], types, cap_valence=False)
    assert art.data["status"].startswith("fallback: infeasible")
    assert art.data["chosen"] == [10, 11]        # the cheap pair; the expensive duplicates are pruned
    capped = _run(paths, cov, [10.0, 10.0, 100.0, 30.0], types)
    assert capped.data["status"] == "optimal" and capped.data["chosen"] == [10, 11]


@pytest.mark.parametrize("reason", ["no_solution", "solver_error: boom"])
def test_solver_failures_fall_back_and_report(monkeypatch, reason):
    monkeypatch.setattr(select_code, "solve_mip", lambda problem, params: (None, reason, None))
    art = _run([((0, 1), ()), ((0, 1), ())], [range(0, 40), range(0, 40)], [50.0, 42.0], {0: 1, 1: 1})
    assert art.data["status"] == f"fallback: {reason}"
    assert art.data["chosen"] == [11]
    # the guard (CBC's time limit, or a failure) says so in one line (issue 18 item 4)
    assert len(art.notes) == 1 and "not proven optimal" in art.notes[0] and "select.time_limit" in art.notes[0]


def test_a_time_limited_selection_says_so(monkeypatch):
    """CBC stopped by select.time_limit with an integer solution: used, and said to be unproven."""
    monkeypatch.setattr(select_code, "solve_mip", lambda problem, params: (np.array([False, True]), "feasible", 72.0))
    art = _run([((0, 1), ()), ((0, 1), ())], [range(0, 40), range(0, 40)], [50.0, 42.0], {0: 1, 1: 1})
    assert art.data["status"] == "feasible" and art.data["chosen"] == [11]
    assert art.notes == ["selection not proven optimal (feasible; CBC stops at select.time_limit = 20 s)"]


def test_a_violating_solver_answer_is_not_trusted(monkeypatch):
    monkeypatch.setattr(select_code, "solve_mip",
                        lambda problem, params: (np.zeros(len(problem.cost), bool), "optimal", 0.0))
    art = _run([((0, 1), ()), ((0, 1), ())], [range(0, 40), range(0, 40)], [50.0, 42.0], {0: 1, 1: 1})
    assert art.data["status"].startswith("fallback: optimal answer violates")
    assert art.data["chosen"] == [11]


def test_greedy_fallback_is_valid_and_minimal():
    rng = np.random.default_rng(3)
    p = from_section(select.SelectConfig, CFG, "select")
    paths = [{"end_keypoints": [int(a), int(b)]} for a, b in rng.integers(0, 6, (20, 2))]
    cov = [np.unique(rng.integers(0, 100, 30)) for _ in range(20)]
    prob = select.build_problem(paths, cov, rng.uniform(1, 10, 20), {k: [1, 3, 5][k % 3] for k in range(6)}, p)
    x = select.greedy_selection(prob)
    assert select.satisfies(prob, x)
    for j in np.flatnonzero(x):  # no chosen path is redundant
        y = x.copy()
        y[j] = False
        assert not select.satisfies(prob, y)


def test_run_contract_and_bad_input():
    art = _run([], [], [], {})
    assert art.data["chosen"] == [] and art.data["status"] == "empty"
    art = _run([((0, 1), ())], [range(5)], [3.0], {0: 1, 1: 1})
    json.dumps(art.data)
    assert set(art.data) >= {"chosen", "status", "objective"}
    inputs = _inputs([((0, 1), ())], [range(5)], [3.0, 4.0], {})
    with pytest.raises(InputError):
        select.run(CFG, **inputs)
    inputs = _inputs([((0, 1), ())], [range(5)], [float("nan")], {})
    with pytest.raises(InputError):
        select.run(CFG, **inputs)
    with pytest.raises(InputError):
        select.run({k: v for k, v in CFG.items() if k != "valence"}, **_inputs([], [], [], {}))


def test_independent_drawings_are_selected_as_each_alone(monkeypatch):
    """A page of two independent drawings in programs of at most 3 paths: each drawing is its own program,
    chosen as it is alone; with the default bound both are one program, the program of before."""
    one = ([((0, 1), ()), ((0, 1), ())], [range(0, 40), range(0, 40)], [50.0, 42.0], {0: 1, 1: 1})
    two = ([((2, 3), ()), ((3, 4), ()), ((2, 4), ())], [range(0, 10), range(10, 20), range(0, 20)],
           [10.0, 10.0, 15.0], {2: 1, 3: 5, 4: 1})
    page = (one[0] + two[0], list(one[1]) + [range(100 + c.start, 100 + c.stop) for c in two[1]],
            one[2] + two[2], {**one[3], **two[3]})
    sizes = []
    real = select_code.solve_mip
    monkeypatch.setattr(select_code, "solve_mip", lambda problem, params: (sizes.append(len(problem.cost)),
                                                                             real(problem, params))[1])
    alone = [[c - 10 for c in _run(*d).data["chosen"]] for d in (one, two)]
    sizes.clear()
    together = _run(*page)
    assert sizes == [5]                         # a few paths: one program, as before
    monkeypatch.setattr(select_code, "PROGRAM_PATHS", 3)
    sizes.clear()
    art = _run(*page)
    assert sizes == [2, 3]                      # one program per drawing, in order of their first path
    assert art.data["chosen"] == together.data["chosen"]
    assert art.data["chosen"] == [10 + c for c in alone[0]] + [12 + c for c in alone[1]]
    assert art.data["status"] == "optimal"
    assert art.data["objective"] == pytest.approx(sum(_run(*d).data["objective"] for d in (one, two)))
