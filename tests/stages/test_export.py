"""Tests of the SVG export: valid XML, viewBox, coordinates aligned with the drawing, Bézier fit."""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import yaml

from stages import export, synthetic
from stages.artifact import Artifact, pack_ragged
from stages.errors import InputError
from stages.export import bezier, joins

ROOT = Path(__file__).resolve().parents[2]
CFG = yaml.safe_load((ROOT / "conf" / "export" / "default.yaml").read_text())
NS = {"svg": "http://www.w3.org/2000/svg"}


def _cfg(**over):
    cfg = json.loads(json.dumps(CFG))
    for k, v in over.items():
        cfg[k] = v
    return cfg


def _inputs(curves, chosen, shape=(64, 80), widths=None):
    paths = [{"id": 100 + k, "component": 0, "vertices": [], "xy": np.asarray(c).tolist(),
              "widths": list(widths[k]) if widths else [3.0] * len(c), "interest_dist": [0.0] * len(c),
              "end_types": [1, 3], "end_keypoints": [0, 1]} for k, c in enumerate(curves)]
    flat, off = pack_ragged([np.asarray(c, float) for c in curves], np.float64)
    return {"prep": Artifact(data={"height": shape[0], "width": shape[1]}),
            "topology": Artifact(data={"paths": paths}),
            "flow": Artifact(arrays={"curve_xy": flat.reshape(-1, 2), "curve_xy_offsets": off}),
            "select": Artifact(data={"chosen": [100 + k for k in chosen], "status": "optimal"})}


def _path_points(d: str) -> np.ndarray:
    nums = [float(v) for v in re.findall(r"-?\d+(?:\.\d+)?", d)]
    return np.array(nums).reshape(-1, 2)


def test_svg_parses_with_the_image_viewbox_and_one_path_per_chosen_curve():
    curves = [np.array([[1.0, 2.0], [10.5, 20.25], [30.125, 40.0]]), np.array([[5.0, 5.0], [6.0, 9.0]]),
              np.array([[50.0, 1.0], [70.0, 60.0]])]
    art = export.run(CFG, **_inputs(curves, [2, 0]))
    root = ET.fromstring(art.data["svg"].encode())
    assert root.tag == "{http://www.w3.org/2000/svg}svg"
    assert root.get("viewBox") == "0 0 80 64"
    assert root.get("width") == "80" and root.get("height") == "64"
    paths = root.findall(".//svg:path", NS)
    assert [p.get("id") for p in paths] == ["curve-102", "curve-100"]
    group = root.find("svg:g", NS)
    assert group.get("fill") == "none" and group.get("stroke") == "#000000"
    np.testing.assert_allclose(_path_points(paths[1].get("d")), curves[0], atol=0.005 + 1e-9)
    np.testing.assert_allclose(_path_points(paths[0].get("d")), curves[2], atol=0.005 + 1e-9)
    assert [c["id"] for c in art.data["curves"]] == [102, 100]
    assert art.data["curves"][1]["end_types"] == [1, 3]
    assert art.data["curves"][1]["width"] == pytest.approx(3.0)
    json.dumps(art.data)
    assert "bezier_svg" not in art.data


def test_svg_coordinates_lie_on_the_drawn_strokes():
    """Pixel coordinates without a half-pixel shift: each path point sits at the ink centroid across it."""
    d = synthetic.line(angle=17, width=3.0)
    a, b = d.strokes[0]
    dense = a + np.linspace(0.1, 0.9, 40)[:, None] * (b - a)
    art = export.run(CFG, **_inputs([dense], [0], shape=d.grey.shape))
    pts = _path_points(ET.fromstring(art.data["svg"]).find(".//svg:path", NS).get("d"))
    nrm = np.array([-(b - a)[1], (b - a)[0]]) / np.hypot(*(b - a))
    ink = 1.0 - d.grey
    offsets = []
    for p in pts:
        i0, j0 = int(p[1]), int(p[0])
        ii, jj = np.mgrid[i0 - 4:i0 + 5, j0 - 4:j0 + 5]
        centres = np.stack([jj + 0.5, ii + 0.5], -1).reshape(-1, 2)   # pixel [i, j] centre = (j + .5, i + .5)
        w = ink[ii, jj].ravel()
        offsets.append(((centres - p) @ nrm * w).sum() / w.sum())
    assert np.abs(offsets).max() < 0.1


def test_stroke_widths_from_the_graph():
    curves = [np.array([[1.0, 2.0], [10.0, 20.0]]), np.array([[5.0, 5.0], [6.0, 9.0]])]
    art = export.run(_cfg(widths_from_graph=True), **_inputs(curves, [0, 1], widths=[[2.0, 4.0], [5.0, 5.0]]))
    paths = ET.fromstring(art.data["svg"]).findall(".//svg:path", NS)
    assert [p.get("stroke-width") for p in paths] == ["3", "5"]


def test_bezier_fit_stays_within_tolerance_and_keeps_the_ends():
    t = np.linspace(0, 1.5 * np.pi, 300)
    pts = np.stack([40 + 25 * np.cos(t), 40 + 25 * np.sin(t)], 1)
    pts += np.random.default_rng(0).normal(0, 0.05, pts.shape)
    for tol in (0.2, 0.5, 1.0):
        pieces = export.fit_cubic_beziers(pts, tol)
        np.testing.assert_allclose(pieces[0][0], pts[0])
        np.testing.assert_allclose(pieces[-1][-1], pts[-1])
        for a, b in zip(pieces[:-1], pieces[1:]):
            np.testing.assert_allclose(a[-1], b[0])
            # Consecutive pieces share the tangent at their joint.
            ta, tb = a[3] - a[2], b[1] - b[0]
            assert abs(ta[0] * tb[1] - ta[1] * tb[0]) < 1e-9 * np.hypot(*ta) * np.hypot(*tb) + 1e-12
        u = np.linspace(0, 1, 400)
        dense = np.concatenate([bezier._bezier(c, u) for c in pieces])
        dist = np.sqrt(((pts[:, None] - dense[None]) ** 2).sum(-1)).min(1)
        assert dist.max() <= tol + 0.02
        assert len(pieces) <= 8
    assert len(export.fit_cubic_beziers(pts[:2], 0.5)) == 1
    assert export.fit_cubic_beziers(pts[:1], 0.5) == []


