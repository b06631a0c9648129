"""Key vertices move onto corner and junction keypoints only as far as the ink's centre region allows.

A corner keypoint near the band's edge (a stroke of two drawn side by side in one band:
qd_dog_01_pencil, tu_angel_163_pencil on realvec_dev) dragged the curves through it against that
side, leaving the other stroke 3–4 px away; see :func:`stages.topology.key_vertices.snap_position`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import ndimage
from synthetic_graph import synthetic_inputs

from stages.synthetic import Drawing, render
from stages.topology import run
from stages.topology.key_vertices import snap_position

ROOT = Path(__file__).resolve().parents[2]
CFG = yaml.safe_load((ROOT / "conf" / "topology" / "default.yaml").read_text())
WIDTH = 6.0
APEX = np.array([40.0, 14.0])


def _ell(corner_xy) -> Drawing:
    """An L of width 6 (ends 0 and 1) with its corner keypoint (2) at ``corner_xy``."""
    s = np.array([[10.0, 14.0], APEX, [40.0, 50.0]])
    return Drawing(render((64, 64), [s], WIDTH), [s], WIDTH,
                   [(10.0, 14.0, 1), (40.0, 50.0, 1), (*corner_xy, 5)])


def _off_centre(p) -> float:
    """Distance of a point (x, y) from the L's centre lines."""
    x, y = p
    return min(np.hypot(max(10 - x, 0, x - 40), y - 14), np.hypot(x - 40, max(14 - y, 0, y - 50)))


def _ends_at(art, keypoint: int) -> list[np.ndarray]:
    """Positions where the paths end on keypoint index ``keypoint``."""
    return [np.asarray(p["xy"][i]) for p in art.data["paths"]
            for i, k in zip((0, -1), p["end_keypoints"]) if k == keypoint]


def _corner_ends(art) -> list[np.ndarray]:
    """Positions where the paths end on the corner keypoint (index 2)."""
    return _ends_at(art, 2)


@pytest.mark.parametrize("offset", [2.4, 2.6])
def test_corner_keypoint_at_the_inner_edge_does_not_drag_the_corner_across_the_stroke(offset):
    kp = APEX + np.array([-offset, offset])        # 0.4–0.6 px inside the inner corner's edges
    d = _ell(kp)
    art = run(CFG, **synthetic_inputs(d))
    ends = _corner_ends(art)
    assert len(ends) == 2                            # both arms end on the corner
    assert _off_centre(kp) >= 2.4 - 1e-9
    for e in ends:
        # at least 0.9 px nearer the centre lines than the keypoint, on the ink's deep side
        assert _off_centre(e) <= _off_centre(kp) - 0.9
        assert ndimage.map_coordinates(ndimage.distance_transform_edt(d.grey < 165 / 255), [[e[1] - 0.5], [e[0] - 0.5]],
                                       order=1)[0] >= CFG["keypoint_min_depth"] * WIDTH / 2 - 0.3
    # the authors' rule (min depth 0) puts the corner on the keypoint, 3.4–3.7 px off the centre lines
    art0 = run({**CFG, "keypoint_min_depth": 0.0}, **synthetic_inputs(d))
    for e in _corner_ends(art0):
        np.testing.assert_allclose(e, kp, atol=1e-6)


def test_corner_keypoint_on_the_centre_lines_is_reached_exactly():
    d = _ell(APEX + np.array([0.4, -0.3]))           # a slightly off detection, still deep in the ink
    art = run(CFG, **synthetic_inputs(d))
    ends = _corner_ends(art)
    assert len(ends) == 2
    for e in ends:
        np.testing.assert_allclose(e, APEX + np.array([0.4, -0.3]), atol=1e-6)


def test_endpoint_keypoints_are_always_reached():
    d = _ell(APEX)
    art = run(CFG, **synthetic_inputs(d))
    for p in art.data["paths"]:
        for i, k in zip((0, -1), p["end_keypoints"]):
            if k in (0, 1):
                np.testing.assert_allclose(p["xy"][i], d.keypoints[k][:2], atol=1e-6)


def test_snap_position_stops_where_the_band_gets_shallow():
    band = np.zeros((20, 40), bool)
    band[6:14, :] = True                             # horizontal band, rows 6..13: centre y = 10, half width 4
    depth = ndimage.distance_transform_edt(band)
    v = np.array([20.0, 10.0])
    # deep keypoint: reached
    np.testing.assert_allclose(snap_position(depth, v, [23.0, 11.0], 4.0, 0.8), [23.0, 11.0])
    # keypoint at the edge: stops where depth first falls below 0.8 × 4 = 3.2
    p = snap_position(depth, v, [20.0, 13.5], 4.0, 0.8)
    assert p[0] == 20.0 and 10.5 <= p[1] <= 11.5       # EDT counts from pixel centres: ~0.5 px more than the ink depth
    # 0 = always the keypoint
    np.testing.assert_allclose(snap_position(depth, v, [20.0, 13.5], 4.0, 0.0), [20.0, 13.5])
    # never asks for more depth than the vertex has (thin band): reaches the keypoint
    thin = np.zeros((20, 40), bool)
    thin[9:11, :] = True
    dt = ndimage.distance_transform_edt(thin)
    np.testing.assert_allclose(snap_position(dt, [20.0, 10.0], [24.0, 10.0], 4.0, 0.8), [24.0, 10.0])


def test_junction_keypoint_at_the_far_edge_of_the_bar_keeps_the_curve_ends_in_the_ink():
    """A T whose junction keypoint sits 0.5 px inside the bar's far edge (a detection at the edge of
    a blob): the curve ends stop inside the ink instead of sticking out to its edge."""
    bar = np.array([[10.0, 14.0], [54.0, 14.0]])
    stem = np.array([[32.0, 14.0], [32.0, 50.0]])
    kp = np.array([32.0, 14.0 - 2.5])
    d = Drawing(render((64, 64), [bar, stem], WIDTH), [bar, stem], WIDTH,
                [(10.0, 14.0, 1), (54.0, 14.0, 1), (32.0, 50.0, 1), (*kp, 3)])
    art = run(CFG, **synthetic_inputs(d))
    ends = _ends_at(art, 3)
    assert ends
    for e in ends:
        assert abs(e[1] - 14.0) <= 2.5 - 0.4               # nearer the bar's centre line than the keypoint
    art0 = run({**CFG, "keypoint_min_depth": 0.0}, **synthetic_inputs(d))
    ends0 = _ends_at(art0, 3)
    assert ends0
    for e in ends0:                                         # the authors' rule: onto the keypoint
        np.testing.assert_allclose(e, kp, atol=1e-6)
