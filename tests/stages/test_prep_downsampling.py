"""stages.prep.downsampling: wide strokes worked on at 1/k of the resolution, by block means."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from stages.prep import DownsampleConfig
from stages.prep.downsampling import downsample, downsample_factor, downsampled

CFG = DownsampleConfig(enabled=True, above_width=7.0, target_width=3.5, max_factor=4)


def test_the_factor_brings_strokes_to_the_target_width():
    assert downsample_factor(6.9, CFG) == 1                 # not wide enough
    assert downsample_factor(7.0, CFG) == 2
    assert downsample_factor(12.0, CFG) == 3
    assert downsample_factor(40.0, CFG) == 4                # max_factor
    assert downsample_factor(40.0, replace(CFG, enabled=False)) == 1


def test_block_means_padded_with_paper():
    grey = np.zeros((5, 7), np.float32)
    out = downsample(grey, 2)
    assert out.shape == (3, 4) and out.dtype == np.float32
    assert (out[:2, :3] == 0).all()
    # the last row and column of blocks are half paper
    assert out[2, 0] == 0.5 and out[0, 3] == 0.5 and out[2, 3] == 0.75


def test_the_step_shrinks_wide_strokes_and_says_so():
    grey = np.ones((64, 64), np.float32)
    grey[20:34, 4:60] = 0.0
    mask = grey < 0.5
    out, k, notes = downsampled(grey, mask, 14.0, CFG)
    assert k == 4 and out.shape == (16, 16)
    assert notes == [("strokes about 14.0 px wide: working at 1/4 resolution "
                      "(prep.downsample; the curves are mapped back)")]
    assert downsampled(grey, mask, 3.0, CFG) == (grey, 1, [])
    assert downsampled(grey, mask, 14.0, replace(CFG, enabled=False)) == (grey, 1, [])
