"""stages.prep.width: the strokes' mean width and soft edges, measured on the band."""

from __future__ import annotations

import numpy as np

from stages.prep.width import soft_edges, stroke_width, width_words


def test_a_level_line_is_as_wide_as_it_is_drawn():
    mask = np.zeros((30, 60), bool)
    mask[10:14, 5:55] = True
    assert abs(stroke_width(mask) - 4.0) < 0.4


def test_a_diagonal_one_pixel_line_is_narrower_than_a_pixel():
    mask = np.eye(40, dtype=bool)
    assert abs(stroke_width(mask) - 1 / np.sqrt(2)) < 0.05
    assert stroke_width(np.zeros((5, 5), bool)) == 0.0


def test_soft_edges_tell_anti_aliased_from_aliased_ink():
    mask = np.zeros((20, 20), bool)
    mask[5:15, 9:11] = True
    grey = np.where(mask, 0.0, 1.0)
    assert soft_edges(grey, mask) == 0.0                  # each pixel ink or paper
    grey[5:15, 8] = grey[5:15, 11] = 0.5                  # a grey pixel either side of the stroke
    assert 0.5 < soft_edges(grey, mask) < 1.0
    assert soft_edges(grey, np.zeros_like(mask)) == 0.0


def test_a_filled_area_is_not_called_a_stroke():
    mask = np.zeros((60, 60), bool)
    mask[10:50, 10:50] = True
    assert width_words(stroke_width(mask), mask) == "ink filled in areas up to 40 px across, not drawn in strokes"
    line = np.zeros((30, 60), bool)
    line[10:13, 5:55] = True
    assert width_words(stroke_width(line), line) == f"strokes about {stroke_width(line):.1f} px wide"
