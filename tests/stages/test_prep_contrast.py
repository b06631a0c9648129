"""stages.prep.contrast: paper stretched to white, the darkest ink to black; a uniform page is blank."""

from __future__ import annotations

import numpy as np
import pytest

from stages.errors import InputError
from stages.prep import ContrastConfig
from stages.prep.contrast import normalise_contrast, stretched


def _faint_page() -> np.ndarray:
    """Grey paper (0.8) with a faint pencil square (0.5) covering about 6 % of it."""
    grey = np.full((100, 100), 0.8)
    grey[20:80, 20:23] = grey[20:80, 77:80] = 0.5
    return grey


def test_paper_becomes_white_and_the_faint_ink_black():
    out = normalise_contrast(_faint_page(), 0.5, 99.0, 0.08)
    assert out.dtype == np.float32
    assert (out[0] == 1.0).all() and (out[20:80, 20:23] == 0.0).all()


def test_sparse_ink_below_the_low_percentile_still_becomes_dark():
    """One short line on a big page: both percentiles are paper; the ink is what stands out of it."""
    grey = np.full((300, 300), 0.8)
    grey[150, 100:140] = 0.5                       # 0.04 % of the page
    out = normalise_contrast(grey, 0.5, 99.0, 0.08)
    assert out[150, 100:140].max() < 0.05 and (out[0] == 1.0).all()


def test_a_uniform_page_is_blank():
    with pytest.raises(InputError, match="blank image"):
        normalise_contrast(np.full((20, 20), 0.7), 0.5, 99.0, 0.08)


def test_the_step_off_keeps_the_grey_and_still_refuses_a_blank_page():
    off = ContrastConfig(enabled=False, low_percentile=0.5, high_percentile=99.0, min_contrast=0.08)
    grey = _faint_page()
    out = stretched(grey, off)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, grey.astype(np.float32))
    with pytest.raises(InputError, match="blank image"):
        stretched(np.full((20, 20), 0.7), off)
    on = ContrastConfig(enabled=True, low_percentile=0.5, high_percentile=99.0, min_contrast=0.08)
    np.testing.assert_array_equal(stretched(grey, on), normalise_contrast(grey, 0.5, 99.0, 0.08))