def test_bezier_svg_is_written_when_enabled():
    t = np.linspace(0, np.pi, 100)
    curve = np.stack([40 + 20 * np.cos(t), 30 + 20 * np.sin(t)], 1)
    art = export.run(_cfg(bezier=True), **_inputs([curve], [0]))
    root = ET.fromstring(art.data["bezier_svg"])
    d = root.find(".//svg:path", NS).get("d")
    assert " C " in d and root.get("viewBox") == "0 0 80 64"


def test_empty_selection_and_bad_input():
    art = export.run(CFG, **_inputs([np.array([[1.0, 2.0], [3.0, 4.0]])], []))
    root = ET.fromstring(art.data["svg"])
    assert root.findall(".//svg:path", NS) == [] and art.data["curves"] == []
    bad = _inputs([np.array([[1.0, 2.0], [3.0, 4.0]])], [])
    bad["select"].data["chosen"] = [7]
    with pytest.raises(InputError):
        export.run(CFG, **bad)
    bad = _inputs([np.array([[1.0, 2.0], [3.0, 4.0]])], [0])
    bad["topology"].data["paths"].append(dict(bad["topology"].data["paths"][0], id=5))
    with pytest.raises(InputError):
        export.run(CFG, **bad)
    with pytest.raises(InputError):
        export.run({k: v for k, v in CFG.items() if k != "precision"}, **_inputs([], []))


def _curve(a, b, types, kps, n=20):
    t = np.linspace(0, 1, n)[:, None]
    return {"points": np.asarray(a, float) + t * (np.subtract(b, a)), "end_types": types, "end_keypoints": kps,
            "parts": [len(kps) * 100 + kps[0]], "width": 3.0}


def test_join_continuations_at_junctions_only_where_the_stroke_goes_straight_on():
    c = (32.0, 32.0)
    # T: the bar's halves end at junction 9 and continue each other; the stem turns by 90°.
    t = [_curve((8, 32), c, [1, 3], [0, 9]), _curve((56, 33), c, [1, 3], [1, 9]), _curve((32, 58), c, [1, 3], [2, 9])]
    out = export.join_continuations(t, 35.0, 5.0)
    assert len(out) == 2
    bar = next(o for o in out if len(o["parts"]) == 2)
    assert sorted(bar["end_keypoints"]) == [0, 1] and len(bar["points"]) == 39
    # Y (120°): nothing continues.  A sharp corner or an endpoint is never a joint.
    y = [_curve(c, (c[0] + 20 * np.cos(a), c[1] + 20 * np.sin(a)), [3, 1], [9, k])
         for k, a in enumerate(np.deg2rad([90, 210, 330]))]
    assert len(export.join_continuations(y, 35.0, 5.0)) == 3
    for ty in (5, 1):
        straight = [_curve((8, 32), c, [1, ty], [0, 9]), _curve((56, 32), c, [1, ty], [1, 9])]
        assert len(export.join_continuations(straight, 35.0, 5.0)) == 2
    # Synthetic ends (type 0) join by position; an X's four halves give its two strokes.
    syn = [_curve((8, 32), c, [1, 0], [0, -1]), _curve(c, (56, 31), [0, 1], [-1, 1])]
    assert len(export.join_continuations(syn, 35.0, 5.0)) == 1
    x = [_curve(c, (c[0] + 20 * np.cos(a), c[1] + 20 * np.sin(a)), [3, 1], [9, k])
         for k, a in enumerate(np.deg2rad([10, 70, 190, 250]))]
    out = export.join_continuations(x, 35.0, 5.0)
    assert sorted(sorted(o["end_keypoints"]) for o in out) == [[0, 2], [1, 3]]


def test_run_joins_and_lists_the_parts():
    c = [32.0, 32.0]
    curves = [[[8, 32], [20, 32], c], [c, [44, 32], [56, 32]]]
    inputs = _inputs(curves, [0, 1])
    for p in inputs["topology"].data["paths"]:
        p["end_types"], p["end_keypoints"] = [1, 3], [p["id"] - 100, 7]
    inputs["topology"].data["paths"][1]["end_types"] = [3, 1]
    inputs["topology"].data["paths"][1]["end_keypoints"] = [7, 1]
    art = export.run(CFG, **inputs)
    assert len(art.data["curves"]) == 1 and art.data["curves"][0]["parts"] == [100, 101]
    assert art.data["svg"].count("<path") == 1
    off = _cfg(join={**CFG["join"], "enabled": False}, meetings={"enabled": False})   # two ends alone: joined by meetings too
    assert len(export.run(off, **inputs).data["curves"]) == 2


# ---------------------------------------------------------------------------------------------
# Issue 6: the whole chain prep → field → graph → topology → flow → select → export on synthetic
# drawings with their exact keypoints
# ---------------------------------------------------------------------------------------------

