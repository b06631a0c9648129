"""Tests for the field's singularity loop on band vectors (issue 54, item 2): the same bits as the
image-sized steps it replaces, and memory that follows the band rather than the page."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import yaml

from stages import field, synthetic
from stages.artifact import Artifact
from stages.field import data_terms, roots, solver

ROOT = Path(__file__).resolve().parents[2]
FIELD_CFG = yaml.safe_load((ROOT / "conf" / "field" / "default.yaml").read_text())
THRESHOLD = 165 / 255  # the reference's ink threshold (grey < 165)


def _band(seed: int = 0, shape=(40, 30)):
    rng = np.random.default_rng(seed)
    mask = rng.random(shape) < 0.7
    mask[0, :5] = mask[:, -1] = True  # band pixels on the image border (s = 1 there)
    return rng, mask


def test_band_smart_weights_are_the_image_ones_bit_for_bit():
    rng, mask = _band()
    w = rng.random(mask.shape)
    ring = data_terms.band_ring(w, mask)
    w_b = w[mask]
    assert data_terms.band_smart_weights(w_b, ring).tobytes() == data_terms.smart_weights(w)[mask].tobytes()
    zeroed = mask & (rng.random(mask.shape) < 0.3)  # the loop zeroes band pixels only
    w[zeroed] = 0.0
    w_b[zeroed[mask]] = 0.0
    assert data_terms.band_smart_weights(w_b, ring).tobytes() == data_terms.smart_weights(w)[mask].tobytes()


def test_band_singular_pixels_are_the_image_test():
    rng, mask = _band(1)
    r = rng.standard_normal(mask.shape + (2,)) + 1j * rng.standard_normal(mask.shape + (2,))
    image = field.singular_pixels(field.singular_cells(r, mask), mask.shape)
    cells = roots.band_cells(mask, solver._region_index(mask))
    band = roots.band_singular_pixels(r[mask], cells)
    assert image.any() and not (image & ~mask).any()
    assert np.array_equal(band, image[mask])


def _page(height: int = 600, width: int = 700):
    """The example drawing at the top left of a larger sheet of paper."""
    g = synthetic.example_drawing().grey
    page = np.ones((height, width), np.float32)
    page[:g.shape[0], :g.shape[1]] = g
    return Artifact(arrays={"grey": page, "mask": page < THRESHOLD})


def test_tie_break_by_strips_is_the_whole_image_one(monkeypatch):
    """The tie-break smooths strips of rows (each with the filter's reach): the same orientation and
    artifact as one smoothing of the whole image."""
    page = _page(300, 320)
    whole = field.run(FIELD_CFG, prep=page)
    monkeypatch.setattr(roots, "TIE_STRIP_PIXELS", 7 * 320)  # 7-row strips, under the reach of 8
    strips = field.run(FIELD_CFG, prep=page)
    assert whole.data["tie_swapped"] > 0
    assert whole.data == {**strips.data, "solve_seconds": whole.data["solve_seconds"]}
    for name, array in whole.arrays.items():
        assert array.tobytes() == strips.arrays[name].tobytes(), name


def test_field_memory_follows_the_band_not_the_page():
    """Paper around a drawing costs the data terms' image filters, not image-sized copies per pass of
    the loop or a complex128 image of the roots: 214 B per page pixel before, 132 after."""
    page = _page()
    tracemalloc.start()
    try:
        field.run(FIELD_CFG, prep=page)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak / page["grey"].size < 170
