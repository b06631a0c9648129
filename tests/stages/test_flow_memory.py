"""The flow's page-sized arrays (issue #54): the packed field is the only copy of the extended field."""

from __future__ import annotations

import tracemalloc

import numpy as np

from stages.flow import kernel


def test_packed_field_takes_no_page_sized_temporary():
    rng = np.random.default_rng(0)
    c0 = (rng.normal(size=(600, 500)) + 1j * rng.normal(size=(600, 500))).astype(np.complex64)
    c2 = (rng.normal(size=(600, 500)) + 1j * rng.normal(size=(600, 500))).astype(np.complex64)
    tracemalloc.start()
    fld = kernel._pack_field(c0, c2)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 1.1 * fld.nbytes
    assert fld.shape == (602, 502, 4) and not fld[0].any() and not fld[:, -1].any()
    np.testing.assert_array_equal(fld[1:-1, 1:-1, 0] + 1j * fld[1:-1, 1:-1, 1], c0)
    np.testing.assert_array_equal(fld[1:-1, 1:-1, 2] + 1j * fld[1:-1, 1:-1, 3], c2)