def _vectorise(drawing):
    from stages import extension, field, flow, graph, prep, select, topology
    from synthetic_graph import synthetic_inputs

    conf = {n: yaml.safe_load((ROOT / "conf" / n / "default.yaml").read_text())
            for n in ("prep", "field", "extension", "graph", "topology", "flow", "select")}
    p = prep.run(conf["prep"], image_bytes=drawing.png_bytes(), image_name="synthetic.png")
    f = field.run(conf["field"], prep=p)
    g = graph.run(conf["graph"], prep=p, field=f)
    k = synthetic_inputs(drawing)["keypoints"]
    t = topology.run(conf["topology"], prep=p, field=f, graph=g, keypoints=k)
    e = extension.run(conf["extension"], prep=p, field=f)
    fl = flow.run(conf["flow"], prep=p, extension=e, graph=g, topology=t)
    s = select.run(conf["select"], prep=p, topology=t, flow=fl)
    return [np.asarray(c["points"]) for c in export.run(CFG, prep=p, topology=t, flow=fl, select=s).data["curves"]]


def _distance_to(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    a, b = polyline[:-1], polyline[1:]
    d = b - a
    t = np.clip(((points[:, None] - a) * d).sum(-1) / np.maximum((d * d).sum(-1), 1e-12), 0, 1)
    return np.hypot(*np.moveaxis(points[:, None] - a - t[..., None] * d, -1, 0)).min(1)


ISSUE6 = {  # drawing, expected number of curves
    "X": (lambda: synthetic.cross(), 2),
    "T": (lambda: synthetic.tee(), 2),
    "Y": (lambda: synthetic.wye(angle=45.0), 3),
    "zigzag": (lambda: synthetic.zigzag(), 1),     # one stroke through its corners (export.corners)
    "loop": (lambda: synthetic.circle(), 1),
    "vee": (lambda: synthetic.vee(), 1),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(ISSUE6))
def test_issue6_synthetic_drawings_vectorise_with_the_right_topology_and_geometry(name):
    make, n_curves = ISSUE6[name]
    d = make()
    curves = _vectorise(d)
    assert len(curves) == n_curves
    kps = np.array([k[:2] for k in d.keypoints]) if d.keypoints else np.zeros((0, 2))
    for c in curves:
        # No curve farther than 1 px from the stroke centre lines.
        assert np.max(np.min([_distance_to(c, s) for s in d.strokes], axis=0)) <= 1.0
        if len(kps):  # ends on the junction / corner / end positions
            for e in (c[0], c[-1]):
                assert np.hypot(*(kps - e).T).min() <= 1.5
        else:         # the loop closes on itself
            assert np.hypot(*(c[0] - c[-1])) <= 1.5
    if name == "Y":   # three curves meeting at the centre, none turning from one branch into another
        centre = np.array(d.keypoints[3][:2])
        for c in curves:
            assert min(np.hypot(*(c[0] - centre)), np.hypot(*(c[-1] - centre))) <= 1.5
            assert min(_distance_to(c, s).max() for s in d.strokes) <= 1.0
    if name in ("vee", "zigzag"):  # sharp corners stay sharp: a curve vertex at every corner, turning there
        for x, y, t in d.keypoints:
            if t == 5:
                c = curves[int(np.argmin([np.hypot(*(c - [x, y]).T).min() for c in curves]))]
                i = int(np.argmin(np.hypot(*(c - [x, y]).T)))
                assert np.hypot(*(c[i] - [x, y])) <= 1.5
                s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(c, axis=0).T))])
                before = c[i] - c[np.searchsorted(s, s[i] - 5.0)]
                after = c[min(np.searchsorted(s, s[i] + 5.0), len(c) - 1)] - c[i]
                cosang = before @ after / (np.linalg.norm(before) * np.linalg.norm(after))
                assert cosang < np.cos(np.radians(45.0))
    if name == "T":   # the bar runs through, the stem ends on it
        stem = next(c for c in curves if min(_distance_to(c, d.strokes[1]).max(), 99) <= 1.0)
        assert min(np.hypot(*(stem[0] - d.keypoints[3][:2])), np.hypot(*(stem[-1] - d.keypoints[3][:2]))) <= 1.5


# ---------------------------------------------------------------------------------------------
# Spurs at junctions and unlabelled overshoots
# ---------------------------------------------------------------------------------------------

def _piece(cid, pts, types, kps, width=3.0):
    return {"id": cid, "points": np.asarray(pts, float), "end_types": list(types), "end_keypoints": list(kps),
            "parts": [cid], "width": width}


def _run_pieces(pieces, cfg, shape=(48, 48), mask=None):
    """``export.run`` on the pieces as chosen paths with their own end types and keypoints (and ``mask``
    as prep's band when given); the curves it writes."""
    inputs = _inputs([p["points"] for p in pieces], list(range(len(pieces))), shape=shape)
    if mask is not None:
        inputs["prep"] = Artifact(data={"height": shape[0], "width": shape[1]}, arrays={"mask": mask})
    for p, c in zip(inputs["topology"].data["paths"], pieces):
        p["end_types"], p["end_keypoints"] = c["end_types"], c["end_keypoints"]
    return export.run(cfg, **inputs).data["curves"]


def _line(a, b, step=0.5):
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = max(2, int(np.ceil(np.hypot(*(b - a)) / step)) + 1)
    return a + np.linspace(0, 1, n)[:, None] * (b - a)


def _ink_set(curves):
    return {tuple(np.round(p, 6)) for c in curves for p in np.asarray(c["points"])}


