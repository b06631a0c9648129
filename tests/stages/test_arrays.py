"""Array helpers shared by the stages (stages/arrays.py)."""

from __future__ import annotations

import numpy as np
import pytest

from stages.arrays import sorted_unique


@pytest.mark.parametrize("values", [
    np.zeros(0, np.int64), np.array([7]), np.array([3, 3, 3]), np.array([-2, 5, -2, 0, 5], np.int32),
    np.arange(12, dtype=np.uint8).reshape(3, 4) % 5,
    np.random.default_rng(0).integers(0, 10**12, 200_000),    # mostly distinct, as the graph's keys
    np.random.default_rng(1).integers(-40, 40, 5_000),        # many repeats
])
def test_sorted_unique_is_numpys_unique(values):
    """The same values, order and dtype as ``np.unique`` (which the graph and topology stages called)."""
    got, want = sorted_unique(values), np.unique(values)
    assert got.dtype == want.dtype and np.array_equal(got, want)
    assert values.size == 0 or got.base is not values   # a new array: the caller's is left as it was
