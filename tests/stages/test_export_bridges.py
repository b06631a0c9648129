"""Export: two free curve ends that the ink bridges are joined at a corner (``export.bridges``)."""

from __future__ import annotations

import numpy as np

from test_export import CFG, _cfg, _line, _piece, _run_pieces


def _ell_mask(shape=(48, 48), w=3):
    # an L of ink: a bar y ∈ [20-w/2, 20+w/2], x ∈ [4, 27], and a leg x ∈ [26-w/2, 26+w/2], y ∈ [18, 44]
    mask = np.zeros(shape, bool)
    mask[19:22, 4:28] = True
    mask[18:44, 25:28] = True
    return mask


def _corner_found_twice():
    # One stroke turning at (26, 20): the detector found the corner twice, 6.4 px apart (keypoints 3
    # and 4), and the selection ended one curve at each.
    bar = _piece(1, _line([5, 20.5], [21, 20.5]), [1, 5], [0, 3])
    leg = _piece(2, _line([26.5, 25.5], [26.5, 43]), [5, 1], [4, 1])
    return [bar, leg]


def _run(pieces, cfg, mask):
    return _run_pieces(pieces, cfg, mask.shape, mask)


def test_two_free_ends_at_a_corner_found_twice_become_one_curve_with_a_corner():
    pieces, mask = _corner_found_twice(), _ell_mask()
    out = _run(pieces, CFG, mask)
    assert len(out) == 1 and sorted(out[0]["parts"]) == [100, 101]
    assert sorted(out[0]["end_keypoints"]) == [0, 1] and len(out[0]["corners"]) == 1
    assert len(_run(pieces, _cfg(bridges={**CFG["bridges"], "enabled": False}), mask)) == 2


def test_ends_without_ink_between_or_without_a_corner_keypoint_are_left():
    pieces = _corner_found_twice()
    gap = _ell_mask()
    gap[18:25, 21:28] = False                      # the corner's ink missing: two strokes, not one
    assert len(_run(pieces, CFG, gap)) == 2
    plain = [dict(p, end_types=[1, 1]) for p in pieces]   # two endpoints near each other: the detector says ends
    assert len(_run(plain, CFG, _ell_mask())) == 2
    assert len(_run(plain, _cfg(bridges={**CFG["bridges"], "corners_only": False}), _ell_mask())) == 1
    # a corner keypoint beside an endpoint keypoint: the detector says a stroke ends there
    tip = [pieces[0], dict(pieces[1], end_types=[1, 1])]
    assert len(_run(tip, CFG, _ell_mask())) == 2