def test_spur_joins_the_curve_ending_at_the_junction_that_it_continues():
    # A stroke arrives from the left at junction 7 and overshoots it by 6 px (a spur to endpoint 9);
    # a second curve leaves the junction upwards.
    a = _piece(1, _line((0, 20), (20, 20)), [1, 3], [8, 7])
    up = _piece(2, _line((20, 20), (20, 0)), [3, 1], [7, 10])
    spur = _piece(3, _line((20, 20), (25, 23)), [3, 1], [7, 9])
    out = export.attach_spurs([a, up, spur], 12.0, 4.0, 60.0, 5.0, 1.5)
    assert len(out) == 2
    joined = next(c for c in out if len(c["parts"]) == 2)
    assert sorted(joined["parts"]) == [1, 3] and sorted(joined["end_keypoints"]) == [8, 9]
    assert _ink_set(out) == _ink_set([a, up, spur])


def test_spur_splits_a_curve_passing_through_the_junction():
    through = _piece(1, _line((0, 0), (40, 40)), [1, 1], [1, 2])            # passes (20, 20)
    spur = _piece(3, _line((20, 20), (24.6, 28.9)), [3, 1], [7, 9])         # 18° off the lower half
    out = export.attach_spurs([through, spur], 12.0, 4.0, 60.0, 5.0, 1.5)
    assert len(out) == 2
    joined = next(c for c in out if 3 in c["parts"])
    rest = next(c for c in out if 3 not in c["parts"])
    assert sorted(joined["end_keypoints"]) == [1, 9]                         # upper half + spur
    assert rest["end_keypoints"] == [7, 2] and rest["end_types"] == [3, 1]   # lower half ends at 7
    np.testing.assert_allclose(rest["points"][0], [20, 20])
    # A spur at a right angle to the through curve, or a long curve, stays on its own.
    square = _piece(3, _line((20, 20), (26, 14)), [3, 1], [7, 9])
    assert len(export.attach_spurs([through, square], 12.0, 4.0, 60.0, 5.0, 1.5)) == 2
    assert all(len(c["parts"]) == 1 for c in export.attach_spurs([through, square], 12.0, 4.0, 60.0, 5.0, 1.5))
    long = _piece(3, _line((20, 20), (28, 50)), [3, 1], [7, 9])
    assert all(len(c["parts"]) == 1 for c in export.attach_spurs([through, long], 12.0, 4.0, 60.0, 5.0, 1.5))


def _overshoot_drawing(overshoot, width=3.0):
    bar = np.array([[6.0, 30.0], [74.0, 30.0]])
    stem = np.array([[40.0, 6.0], [40.0, 30.0 + overshoot]])
    grey = synthetic.render((60, 80), [bar, stem], width)
    curves = [_piece(1, _line(*bar), [1, 1], [1, 2], width), _piece(2, _line((40, 6), (40, 30)), [1, 3], [3, 4], width)]
    return grey < 0.5, curves


@pytest.mark.parametrize("overshoot", [0.0, 6.0])
def test_overshoot_beyond_a_junction_is_drawn_and_a_plain_tee_is_not_extended(overshoot):
    mask, curves = _overshoot_drawing(overshoot)
    out = export.extend_overshoots(curves, mask, 5.0, 2.0, 1.0, 12.0, 4.0, 0.7)
    stem = next(c for c in out if c["id"] == 2)
    bar = next(c for c in out if c["id"] == 1)
    np.testing.assert_allclose(bar["points"], curves[0]["points"])          # endpoint ends never move
    if overshoot == 0:
        np.testing.assert_allclose(stem["points"], curves[1]["points"])
        assert stem["end_types"] == [1, 3]
    else:
        assert abs(stem["points"][-1][1] - (30.0 + overshoot)) <= 1.0
        assert abs(stem["points"][-1][0] - 40.0) <= 1e-6
        assert stem["end_types"] == [1, 0] and stem["end_keypoints"] == [3, -1] and stem["through_keypoints"] == [4]


def test_no_overshoot_into_the_gap_of_a_wye_or_past_a_closed_loop():
    d = synthetic.wye(size=64, length=22.0, width=3.0)
    mask = d.grey < 0.5
    c = np.array(d.keypoints[3][:2])
    # Two branches end at the junction, the third one does too: no end may grow into the gap.
    curves = [_piece(k, _line(s[1], c), [1, 3], [k, 3]) for k, s in enumerate(d.strokes)]
    out = export.extend_overshoots(curves, mask, 5.0, 2.0, 1.0, 12.0, 4.0, 0.7)
    for a, b in zip(curves, out):
        np.testing.assert_allclose(a["points"], b["points"])
    d = synthetic.circle()
    loop = np.asarray(d.strokes[0])
    out = export.extend_overshoots([_piece(0, loop, [0, 0], [-1, -1])], d.grey < 0.5, 5.0, 2.0, 1.0, 12.0, 4.0, 0.7)
    np.testing.assert_allclose(out[0]["points"], loop)



def test_spur_at_a_synthetic_junction_with_a_free_synthetic_end():
    # Topology ends without keypoints: two curves share the synthetic point (20, 20); the spur's far
    # end is shared by nobody, so it is free.
    a = _piece(1, _line((0, 20), (20, 20)), [1, 0], [8, -1])
    b = _piece(2, _line((20, 20), (20, 0)), [0, 1], [-1, 10])
    spur = _piece(3, _line((20, 20), (25, 23)), [0, 0], [-1, -1])
    out = export.attach_spurs([a, b, spur], 12.0, 4.0, 60.0, 5.0, 1.5)
    assert len(out) == 2 and sorted(next(c for c in out if len(c["parts"]) == 2)["parts"]) == [1, 3]
    # The same spur whose far end is shared (a chain goes on there) is no spur.
    c = _piece(4, _line((25, 23), (45, 23)), [0, 1], [-1, 11])
    assert len(export.attach_spurs([a, b, spur, c], 12.0, 4.0, 60.0, 5.0, 1.5)) == 4


