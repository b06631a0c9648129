"""stages.prep.invert: light strokes on dark paper become ink on paper; ink on paper is left alone."""

from __future__ import annotations

import numpy as np

from stages.prep.invert import MID_GREY, invert


def _chalk() -> np.ndarray:
    """A light 3-px cross on dark paper (a blackboard)."""
    grey = np.full((40, 40), 0.15)
    grey[19:22, 5:35] = 0.9
    grey[5:35, 19:22] = 0.9
    return grey


def test_light_strokes_on_dark_paper_are_inverted_and_said():
    grey = _chalk()
    out, notes = invert(grey, "auto")
    np.testing.assert_array_equal(out, 1.0 - grey)
    assert notes == ["light strokes on dark paper (paper level 0.15): inverted (prep.invert)"]


def test_dark_strokes_on_light_paper_are_left_as_they_are():
    grey = 1.0 - _chalk()
    out, notes = invert(grey, "auto")
    assert out is grey and notes == []


def test_always_and_never():
    light = 1.0 - _chalk()
    out, notes = invert(light, "always")
    np.testing.assert_array_equal(out, 1.0 - light)
    assert notes == ["inverted (prep.invert=always)"]
    dark = _chalk()
    out, notes = invert(dark, "never")
    assert out is dark and notes == []


def test_the_line_is_mid_grey():
    assert MID_GREY == 0.5
    assert invert(np.full((8, 8), 0.49), "auto")[1] and not invert(np.full((8, 8), 0.51), "auto")[1]
