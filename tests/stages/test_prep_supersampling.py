"""stages.prep.supersampling: thin aliased strokes worked on at an integer multiple of the resolution."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from stages.prep import SupersampleConfig
from stages.prep.supersampling import supersample, supersample_factor, supersampled
from stages.prep.width import stroke_width

CFG = SupersampleConfig(enabled=True, below_width=1.9, max_soft_edges=0.03, target_width=3.0, max_factor=2,
                        max_pixels=9_000_000, blur=0.5)


def test_only_thin_aliased_strokes_are_supersampled():
    assert supersample_factor(1.0, 0.0, (100, 100), CFG) == (2, None)
    assert supersample_factor(1.0, 0.5, (100, 100), CFG) == (1, None)       # anti-aliased: soft edges
    assert supersample_factor(2.5, 0.0, (100, 100), CFG) == (1, None)       # wide enough
    assert supersample_factor(0.0, 0.0, (100, 100), CFG) == (1, None)       # no ink
    assert supersample_factor(1.0, 0.0, (100, 100), replace(CFG, enabled=False)) == (1, None)


def test_the_factor_is_capped_by_max_pixels_and_says_so():
    factor, note = supersample_factor(1.0, 0.0, (100, 100), replace(CFG, max_pixels=30_000))
    assert factor == 1 and "would need 2x resolution" in note and "allows 1x" in note


def test_the_zoom_is_pixel_aligned():
    grey = np.ones((10, 10), np.float32)
    grey[4, 6] = 0.0
    out = supersample(grey, 2, 0.0)
    assert out.shape == (20, 20) and out.dtype == np.float32
    # internal pixels [8:10, 12:14] cover source pixel [4, 6]: the darkest are there
    assert out[8:10, 12:14].max() < out.min() + 0.5 and np.unravel_index(out.argmin(), out.shape) in \
        [(8, 12), (8, 13), (9, 12), (9, 13)]
    np.testing.assert_array_equal(supersample(np.full((4, 4), 0.7, np.float32), 3, 0.5), np.float32(0.7))


def test_the_step_zooms_an_aliased_one_pixel_line_and_says_so():
    grey = np.ones((40, 40), np.float32)
    mask = np.zeros((40, 40), bool)
    mask[np.arange(5, 35), np.arange(5, 35)] = True
    grey[mask] = 0.0
    out, factor, notes = supersampled(grey, mask, stroke_width(mask), CFG)
    assert factor == 2 and out.shape == (80, 80)
    assert notes == [("strokes about 0.7 px wide: working at 2x resolution "
                      "(prep.supersample; the curves are mapped back)")]
    assert supersampled(grey, mask, stroke_width(mask), replace(CFG, enabled=False)) == (grey, 1, [])