# ---------------------------------------------------------------------------------------------
# Spur ends by their drawn valence, and links below the drawing's resolution
# ---------------------------------------------------------------------------------------------

def _topology(curves, width=3.0):
    from stages.config import from_section
    from stages.evaluate.curve_topology import TopologyParams, curve_topology

    bench = yaml.safe_load((ROOT / "conf" / "bench" / "default.yaml").read_text())
    return curve_topology([np.asarray(c["points"]) for c in curves], width,
                            from_section(TopologyParams, bench["topology"], "bench.topology"))


@pytest.mark.parametrize("by_valence", [False, True])
def test_spur_at_a_corner_where_three_curves_end_is_joined_by_its_drawn_valence(by_valence):
    # Corner keypoint 7 at (30, 30): arms from the left and from above, and a 6 px piece going on
    # straight to the right to endpoint 9 — three curve ends at a "corner": a junction as drawn.
    left = _piece(1, _line((0, 30), (30, 30)), [1, 5], [8, 7])
    up = _piece(2, _line((30, 30), (30, 0)), [5, 1], [7, 10])
    spur = _piece(3, _line((30, 30), (36, 30)), [5, 1], [7, 9])
    out = export.attach_spurs([left, up, spur], 12.0, 4.0, 75.0, 5.0, 1.5, by_valence)
    assert _ink_set(out) == _ink_set([left, up, spur])
    if by_valence:
        assert len(out) == 2 and sorted(next(c for c in out if len(c["parts"]) == 2)["parts"]) == [1, 3]
        assert _topology(out).dangling == []
    else:
        assert len(out) == 3 and len(_topology(out).dangling) == 1


def test_spur_to_a_corner_that_no_other_curve_reaches_is_free_by_its_drawn_valence():
    # A stroke passes junction 7 at (20, 20); an 8 px piece leaves it at 34° to a corner keypoint 9
    # that nothing else reaches (a stroke tip typed as a corner): a dangling branch as drawn.
    through = _piece(1, _line((0, 20), (40, 20)), [1, 1], [1, 2])
    spur = _piece(3, _line((20, 20), (20 + 8 * np.cos(0.6), 20 + 8 * np.sin(0.6))), [3, 5], [7, 9])
    assert len(_topology([through, spur]).dangling) == 1
    assert len(export.attach_spurs([through, spur], 12.0, 4.0, 75.0, 5.0, 1.5, False)) == 2      # kept apart
    out = export.attach_spurs([through, spur], 12.0, 4.0, 75.0, 5.0, 1.5, True)
    assert len(out) == 2 and _topology(out).dangling == []
    assert sorted(next(c for c in out if 3 in c["parts"])["end_keypoints"]) == [1, 9]     # the left half goes on into it
    # A corner end that another curve shares is not free: nothing is joined.
    other = _piece(4, _line(spur["points"][-1], (40, 40)), [5, 1], [9, 11])
    assert all(len(c["parts"]) == 1 for c in export.attach_spurs([through, spur, other], 12.0, 4.0, 75.0, 5.0, 1.5,
                                                                  True))


def _vee_with_a_doubled_corner(gap=3.0):
    """Two arms of a vee ending at corner keypoints 5 and 6, ``gap`` px apart, and the tiny link between."""
    c1, c2 = np.array([30.0, 40.0]), np.array([30.0 + gap, 40.0])
    a = _piece(1, _line((10, 10), c1), [1, 5], [0, 5])
    b = _piece(2, _line(c2, (50, 10)), [5, 1], [6, 1])
    link = _piece(3, _line(c1, c2), [5, 5], [5, 6])
    return a, b, link


def test_a_link_shorter_than_the_stroke_width_between_two_corners_is_contracted():
    a, b, link = _vee_with_a_doubled_corner()
    before = _topology([a, b, link])
    assert len(before.junctions) == 1                     # arm + arm + link ends read as a junction
    out = export.collapse_short_links([a, b, link], 3.0, 1.5)
    assert [c["id"] for c in out] == [1, 2]
    mid = np.array([31.5, 40.0])
    np.testing.assert_allclose(out[0]["points"][-1], mid)
    np.testing.assert_allclose(out[1]["points"][0], mid)
    assert out[0]["end_keypoints"][1] == out[1]["end_keypoints"][0]
    np.testing.assert_allclose(out[0]["points"][:-1], a["points"][:-1])      # only the end moved
    after = _topology(out)
    assert len(after.junctions) == 0 and len(after.continuations) == 1
    # Through run(): the config switch turns it on and off.
    inputs = _inputs([c["points"] for c in (a, b, link)], [0, 1, 2])
    for p, c in zip(inputs["topology"].data["paths"], (a, b, link)):
        p["end_types"], p["end_keypoints"], p["widths"] = c["end_types"], c["end_keypoints"], [3.0] * len(c["points"])
    no_corners = {"enabled": False}     # keep the two arms apart, to count what the contraction did
    assert len(export.run(_cfg(corners=no_corners, meetings={"enabled": False}), **inputs).data["curves"]) == 2
    assert len(export.run(_cfg(corners=no_corners, meetings={"enabled": False}, collapse={**CFG["collapse"], "enabled": False}),
                          **inputs).data["curves"]) == 3
    assert len(export.run(CFG, **inputs).data["curves"]) == 1     # and by default the vee is one stroke


