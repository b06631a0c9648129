"""Thin anti-aliased strokes in a grey halo: a drawing enlarged from a low resolution (stages.prep.upscaling)."""

from __future__ import annotations

import io
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from stages import synthetic
from stages.errors import InputError
from stages.prep import DeblockConfig
from stages.prep.upscaling import block_edges, block_period, deblocked, edge_lattice

CONF = Path(__file__).resolve().parents[2] / "conf"
PREP = yaml.safe_load((CONF / "prep" / "default.yaml").read_text())
CFG = DeblockConfig(**PREP["deblock"])
T, U = np.linspace(0, 2 * np.pi, 120), np.linspace(0, 1, 40)


def _strokes(low: int) -> list[np.ndarray]:
    """Two smooth ellipses and an arc (its two ends the only keypoints) on a ``low``² canvas."""
    c = low / 600
    return [np.stack([300 + 200 * np.cos(T), 330 + 140 * np.sin(T)], 1) * c,
            np.stack([200 + 70 * np.cos(T), 140 + 50 * np.sin(T)], 1) * c,
            np.stack([430 + 140 * U, 150 - 70 * np.sin(np.pi * U)], 1) * c]


def _enlarged(factor: float, width: float = 1.2, size: int = 600) -> tuple[np.ndarray, float]:
    """The strokes drawn ``width`` px wide (anti-aliased) at ``size / factor`` px, enlarged to ``size``²
    by area-weighted resampling (a pixel across a block edge blends two blocks), as 8-bit grey; and the
    exact enlargement."""
    low = round(size / factor)
    grey = synthetic.render((low, low), _strokes(low), width, darkness=0.9)
    img = Image.fromarray((grey * 255).round().astype(np.uint8)).resize((size, size), Image.BOX)
    return np.asarray(img, np.float32) / 255, size / low


@pytest.mark.parametrize("factor", [2.5, 3.5, 4.25])
def test_an_enlarged_drawing_is_found_with_its_block_period(factor):
    grey, exact = _enlarged(factor)
    period = block_period(grey, grey < 0.647, CFG)
    assert period == pytest.approx(exact, abs=0.3)


def test_drawings_at_their_own_resolution_are_not_taken_for_enlarged_ones():
    smooth = synthetic.render((300, 300), _strokes(300), 3.0)
    aliased = np.where(synthetic.render((300, 300), _strokes(300), 1.0) < 0.5, 0.4, 1.0).astype(np.float32)
    # A box of level and upright strokes repeats most of its rows and columns, but changes at a few rows
    # only; a steep aliased line repeats rows too, at steps that keep to no lattice.
    box = synthetic.render((300, 300), [np.array([[40.0, 40], [260, 40], [260, 260], [40, 260], [40, 40]]),
                                        np.array([[150.0, 40], [150, 260]])], 3.0)
    for grey in (smooth, aliased, box):
        assert block_period(grey, grey < 0.647, CFG) is None
    assert len(block_edges(box, box < 0.647)) < 10


def test_the_block_edges_lattice_statistic():
    lattice = np.round(np.arange(40) * 3.5 + 7).astype(int)           # an enlargement by 3.5: 3 and 4 apart
    period, z = edge_lattice(lattice, 2.0, 8.0)
    assert period == pytest.approx(3.5, abs=0.02) and z > 0.5 * len(lattice)
    assert edge_lattice(np.arange(0, 200, 4), 2.0, 8.0)[0] == pytest.approx(4.0, abs=0.05)   # not 2, its half
    random = np.sort(np.random.default_rng(0).choice(500, 140, replace=False))
    assert edge_lattice(random, 2.0, 8.0)[1] < CFG.min_lattice
    assert edge_lattice(np.array([3, 9]), 2.0, 8.0) == (0.0, 0.0)


def test_the_staircase_is_smoothed_at_the_block_period_and_nothing_else_is():
    grey, _ = _enlarged(3.5)
    out, period, notes = deblocked(grey, grey < 0.647, CFG)
    assert period == pytest.approx(3.5, abs=0.3) and "blocks of 3." in notes[0] and out.dtype == np.float32
    assert block_period(out, out < 0.647, CFG) is None         # the blocks are gone
    plain = synthetic.render((200, 200), _strokes(200), 3.0)
    assert deblocked(plain, plain < 0.647, CFG) == (plain, None, [])
    assert deblocked(grey, grey < 0.647, replace(CFG, enabled=False))[1] is None
    with pytest.raises(InputError):
        replace(CFG, min_period=1.0)


def _png(grey: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray((grey * 255).round().astype(np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def test_prep_smooths_an_enlarged_drawing_and_says_so():
    from stages import prep

    grey, exact = _enlarged(3.5)
    a = prep.run(PREP, image_bytes=_png(grey), image_name="duck-like.png")
    assert a.data["block_period"] == pytest.approx(exact, abs=0.3) and a.data["scale"] == 1.0
    assert any("prep.deblock" in n for n in a.notes)
    assert block_period(a["grey"], a["mask"], CFG) is None
    plain = prep.run(dict(PREP, deblock=dict(PREP["deblock"], enabled=False)), image_bytes=_png(grey))
    assert "block_period" not in plain.data and block_period(plain["grey"], plain["mask"], CFG) is not None


def test_a_thin_anti_aliased_drawing_in_a_halo_gives_no_keypoint_on_its_smooth_curves():
    """The paper's duck in miniature: 1.2-px anti-aliased strokes enlarged 3.5× (a dark core of blocks
    in a grey halo). The keypoint network put endpoints and corners on the block staircase of the
    ellipses; smoothed at the block period, the only keypoints are the arc's two ends."""
    from stages import keypoints, prep
    from stages.keypoints import PACKAGED_WEIGHTS

    if not PACKAGED_WEIGHTS.is_file():
        pytest.skip("no shipped weights")
    grey, exact = _enlarged(3.5)
    arc = _strokes(600)[2]
    ends = arc[[0, -1]]
    kcfg = yaml.safe_load((CONF / "keypoints" / "default.yaml").read_text())
    a = keypoints.run(kcfg, prep=prep.run(PREP, image_bytes=_png(grey), image_name="duck-like.png"))
    points = np.asarray(a["points"], np.float64).reshape(-1, 2)
    spurious = [p.round().tolist() for p in points if np.min(np.hypot(*(ends - p).T)) > 3 * exact]
    assert not spurious
    assert all(np.min(np.hypot(*(points - e).T)) <= 3 * exact for e in ends)
