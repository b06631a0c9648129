"""Tests for stages/extension/: the field extended beyond the band, for the flow."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import ndimage as ndi

from stages import extension, field, synthetic
from stages.artifact import Artifact
from stages.errors import InputError

ROOT = Path(__file__).resolve().parents[2]
CFG = yaml.safe_load((ROOT / "conf" / "extension" / "default.yaml").read_text())
FIELD_CFG = yaml.safe_load((ROOT / "conf" / "field" / "default.yaml").read_text())
THRESHOLD = 165 / 255  # the reference's ink threshold (grey < 165)


def _inputs(grey, mask=None):
    mask = grey < THRESHOLD if mask is None else mask
    prep = Artifact(arrays={"grey": grey, "mask": mask})
    return {"prep": prep, "field": field.run(FIELD_CFG, prep=prep)}


def test_extension_fills_the_ring_and_nothing_beyond():
    d = synthetic.line(size=64, length=40, angle=17.0, width=3.0)
    mask = d.grey < THRESHOLD
    ins = _inputs(d.grey)
    art = extension.run(CFG, **ins)
    dist = ndi.distance_transform_edt(~mask)
    ring = ~mask & (dist <= CFG["radius"])
    beyond = dist > CFG["radius"]
    ext = np.abs(art["c0_ext"]) + np.abs(art["c2_ext"])
    assert (ext[ring] > 0).mean() > 0.99
    assert not ext[beyond].any()
    # Band values are the field's; the ring grows with the L1 distance (soft wall).
    assert np.array_equal(art["c0_ext"][mask], ins["field"]["c0"][mask])
    assert np.array_equal(art["c2_ext"][mask], ins["field"]["c2"][mask])
    taxicab = ndi.distance_transform_cdt(~mask, metric="taxicab")
    near, far = ring & (taxicab == 1), ring & (taxicab >= 4)
    assert np.median(ext[far]) > 2 * np.median(ext[near])
    # the radius and scale are this stage's: a wider ring reaches further, a larger scale is steeper
    wide = extension.run(dict(CFG, radius=8), **ins)
    assert (np.abs(wide["c0_ext"]) > 0)[~mask & (dist > 6) & (dist <= 7.5)].mean() > 0.99
    steep = extension.run(dict(CFG, scale=4.0), **ins)
    assert np.allclose(np.abs(steep["c0_ext"][ring]), 2 * np.abs(art["c0_ext"][ring]), rtol=1e-4, atol=1e-6)


def test_the_ring_is_the_smart_weighted_harmonic_extension_of_the_band():
    """Before the distance scaling the ring values solve the smart-weighted Laplace equation with the
    band held: the same solve as a direct sparse factorisation."""
    from scipy.sparse.linalg import spsolve

    from stages.field.solver import _smart_laplacian

    d = synthetic.vee(size=48, width=3)
    ins = _inputs(d.grey)
    mask = ins["prep"]["mask"]
    f = ins["field"]
    c0_ext, _, stats = extension.extend_field(f["c0"], f["c2"], mask, f["smart_weights"],
                                              extension.ExtensionConfig(radius=3, scale=1.0, cg_rtol=1e-12,
                                                                        cg_max_iterations=5000))
    assert stats["extension_cg_converged"]
    r = 3
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    dil = ndi.binary_dilation(mask, structure=xx * xx + yy * yy <= r * r)
    ring = dil & ~mask
    lap = _smart_laplacian(dil, np.asarray(f["smart_weights"], np.float64))
    in_ring = ring[dil]
    direct = spsolve(lap[in_ring][:, in_ring].tocsc(),
                     -(lap[in_ring][:, ~in_ring] @ np.asarray(f["c0"][mask], np.complex128)))
    dist = ndi.distance_transform_cdt(~mask, metric="taxicab")[ring]
    assert np.allclose(c0_ext[ring], direct * dist, atol=1e-8)


def test_an_empty_band_gives_an_empty_extension():
    grey = np.ones((20, 30), np.float32)
    art = extension.run(CFG, **_inputs(grey, mask=np.zeros((20, 30), bool)))
    for name in ("c0_ext", "c2_ext"):
        assert art[name].dtype == np.complex64 and art[name].shape == (20, 30) and not art[name].any()


def test_bad_input_is_a_clear_error():
    ins = _inputs(np.ones((10, 10), np.float32), mask=np.zeros((10, 10), bool))
    with pytest.raises(InputError, match="'field'"):
        extension.run(CFG, prep=ins["prep"])
    with pytest.raises(InputError, match="equal-shaped"):
        extension.run(CFG, prep=Artifact(arrays={"mask": np.zeros((10, 11), bool)}), field=ins["field"])
    with pytest.raises(InputError, match="radius"):
        extension.run({k: v for k, v in CFG.items() if k != "radius"}, **ins)
    for bad in ({"radius": -1}, {"scale": -2.0}, {"cg_rtol": 0.0}, {"cg_max_iterations": 0}):
        with pytest.raises(InputError, match="extension config"):
            extension.run(dict(CFG, **bad), **ins)


def test_a_capped_solve_says_so():
    d = synthetic.line(size=48, length=30, angle=17.0, width=3.0)
    art = extension.run(dict(CFG, cg_max_iterations=1), **_inputs(d.grey))
    assert any("extension.cg_max_iterations" in n for n in art.notes)