def test_long_links_free_tips_and_triangles_are_not_contracted():
    a, b, link = _vee_with_a_doubled_corner(gap=8.0)            # longer than 1.5 widths
    assert len(export.collapse_short_links([a, b, link], 3.0, 1.5)) == 3
    a, b, link = _vee_with_a_doubled_corner()
    tip = dict(link, end_types=[5, 1], end_keypoints=[5, 9])     # one end free: a tip, not a link
    assert len(export.collapse_short_links([a, b, tip], 3.0, 1.5)) == 3
    # A curve with one end at each end of the link: contracting would close it on itself.
    loop = _piece(4, [[30, 40], [31.5, 30], [33, 40]], [5, 5], [5, 6])
    assert len(export.collapse_short_links([a, b, link, loop], 3.0, 1.5)) == 4
    # Tiny curves among tiny curves (a filled eye with many keypoints) would shrink to a point.
    a_short = dict(a, points=_line((28, 38), (30, 40)))
    assert len(export.collapse_short_links([a_short, b, link], 3.0, 1.5)) == 3


def test_curves_shorter_than_a_pixel_are_not_exported():
    """A selected path that flowed onto one point (`M x y L x y`) reaches no SVG, and the Bézier fit copes."""
    curves = [np.array([[245.74, 232.44], [245.74, 232.44]]), np.array([[5.0, 5.0], [5.3, 5.2], [5.5, 5.4]]),
              np.array([[10.0, 10.0], [30.0, 12.0], [50.0, 30.0]])]
    art = export.run(_cfg(bezier=True), **_inputs(curves, [0, 1, 2], shape=(300, 300)))
    for doc in (art.data["svg"], art.data["bezier_svg"]):
        paths = ET.fromstring(doc).findall(".//svg:path", NS)
        assert [p.get("id") for p in paths] == ["curve-102"]
    assert [c["id"] for c in art.data["curves"]] == [102]


def test_bezier_flag_spelling():
    """`export.bezier=true` is the one spelling; the old nested `bezier: {enabled: ...}` is a clear error."""
    with pytest.raises(InputError, match=r"export.bezier must be true or false"):
        export.run(_cfg(bezier={"enabled": True, "tolerance": 0.5}), **_inputs([np.eye(2) * 9], [0]))


def test_joining_is_near_linear_in_the_number_of_curves(monkeypatch):
    """A chain of N curves meeting end to end at junctions: every join re-examines only the groups it
    touches, so end directions are measured O(N) times, not O(N²) (dense scribbles took minutes)."""
    calls = {"n": 0}
    direction = joins.end_direction

    def counting(*a, **k):
        calls["n"] += 1
        return direction(*a, **k)

    monkeypatch.setattr(joins, "end_direction", counting)
    n = 400
    xs = np.arange(n + 1) * 4.0
    curves = [{"id": k, "points": np.array([[xs[k], 0.0], [xs[k] + 2, 0.1 * (k % 2)], [xs[k + 1], 0.0]]),
               "end_types": [3 if k else 1, 3 if k < n - 1 else 1], "end_keypoints": [k, k + 1], "parts": [k],
               "width": 2.0} for k in range(n)]
    out = export.join_continuations(curves, 35.0, 5.0, 10.0, 10.0)
    assert len(out) == 1 and sorted(out[0]["parts"]) == list(range(n))
    assert calls["n"] <= 6 * n, calls["n"]


def _count_lengths(monkeypatch) -> dict:
    from stages.export import curve_ends, overshoots, spurs

    calls = {"n": 0}
    length = joins.polyline_length

    def counting(points):
        calls["n"] += 1
        return length(points)

    for module in (joins, curve_ends, spurs, overshoots):   # the clean-ups' modules, joins.py and those split from it
        monkeypatch.setattr(module, "polyline_length", counting)
    return calls


def test_collapsing_and_attaching_spurs_are_near_linear_in_the_number_of_curves(monkeypatch):
    """Issue 18 item 4: N doubled corners (N links to contract) and N spurs at N crossings.  A rescan of
    every curve after each edit measured curve lengths O(N²) times (minutes on dense scribbles); now
    only the curves near an edit are examined again.  Results are those of the rescan: every link is
    contracted, every spur attached, in curve order."""
    n = 150
    vees = []
    for k in range(n):
        a, b, link = _vee_with_a_doubled_corner()
        shift = np.array([60.0 * k, 0.0])
        kp = {0: 10 * k, 1: 10 * k + 1, 5: 10 * k + 5, 6: 10 * k + 6}
        vees += [dict(c, id=3 * k + c["id"], parts=[3 * k + c["id"]], points=c["points"] + shift,
                      end_keypoints=[kp[q] for q in c["end_keypoints"]]) for c in (a, b, link)]
    calls = _count_lengths(monkeypatch)
    out = export.collapse_short_links(vees, 3.0, 1.5)
    assert len(out) == 2 * n and all(c["id"] % 3 != 0 for c in out)          # every link contracted
    assert calls["n"] <= 6 * len(vees), calls["n"]

    spurs = []
    for k in range(n):
        shift = np.array([50.0 * k, 0.0])
        through = _piece(2 * k, _line((0, 0), (40, 40)) + shift, [1, 1], [4 * k, 4 * k + 1])
        spur = _piece(2 * k + 1, _line((20, 20), (24.6, 28.9)) + shift, [3, 1], [4 * k + 2, 4 * k + 3])
        spurs += [through, spur]
    calls["n"] = 0
    out = export.attach_spurs(spurs, 12.0, 4.0, 60.0, 5.0, 1.5)
    assert len(out) == 2 * n and sum(len(c["parts"]) == 2 for c in out) == n  # every spur attached
    assert calls["n"] <= 12 * len(spurs), calls["n"]


