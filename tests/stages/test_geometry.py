"""Shared plane geometry (stages/geometry.py) on hand-computed cases."""

from __future__ import annotations

import numpy as np

from stages.geometry import arc_length, bilinear, point_at_arc, resample_uniform, segment_in_band, subdivide, turn_deg


def test_bilinear():
    c0 = np.zeros((4, 5), np.complex64)
    c2 = np.zeros((4, 5), np.complex64)
    c0[1, 1], c0[1, 2] = 1 + 1j, 3 + 0j
    c2[1, 1] = 2j
    pts = [[1.5, 1.5], [2.0, 1.5], [2.5, 2.0], [-3, 1.5]]
    assert np.allclose(bilinear(c0, pts), [1 + 1j, 2 + 0.5j, 1.5, 0])  # centre, midpoint, half off-band, outside
    assert np.allclose(bilinear(c2, pts), [2j, 1j, 0, 0])
    s0 = bilinear(c0, (1.5, 1.5))
    assert np.ndim(s0) == 0 and np.isclose(s0, 1 + 1j)


def test_polyline_arc_and_resampling():
    p = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]])
    assert np.allclose(arc_length(p), [0, 3, 7])
    assert np.allclose(point_at_arc(p, arc_length(p), 5.0), [3, 2])
    assert np.allclose(point_at_arc(p, arc_length(p), np.array([0.0, 9.0])), [[0, 0], [3, 4]])  # clamped
    q, s = resample_uniform(np.vstack([p[:1], p]), 1.0)  # a repeated vertex is dropped
    assert len(q) == 8 and np.allclose(s, np.arange(8)) and np.allclose(q[-1], [3, 4])
    q, s = subdivide(p, 2.0)
    assert np.allclose(s, [0, 1.5, 3, 5, 7]) and np.allclose(q[2], [3, 0])  # vertices kept


def test_segment_in_band_and_turn():
    band = np.zeros((5, 5), bool)
    band[2, :] = True
    assert segment_in_band(band, np.array([0.5, 2.5]), np.array([4.5, 2.5]))
    assert not segment_in_band(band, np.array([0.5, 2.5]), np.array([4.5, 3.5]))
    assert not segment_in_band(band, np.array([0.5, 2.5]), np.array([5.5, 2.5]))  # leaves the image
    assert np.isclose(turn_deg(np.array([1.0, 0]), np.array([-1.0, 0])), 0)
    assert np.isclose(turn_deg(np.array([1.0, 0]), np.array([0, 1.0])), 90)
