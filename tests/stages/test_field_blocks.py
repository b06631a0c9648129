"""Tests for the field's and the extension's solves by blocks of band components (issue 54)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from stages import extension, field, synthetic
from stages.field import solver

ROOT = Path(__file__).resolve().parents[2]
FIELD_CFG = field.FieldConfig(**yaml.safe_load((ROOT / "conf" / "field" / "default.yaml").read_text()))
EXT_CFG = extension.ExtensionConfig(**yaml.safe_load((ROOT / "conf" / "extension" / "default.yaml").read_text()))
THRESHOLD = 165 / 255  # the reference's ink threshold (grey < 165)
GAP = 16  # paper between the two drawings, wider than the extension's ring on both sides


def _two_drawings():
    """A line and a vee side by side, as one picture, and each alone."""
    a, b = synthetic.line(size=64, angle=17.0, width=3.0).grey, synthetic.vee(size=64, width=3.0).grey
    both = np.ones((64, 128 + GAP))
    both[:, :64], both[:, 64 + GAP:] = a, b
    return both, a, b


def test_blocks_are_independent_and_cover_the_unknowns():
    grey, _, _ = _two_drawings()
    mask = grey < THRESHOLD
    n = int(mask.sum())
    assert [b.tolist() for b in solver._solve_blocks(mask, mask)] == [list(range(n))]  # small: one block
    blocks = solver._solve_blocks(mask, mask, limit=1)
    assert len(blocks) >= 2 and np.array_equal(np.sort(np.concatenate(blocks)), np.arange(n))
    assert all(np.all(np.diff(b) > 0) for b in blocks)  # raster order within a block
    k = solver._smart_laplacian(mask, np.ones(mask.shape))
    block_of = np.empty(n, int)
    for i, b in enumerate(blocks):
        block_of[b] = i
    coo = k.tocoo()
    assert np.array_equal(block_of[coo.row], block_of[coo.col])  # no entry couples two blocks


def test_a_drawings_field_does_not_depend_on_the_drawing_beside_it(monkeypatch):
    """Each block stops on its own residual: a drawing on a page with others gets the field it gets
    alone (its own pieces' data terms, one solve), not one whose CG ran until the page's slowest part
    converged.  On one system for the page the two parts differ at the solver tolerance."""
    monkeypatch.setattr(solver, "BLOCK_UNKNOWNS", 1, raising=False)  # every component a block
    grey, a, b = _two_drawings()
    cfg = field.FieldConfig(**dict(vars(FIELD_CFG), max_singularity_iterations=1))
    windows = [(slice(0, 64), slice(0, 64)), (slice(0, 64), slice(64 + GAP, 128 + GAP))]
    page = field.compute_field(grey, grey < THRESHOLD, cfg, windows)
    for part, win in zip((a, b), windows):
        alone = field.compute_field(part, part < THRESHOLD, cfg)
        scale = np.abs(alone["c0"]).max()
        assert np.abs(page["c0"][win] - alone["c0"]).max() <= 1e-12 * scale
        assert np.abs(page["c2"][win] - alone["c2"]).max() <= 1e-12 * scale


def test_a_drawings_extension_does_not_depend_on_the_drawing_beside_it(monkeypatch):
    """The same for the extension's ring (blocks of the dilated band's components), from one field."""
    monkeypatch.setattr(solver, "BLOCK_UNKNOWNS", 1, raising=False)
    grey, _, _ = _two_drawings()
    mask = grey < THRESHOLD
    f = field.compute_field(grey, mask, FIELD_CFG)
    page = extension.extend_field(f["c0"], f["c2"], mask, f["smart_weights"], EXT_CFG)[0]
    for cols in (slice(0, 64), slice(64 + GAP, 128 + GAP)):
        sub = (slice(None), cols)
        alone = extension.extend_field(f["c0"][sub], f["c2"][sub], mask[sub], f["smart_weights"][sub], EXT_CFG)[0]
        assert np.abs(page[sub] - alone).max() <= 1e-12 * np.abs(alone).max()
