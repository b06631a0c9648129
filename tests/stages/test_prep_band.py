"""stages.prep.band: the ink mask, its hole repair, the paper it is found against, and the band again
after a resampling."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from stages.config import from_section
from stages.errors import InputError
from stages.prep import PrepConfig
from stages.prep.band import band_at_scale, grey_and_band, narrow_band, paper_statistics

CFG = yaml.safe_load((Path(__file__).resolve().parents[2] / "conf" / "prep" / "default.yaml").read_text())
C = from_section(PrepConfig, CFG, "prep")


def _band(grey: np.ndarray, min_component_px: int = 1) -> np.ndarray:
    return narrow_band(grey, C.threshold, C.repair_passes, C.repair_neighbours, min_component_px, C.repair_max_grey)


def test_a_one_pixel_pinhole_of_paper_is_filled():
    grey = np.ones((20, 20), np.float32)
    grey[5:15, 5:15] = 0.0
    grey[9, 9] = 1.0                         # all 8 neighbours ink
    assert _band(grey)[9, 9]


def test_paper_with_fewer_than_eight_ink_neighbours_is_kept():
    """A notch of paper at a stroke's edge, and a two-pixel hole: 7 and 5 ink neighbours, paper-white."""
    grey = np.ones((20, 20), np.float32)
    grey[5:15, 5:15] = 0.0
    grey[5, 9] = 1.0                         # notch in the top edge: 5 ink neighbours
    grey[10, 9:11] = 1.0                     # two-pixel hole: 7 ink neighbours each
    mask = _band(grey)
    assert not mask[5, 9] and not mask[10, 9:11].any()


def test_grey_pencil_texture_is_repaired_with_six_of_eight_neighbours():
    grey = np.ones((20, 20), np.float32)
    grey[5:15, 5:15] = 0.0
    grey[10, 6:14] = 0.75                    # a lighter streak inside the stroke, not paper (≤ 0.85)
    assert _band(grey)[10, 6:14].all()
    # the same streak as white as paper stays out
    grey[10, 6:14] = 1.0
    assert not _band(grey)[10, 6:14].any()


def test_components_smaller_than_min_component_px_are_dropped():
    grey = np.ones((30, 30), np.float32)
    grey[2:4, 2:4] = 0.0                     # a 4-px speck
    grey[10:20, 10:13] = 0.0                 # a stroke
    mask = _band(grey, min_component_px=6)
    assert not mask[2:4, 2:4].any() and mask[10:20, 10:13].all()


def test_paper_statistics_are_the_paper_level_and_its_grain():
    rng = np.random.default_rng(0)
    grey = np.clip(0.9 + rng.normal(0, 0.02, (200, 200)), 0, 1)
    grey[50:150, 98:101] = 0.1               # 1.5 % ink does not move them
    level, grain = paper_statistics(grey)
    assert abs(level - 0.9) < 0.005 and abs(grain - 0.02) < 0.002
    assert paper_statistics(np.ones((10, 10))) == (1.0, 0.0)


def _square(grain: float) -> np.ndarray:
    """A faint 3-px square outline on 120×120 paper with Gaussian grain."""
    grey = np.full((120, 120), 0.86)
    grey[20:100, 20:23] = grey[20:100, 97:100] = grey[20:23, 20:100] = grey[97:100, 20:100] = 0.63
    return np.clip(grey + np.random.default_rng(3).normal(0, grain, grey.shape), 0, 1)


def test_clean_paper_keeps_the_configured_threshold():
    grey, mask, data = grey_and_band(_square(0.0), C)
    assert grey.dtype == np.float32 and mask.dtype == bool
    assert data["band_threshold"] == C.threshold and data["band_smoothing"] == 0.0 and data["paper_grain"] == 0.0
    assert mask[20:100, 20:23].all() and mask.sum() == 4 * 3 * 80 - 4 * 9
    assert data["ink_fraction"] == mask.mean()


def test_grainy_paper_lowers_the_threshold_and_smooths_the_band_only():
    grey, mask, data = grey_and_band(_square(0.05), C)
    assert data["band_threshold"] < C.threshold and data["band_smoothing"] == C.grain_smoothing
    assert mask.mean() < 0.2 and mask[20:100, 21].mean() > 0.9
    assert grey.std() > 0.05                 # the grey passed on is not blurred


def test_a_blank_page_and_a_page_of_ink_are_refused():
    with pytest.raises(InputError, match="blank image"):
        grey_and_band(np.ones((50, 50)), C)
    dark = np.zeros((50, 50))
    dark[:, :15] = 1.0                       # 70 % ink (the grain rule off: the median is no paper here)
    with pytest.raises(InputError, match="70% ink .* not a line drawing"):
        grey_and_band(dark, replace(C, paper_grain_sigmas=0.0))


def test_the_band_again_at_the_internal_resolution():
    """After a 2× zoom the band is found with the threshold that found it, specks by their source area."""
    grey, mask, data = grey_and_band(_square(0.0), C)
    zoomed = np.repeat(np.repeat(grey, 2, axis=0), 2, axis=1)
    np.testing.assert_array_equal(band_at_scale(zoomed, 2.0, None, data, C),
                                  np.repeat(np.repeat(mask, 2, axis=0), 2, axis=1))
    speck = zoomed.copy()
    speck[2:6, 2:6] = 0.0                    # 16 internal px = 4 source px < min_component_px
    assert not band_at_scale(speck, 2.0, None, data, C)[2:6, 2:6].any()
    with pytest.raises(InputError, match="no ink left at the internal resolution"):
        band_at_scale(np.ones_like(zoomed), 2.0, None, data, C)