def test_no_join_where_more_ends_meet_than_join_max_ends():
    """Issue 18 item 4, the joins' guard: the pair test at a joint costs its number of ends cubed, so
    past ``join.max_ends`` nothing is joined there and the joint is reported (run() says so)."""
    c = np.array([32.0, 32.0])
    # a straight bar through junction 9 (its halves continue each other), and four arms off to one side
    arms = [_curve(c - [20, 0], c, [1, 3], [1, 9]), _curve(c, c + [20, 0], [3, 1], [9, 2])]
    arms += [_curve(c, c + 20 * np.array([np.cos(a), np.sin(a)]), [3, 1], [9, 3 + k])
             for k, a in enumerate(np.radians([50, 80, 110, 140]))]
    assert len(export.join_continuations(arms, 35.0, 5.0, 10.0, 10.0)) == 5            # the bar is joined
    crowded = set()
    assert len(export.join_continuations(arms, 35.0, 5.0, 10.0, 10.0, 5, crowded)) == 6
    assert crowded == {("k", 9)}
    paths = [a["points"] for a in arms]
    inputs = _inputs(paths, list(range(len(paths))))
    for p, a in zip(inputs["topology"].data["paths"], arms):
        p["end_types"], p["end_keypoints"] = a["end_types"], a["end_keypoints"]
    art = export.run(_cfg(join={**CFG["join"], "max_ends": 5}), **inputs)
    assert len(art.data["curves"]) == 6 and art.notes == [
        "1 joints where more than export.join.max_ends (5) curve ends meet: no curves joined there"]
    assert export.run(CFG, **inputs).notes == []


# ---------------------------------------------------------------------------------------------
# Strokes through their sharp corners (export.corners)
# ---------------------------------------------------------------------------------------------

def _crossings_between_curves(curves) -> int:
    """Proper crossings of segments of *different* curves (a stroke crossing itself does not count)."""
    segs = [(n, p[k], p[k + 1]) for n, c in enumerate(curves) for p in [np.asarray(c["points"])]
            for k in range(len(p) - 1)]
    cross = lambda o, a, b: (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])  # noqa: E731
    hits = 0
    for i, (n, a, b) in enumerate(segs):
        for m, c, d in segs[i + 1:]:
            if m != n and cross(a, b, c) * cross(a, b, d) < 0 and cross(c, d, a) * cross(c, d, b) < 0:
                hits += 1
    return hits


def _self_crossing_stroke():
    # One stroke (0,0) -> corner (40,40) -> corner (40,0) -> end (0,41.3): its first and last legs cross
    # near (20,20). The pieces come in mixed directions, as the selection returns them.
    a = _piece(1, _line([0, 0], [40, 40]), [1, 5], [0, 1])
    b = _piece(2, _line([40, 0], [40, 40]), [5, 5], [2, 1])          # runs backwards
    c = _piece(3, _line([40, 0], [0, 41.3]), [5, 1], [2, 3])
    return [a, b, c]


def test_a_stroke_through_its_corners_is_one_curve_that_crosses_only_itself():
    pieces = _self_crossing_stroke()
    assert _crossings_between_curves(pieces) == 1                   # as selected: two curves cross
    out = export.join_at_corners(pieces)
    assert len(out) == 1 and sorted(out[0]["parts"]) == [1, 2, 3]
    c = out[0]
    pts = np.asarray(c["points"])
    assert np.hypot(*np.diff(pts, axis=0).T).max() <= 0.6            # continuous, no jump at a joint
    assert {tuple(np.round(pts[i])) for i in c["corners"]} == {(40.0, 40.0), (40.0, 0.0)}
    assert sorted(c["end_keypoints"]) == [0, 3] and c["end_types"] == [1, 1]
    assert _crossings_between_curves(out) == 0
    # Through run(): on by default, off by its switch.
    inputs = _inputs([p["points"] for p in pieces], [0, 1, 2], shape=(48, 48))
    for p, c in zip(inputs["topology"].data["paths"], pieces):
        p["end_types"], p["end_keypoints"] = c["end_types"], c["end_keypoints"]
    assert len(export.run(CFG, **inputs).data["curves"]) == 1
    assert len(export.run(_cfg(corners={"enabled": False}, meetings={"enabled": False}), **inputs).data["curves"]) == 3


def test_corners_where_three_ends_meet_or_one_curve_closes_are_left():
    a, b, c = _self_crossing_stroke()
    spur = _piece(4, _line([40, 40], [48, 48]), [5, 1], [1, 4])      # a third end at corner 1
    out = export.join_at_corners([a, b, c, spur])
    assert sorted(sorted(o["parts"]) for o in out) == [[1], [2, 3], [4]]
    # A triangle in three pieces: one curve, opened at a corner, never closed on itself.
    tri = [_piece(1, _line([0, 0], [40, 0]), [5, 5], [0, 1]), _piece(2, _line([40, 0], [20, 30]), [5, 5], [1, 2]),
           _piece(3, _line([20, 30], [0, 0]), [5, 5], [2, 0])]
    out = export.join_at_corners(tri)
    assert len(out) == 1 and len(out[0]["corners"]) == 2
    assert out[0]["end_keypoints"][0] == out[0]["end_keypoints"][1]
    # A single curve whose two ends share the corner keypoint is not closed either.
    loop = _piece(5, [[0, 0], [10, 10], [20, 0], [0, 0]], [5, 5], [7, 7])
    assert export.join_at_corners([loop])[0]["corners"] == []


