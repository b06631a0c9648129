"""stages.prep.pixels: the helpers on pixel grids that prep's steps share."""

from __future__ import annotations

import numpy as np

from stages.prep.pixels import CELL_PX, blocks, smoothed


def test_blocks_spreads_each_cell_over_its_block_of_pixels():
    cells = np.array([[1, 2], [3, 4]], np.uint8)
    out = blocks(cells, 2, 3)
    assert out.shape == (4, 6) and out.dtype == np.uint8
    np.testing.assert_array_equal(out[:2, :3], 1)
    np.testing.assert_array_equal(out[2:, 3:], 4)
    # the mean of each block gives the cells back
    np.testing.assert_array_equal(out.reshape(2, 2, 2, 3).mean(axis=(1, 3)), cells)
    assert CELL_PX == 16


def test_smoothed_blurs_by_sigma_and_leaves_sigma_zero_alone():
    grey = np.ones((21, 21), np.float32)
    grey[10, 10] = 0.0
    assert smoothed(grey, 0.0) is grey
    out = smoothed(grey, 1.5)
    assert out.dtype == np.float32 and out[10, 10] > 0.5 and out[10, 12] < 1.0
    assert abs(float(out.sum()) - float(grey.sum())) < 1e-3       # a blur moves grey, does not add it
