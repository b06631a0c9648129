"""Tests of ``export.passes``: passes of the pen over one line become one centred curve (issue 55, item 2)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from stages import export, synthetic
from stages.artifact import Artifact, pack_ragged
from stages.export.passes import _near_pairs, merge_passes

ROOT = Path(__file__).resolve().parents[2]
CFG = yaml.safe_load((ROOT / "conf" / "export" / "default.yaml").read_text())
P = CFG["passes"]


def _merge(curves):
    return merge_passes(curves, P["max_gap_widths"], P["min_run_widths"], P["max_angle_deg"], P["end_slack_widths"])


def _curve(cid, pts, types=(1, 1), kps=(-1, -1), width=2.0):
    return {"id": cid, "points": np.asarray(pts, float), "end_types": list(types), "end_keypoints": list(kps),
            "parts": [cid], "width": width}


def _line(x0, x1, y, n=80):
    x = np.linspace(x0, x1, n)
    return np.c_[x, np.full(n, float(y))]


def _inputs(curves, shape=(100, 140), width=2.0):
    paths = [{"id": 100 + k, "component": 0, "vertices": [], "xy": np.asarray(c).tolist(),
              "widths": [width] * len(c), "interest_dist": [0.0] * len(c),
              "end_types": [1, 1], "end_keypoints": [2 * k, 2 * k + 1]} for k, c in enumerate(curves)]
    flat, off = pack_ragged([np.asarray(c, float) for c in curves], np.float64)
    return {"prep": Artifact(data={"height": shape[0], "width": shape[1]}),
            "topology": Artifact(data={"paths": paths}),
            "flow": Artifact(arrays={"curve_xy": flat.reshape(-1, 2), "curve_xy_offsets": off}),
            "select": Artifact(data={"chosen": [100 + k for k in range(len(curves))], "status": "optimal"})}


def test_a_doubled_stroke_is_one_centred_curve_in_the_export():
    # Two passes 1.5 widths apart, drawn in opposite directions, their ends 1–2 px apart: one line.
    a = _line(10, 120, 50)
    b = _line(12, 118, 53)[::-1]
    art = export.run(CFG, **_inputs([a, b]))
    curves = art.data["curves"]
    assert len(curves) == 1 and sorted(curves[0]["parts"]) == [100, 101]
    pts = np.asarray(curves[0]["points"])
    middle = pts[(pts[:, 0] > 20) & (pts[:, 0] < 110)]
    np.testing.assert_allclose(middle[:, 1], 51.5, atol=0.05)        # along the centre of the two
    assert pts[:, 0].min() <= 11.5 and pts[:, 0].max() >= 118.5       # to the ends of the passes
    off = json.loads(json.dumps(CFG))
    off["passes"]["enabled"] = False
    assert len(export.run(off, **_inputs([a, b])).data["curves"]) == 2


def test_three_passes_are_one_curve_at_their_centre():
    out = _merge([_curve(0, _line(10, 120, 50)), _curve(1, _line(11, 121, 52)), _curve(2, _line(9, 119, 54))])
    assert len(out) == 1 and sorted(out[0]["parts"]) == [0, 1, 2]
    mid = out[0]["points"][len(out[0]["points"]) // 2]
    assert abs(mid[1] - 52.0) < 0.1                                   # weighted by the passes, not 51 or 53


def test_a_stroke_that_doubles_back_is_one_curve_that_ends_at_the_turn():
    s = np.linspace(0.0, 100.0, 101)
    out_and_back = np.r_[np.c_[10 + s, np.full(101, 50.0)], np.c_[110 - s[1:61], np.full(60, 53.0)]]
    out = _merge([_curve(0, out_and_back, types=(1, 1), kps=(4, 5))])
    assert len(out) == 1
    pts = out[0]["points"]
    assert np.hypot(*(pts[0] - [10, 50])) < 0.5                       # the stroke's own start stays
    assert abs(pts[-1][0] - 110) < 2.5 and abs(pts[-1][1] - 51.5) < 1  # the end is the turn of the pen
    assert out[0]["end_keypoints"] == [4, -1] and out[0]["end_types"] == [1, 0]
    assert pts[:, 0].max() < 111


def test_the_retrace_of_two_curves_meeting_at_the_turn_is_one_curve():
    # The selection ended the way out and the way back at the turn (a corner keypoint both reach).
    way_out = _curve(0, _line(10, 110, 50, 101), types=(1, 5), kps=(1, 7))    # ... and it ends on the way out
    way_back = _curve(1, np.c_[np.linspace(110, 50, 61), np.linspace(53, 50.8, 61)], types=(5, 3), kps=(7, 9))
    out = _merge([way_out, way_back])
    assert len(out) == 1 and sorted(out[0]["parts"]) == [0, 1]
    assert out[0]["end_keypoints"][0] == 1


@pytest.mark.parametrize("case", ["vee", "apart", "crossing", "tee", "hatch", "short_turn", "touching"])
def test_lines_that_only_meet_or_run_near_stay_apart(case):
    x = np.linspace(10, 110, 60)
    if case == "vee":          # a narrow V: the arms run within two widths near its tip, then part
        t = np.tan(np.radians(6))
        curves = [_curve(0, np.c_[x, 50 + (x - 10) * t], (5, 1)), _curve(1, np.c_[x, 50 - (x - 10) * t], (5, 1))]
    elif case == "apart":      # parallel lines 2.5 widths apart
        curves = [_curve(0, _line(10, 110, 50)), _curve(1, _line(10, 110, 55))]
    elif case == "crossing":
        curves = [_curve(0, _line(10, 110, 50)), _curve(1, np.c_[np.full(60, 60.0), x - 10])]
    elif case == "tee":
        curves = [_curve(0, _line(10, 110, 50)), _curve(1, np.c_[np.full(60, 60.0), np.linspace(50, 100, 60)])]
    elif case == "hatch":      # a short stroke beside the middle of a contour, ending apart from it
        curves = [_curve(0, _line(10, 110, 50)), _curve(1, _line(40, 70, 53.5, 30))]
    elif case == "short_turn":  # a flick at a stroke's end shorter than min_run_widths widths
        curves = [_curve(0, np.r_[_line(10, 110, 50, 101), _line(109, 101, 53, 9)])]
    else:                      # two strokes that touch along a stretch and part at both ends
        y = 50 + 3 * np.clip(np.abs(x - 60) - 15, 0, None) / 10
        curves = [_curve(0, np.c_[x, y]), _curve(1, np.c_[x, 100 - y - 47])]
    out = _merge(curves)
    assert len(out) == len(curves)
    for c, o in zip(curves, out):
        np.testing.assert_array_equal(c["points"], o["points"])


def test_a_corner_of_the_passes_is_kept():
    # Two passes of an L, each one curve through its corner vertex (as export.corners leaves them).
    a = np.r_[_line(10, 60, 20, 51), np.c_[np.full(50, 60.0), np.linspace(21, 70, 50)]]
    b = a + [1.5, -1.5]
    ca, cb = _curve(0, a), _curve(1, b)
    ca["corners"], cb["corners"] = [50], [50]
    out = _merge([ca, cb])
    assert len(out) == 1
    (k,) = out[0]["corners"]
    np.testing.assert_allclose(out[0]["points"][k], [60.75, 19.25], atol=0.8)


def test_near_pairs_are_all_pairs_within_the_radius():
    rng = np.random.default_rng(3)
    pts = rng.uniform(0, 40, (600, 2))
    i, j = _near_pairs(pts, 2.5)
    got = {(min(a, b), max(a, b)) for a, b in zip(i.tolist(), j.tolist())}
    d = np.hypot(*(pts[:, None] - pts[None]).transpose(2, 0, 1))
    want = {(a, b) for a, b in zip(*np.nonzero(np.triu(d <= 2.5, 1)))}
    assert got == want and len(i) == len(got)


def test_near_pairs_found_chunk_by_chunk_and_filtered_are_those_of_one_pass():
    rng = np.random.default_rng(5)
    pts = np.round(rng.uniform(0, 60, (900, 2)) * 2) / 2             # half pixels: equal distances
    i, j = _near_pairs(pts, 3.0)
    def keep(a, b, d):
        return (a + b) % 3 > 0

    for chunk in (1, 7, 100, 10_000):
        ci, cj = _near_pairs(pts, 3.0, keep, chunk)
        mine = (i + j) % 3 > 0
        np.testing.assert_array_equal(ci, i[mine]), np.testing.assert_array_equal(cj, j[mine])


def test_points_near_are_all_points_within_each_query_radius():
    from stages.export.end_index import points_near

    rng = np.random.default_rng(4)
    pts, qs = rng.uniform(-20, 40, (700, 2)), rng.uniform(-25, 45, (90, 2))
    r = rng.uniform(0.5, 9.0, len(qs))
    q, p = points_near(pts, qs, r, 2.0)
    d = (pts[None] - qs[:, None])
    want = set(zip(*np.nonzero(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] <= (r * r)[:, None])))
    assert set(zip(q.tolist(), p.tolist())) == want and len(q) == len(want) and np.all(np.diff(q) >= 0)


def test_merging_is_near_linear_in_the_ink(monkeypatch):
    # Many short parallel pairs over a page: the pairs searched grow with the ink, not its square.
    import stages.export.passes as passes

    seen = []
    real = passes._near_pairs
    monkeypatch.setattr(passes, "_near_pairs", lambda p, r, *a: seen.append(len(real(p, r, *a)[0])) or real(p, r, *a))

    def page(n):   # 4 rows of n pairs of passes
        return [_curve(k, _line(10 + 130 * c, 120 + 130 * c, 10 + 40 * r + 3 * (k % 2)))
                for r in range(4) for c in range(n) for k in (2 * (r * n + c), 2 * (r * n + c) + 1)]

    small = _merge(page(2))
    pairs_small, seen[:] = seen[0], []
    large = _merge(page(8))
    assert len(small) == 8 and len(large) == 32
    assert 0 < seen[0] <= 4.5 * pairs_small                           # 4 times the ink


@pytest.mark.slow
def test_a_generated_doubled_stroke_gives_one_curve():
    """The whole chain on a rendered line drawn twice, its passes 1.6 widths apart: one curve."""
    from test_export import _vectorise

    w = 3.0
    a = np.array([[14.0, 40.0], [60.0, 30.0], [110.0, 44.0]])
    b = a + [[1.5, 4.6], [0.0, 4.8], [-1.0, 4.6]]
    grey = synthetic.render((80, 128), [a, b], w)
    kps = [(*a[0], 1), (*a[-1], 1), (*b[0], 1), (*b[-1], 1)]     # a detector sees each pass's ends
    d = synthetic.Drawing(grey=grey, strokes=[a, b], width=w, keypoints=kps)
    curves = _vectorise(d)
    assert len(curves) == 1


def _eye(rise_px: float, top: float):
    """A straight pass and one that leaves its start at ``rise_px`` of run, runs ``top`` px beside it and comes back."""
    x = np.linspace(10, 110, 101)
    y = 50 + top * np.clip(np.minimum(x - 10, 110 - x) / rise_px, 0, 1)
    return _curve(0, _line(10, 110, 50, 101), (5, 5), (1, 2)), _curve(1, np.c_[x, y][::-1], (5, 5), (2, 1))


def test_passes_that_close_up_at_both_ends_are_one_curve():
    # Two passes between the same two keypoints, 1.5 widths apart, converging there steeper than
    # near-parallel over more than end_slack_widths widths (seen on the overdrawn cases: an "eye").
    a, b = _eye(10.0, 3.0)
    out = _merge([a, b])
    assert len(out) == 1 and sorted(out[0]["parts"]) == [0, 1]
    pts = out[0]["points"]
    assert {tuple(np.round(pts[0])), tuple(np.round(pts[-1]))} == {(10.0, 50.0), (110.0, 50.0)}
    middle = pts[(pts[:, 0] > 25) & (pts[:, 0] < 95)]
    np.testing.assert_allclose(middle[:, 1], 51.5, atol=0.05)
    assert sorted(out[0]["end_keypoints"]) == [1, 2]


def test_a_lens_whose_sides_part_stays_two_curves():
    # Two lines from one point to another that run near-parallel in the middle but part by 3 widths
    # on the way there: different lines meeting at both ends.
    x = np.linspace(10, 110, 101)
    y = 50 + np.interp(x, [10, 30, 45, 75, 90, 110], [0, 6, 3, 3, 6, 0])
    curves = [_curve(0, _line(10, 110, 50, 101), (5, 5)), _curve(1, np.c_[x, y], (5, 5))]
    assert len(_merge(curves)) == 2


@pytest.mark.slow
def test_a_generated_stroke_drawn_twice_between_two_points_is_one_open_curve():
    """Two passes of the pen from one point to another, 1.7 widths apart between: one curve, end to end."""
    from test_export import _vectorise

    w = 3.0
    a = np.array([[14.0, 40.0], [40.0, 33.0], [80.0, 33.0], [110.0, 44.0]])
    b = np.array([[14.0, 40.0], [24.0, 41.5], [40.0, 38.2], [80.0, 38.0], [100.0, 46.0], [110.0, 44.0]])
    grey = synthetic.render((80, 128), [a, b], w)
    d = synthetic.Drawing(grey=grey, strokes=[a, b], width=w, keypoints=[(*a[0], 1), (*a[-1], 1)])
    curves = _vectorise(d)
    assert len(curves) == 1                              # before: the two passes joined into a loop
    ends = sorted(map(tuple, np.round(curves[0][[0, -1]])))
    assert ends == [(14.0, 40.0), (110.0, 44.0)]


def _merged_by_full_rounds(curves):
    """``merge_passes`` as first built: every round looks at all pairs of all curves (the reference)."""
    from stages.export import passes as ps

    curves = [dict(c, points=np.asarray(c["points"], np.float64)) for c in curves]
    counts = [1] * len(curves)
    for _ in range(8):
        known = [c["width"] for c in curves if c.get("width")]
        fallback = float(np.median(known)) if known else ps._DEFAULT_WIDTH_PX
        widths = np.array([float(c["width"]) if c.get("width") else fallback for c in curves])
        Pt, T, owner, arc, offsets, W = ps._samples([ps._curve_samples(c) for c in curves], widths)
        i, j = ps._partners(Pt, T, owner, arc, W, P["max_gap_widths"], P["max_angle_deg"])
        used, dropped = set(), set()
        for _, a, b, ia, jb in ps._runs(i, j, owner, arc, W, P["min_run_widths"]):
            if a in used or b in used:
                continue
            w, q, slack = float(0.5 * (widths[a] + widths[b])), arc[jb], P["end_slack_widths"] * 0.5 * (widths[a] + widths[b])
            if a == b:
                if q[0] < arc[ia[0]]:
                    continue
                new = ps._fold(curves[a], Pt[ia], arc[ia], q, slack, 3.0 * P["max_gap_widths"] * w, w)
            else:
                lo, hi = offsets[b], offsets[b + 1]
                new = ps._merge_pair(curves[a], curves[b], Pt[ia], arc[ia], float(arc[offsets[a + 1] - 1]),
                                     Pt[lo:hi], arc[lo:hi], q, counts[a], counts[b], w, slack,
                                     ps._ATTACH_WIDTHS * w, P["max_gap_widths"] * w)
            if new is None:
                continue
            curves[a] = new
            if a != b:
                counts[a] += counts[b]
                dropped.add(b)
            used |= {a, b}
        if not used:
            break
        curves = [c for k, c in enumerate(curves) if k not in dropped]
        counts = [n for k, n in enumerate(counts) if k not in dropped]
    return curves


def _bundles(rng, n):
    """``n`` bundles of 1–4 passes of a line, on whole or half pixels (ties of distance), widths 1.5–3 px or none."""
    curves = []
    for b in range(n):
        x0, y0 = rng.integers(0, 4) * 60, rng.integers(0, 4) * 40
        for k in range(rng.integers(1, 5)):
            shift = np.round(rng.uniform(-1, 4) * 2) / 2
            x = np.arange(x0 + 5 + rng.integers(0, 4), x0 + 55 - rng.integers(0, 4), 1.0)
            y = np.full(len(x), y0 + 10 + shift) + (x - x0) * rng.choice([0.0, 0.5])
            pts = np.c_[x, y][::rng.choice([1, -1])]
            curves.append(_curve(len(curves), pts, width=rng.choice([None, 1.5, 2.0, 3.0])))
    return curves


def test_rounds_on_the_changed_curves_merge_as_full_rounds():
    # Later rounds look only at the curves that changed and their neighbours; the merges are those of
    # rounds over every pair (random bundles of passes, coordinates on half pixels: equal distances).
    rng = np.random.default_rng(7)
    for _ in range(30):
        curves = _bundles(rng, int(rng.integers(1, 8)))
        got, want = _merge(curves), _merged_by_full_rounds(curves)
        assert [c["parts"] for c in got] == [c["parts"] for c in want]
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g["points"], w["points"])
            assert (g["end_types"], g["end_keypoints"], g.get("corners")) == (w["end_types"], w["end_keypoints"],
                                                                          w.get("corners"))


def test_later_rounds_look_only_near_the_changed_curves(monkeypatch):
    # A page of single lines (nothing to merge) and one line drawn three times (two passes merged in
    # the first round, the third in the second): later rounds look at that line's samples, not the page's.
    from stages.export import passes

    seen = []
    real = passes._partners
    monkeypatch.setattr(passes, "_partners", lambda p, *a: seen.append(len(p)) or real(p, *a))
    page = [_curve(k, _line(10 + 130 * (k % 8), 120 + 130 * (k % 8), 10 + 20 * (k // 8))) for k in range(64)]
    triple = [_curve(100 + m, _line(10, 120, 190 + 2 * m)) for m in (0, 1, 2)]
    out = _merge(page + triple)
    assert len(out) == 65 and len(seen) >= 2
    assert seen[0] == 67 * 111 and sum(seen[1:]) <= 4 * 111    # before: all 7,437 samples every round