def test_the_bezier_fit_keeps_the_corners_sharp():
    from stages.export import fit_with_corners

    c = export.join_at_corners(_self_crossing_stroke())[0]
    pts = np.asarray(c["points"])
    assert len(c["corners"]) == 2
    def turns_at_corners(pieces):
        """Turn (degrees) between the tangents in and out of each corner vertex, None if no piece joint there."""
        out = []
        for i in c["corners"]:
            k = [n for n in range(1, len(pieces)) if np.allclose(pieces[n][0], pts[i])]
            if not k:
                out.append(None)
                continue
            t_in, t_out = pieces[k[0] - 1][3] - pieces[k[0] - 1][2], pieces[k[0]][1] - pieces[k[0]][0]
            cosang = t_in @ t_out / (np.linalg.norm(t_in) * np.linalg.norm(t_out))
            out.append(np.degrees(np.arccos(np.clip(cosang, -1, 1))))
        return out

    sharp = turns_at_corners(fit_with_corners(pts, c["corners"], 0.5))
    assert all(t is not None and t > 45.0 for t in sharp)           # the corners stay corners
    # The plain fit joins its pieces with a common tangent: the corners are rounded off.
    assert all(t is None or t < 1.0 for t in turns_at_corners(export.fit_cubic_beziers(pts, 0.5)))


def test_a_stroke_broken_by_a_small_gap_is_one_curve():
    """export.gaps: free ends facing each other across a gap of ≤ max(6 px, 2 widths) are joined."""
    from stages.export.gaps import close_gaps

    left = _piece(1, _line([10, 20], [50, 20]), [1, 1], [0, 1])
    right = _piece(2, _line([85, 21], [55, 20]), [1, 1], [2, 3])      # runs backwards, 5-px gap
    out = close_gaps([left, right], 6.0, 2.0, 30.0, 5.0)
    assert len(out) == 1 and sorted(out[0]["parts"]) == [1, 2] and out[0]["corners"] == []
    pts = np.asarray(out[0]["points"])
    assert {tuple(np.round(pts[0])), tuple(np.round(pts[-1]))} == {(10.0, 20.0), (85.0, 21.0)}
    assert sorted(out[0]["end_keypoints"]) == [0, 2]                 # the far ends
    # Through run(): on by default, off by its switch.
    inputs = _inputs([left["points"], right["points"]], [0, 1], shape=(48, 96))
    for p, c in zip(inputs["topology"].data["paths"], (left, right)):
        p["end_types"], p["end_keypoints"] = c["end_types"], c["end_keypoints"]
    assert len(export.run(CFG, **inputs).data["curves"]) == 1
    assert len(export.run(_cfg(gaps={**CFG["gaps"], "enabled": False}), **inputs).data["curves"]) == 2


def test_a_gap_narrower_than_the_free_radius_closes_between_the_two_tips():
    """Two ends of one broken stroke 2.5 px apart, each estimated 3.2 px wide: each end has the other
    curve within max(2, w), so neither counted as free and the break stayed (val_qd_trumpet_1_pencil,
    val_s3_17_pencil); an end near nothing but the other curve's tip is free for that tip alone."""
    from stages.export.gaps import close_gaps

    left = _piece(1, _line([10, 20], [50, 20]), [0, 0], [-1, -1], width=3.2)
    right = _piece(2, _line([52.5, 20.5], [90, 21]), [0, 0], [-1, -1], width=3.2)
    out = close_gaps([left, right], 6.0, 2.0, 30.0, 5.0)
    assert len(out) == 1 and sorted(out[0]["parts"]) == [1, 2]
    # Beside the tip, a third curve passing by: a junction, not a gap; the ends stay.
    by = _piece(3, _line([51, 0], [51, 40]), [1, 1], [4, 5])
    assert len(close_gaps([left, right, by], 6.0, 2.0, 30.0, 5.0)) == 3
    # Near the *middle* of another curve (a T's stem short of its bar): not a tip; stays.
    bar = _piece(4, _line([52.5, 0], [52.5, 40]), [1, 1], [6, 7])
    assert len(close_gaps([left, bar], 6.0, 2.0, 30.0, 5.0)) == 2


@pytest.mark.parametrize("case", ["wide", "askew", "at_a_junction", "own_ends"])
def test_gaps_that_are_not_a_broken_stroke_stay(case):
    from stages.export.gaps import close_gaps

    left = _piece(1, _line([10, 20], [50, 20]), [1, 1], [0, 1])
    if case == "wide":                          # 10 px: more than max(6, 2 × 3) px
        other = [_piece(2, _line([60, 20], [90, 20]), [1, 1], [2, 3])]
    elif case == "askew":                       # the second piece leaves the gap at 90°
        other = [_piece(2, _line([54, 20], [54, 50]), [1, 1], [2, 3])]
    elif case == "at_a_junction":               # the first piece's end lies on a third curve (a T's stem)
        other = [_piece(2, _line([55, 20], [85, 20]), [1, 1], [2, 3]),
                 _piece(3, _line([51, 0], [51, 40]), [1, 1], [4, 5])]
    else:                                       # one curve's own two ends across a 4-px gap: a ring stays open
        ring = [[50 + 20 * np.cos(t), 40 + 20 * np.sin(t)] for t in np.linspace(0.2, 2 * np.pi - 0.01, 200)]
        left, other = _piece(1, np.array(ring), [1, 1], [0, 1]), []
    out = close_gaps([left, *other], 6.0, 2.0, 30.0, 5.0)
    assert len(out) == 1 + len(other)


def test_a_lambda_rerun_imports_no_scipy_spatial():
    # flow → select → export is what a λ sweep re-runs; scipy.spatial's import (k-d trees) was about
    # a twentieth of that re-run, so the export finds near points with its own grid.
    import subprocess
    import sys

    code = ("import sys, pipeline.cli, stages.flow.stage, stages.select.stage, stages.export.stage; "
            "print(sorted(m for m in sys.modules if m.startswith('scipy.spatial')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
