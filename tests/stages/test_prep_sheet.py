"""stages.prep.sheet: a sheet photographed on a darker desk is cut out of it, or flattened when seen whole."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml
from photos import photographed
from PIL import Image, ImageDraw

from stages.config import from_section
from stages.prep import PrepConfig
from stages.prep.sheet import photographed_sheet

CFG = yaml.safe_load((Path(__file__).resolve().parents[2] / "conf" / "prep" / "default.yaml").read_text())
C = from_section(PrepConfig, CFG, "prep")
NO_FLATTEN = replace(C, crop=replace(C.crop, sheet_flatten=False))


def _sheet() -> Image.Image:
    """A 300×400 white sheet with a 3-px square drawn on it."""
    img = Image.new("L", (300, 400), 255)
    ImageDraw.Draw(img).rectangle([90, 120, 210, 260], outline=0, width=3)
    return img


def _photo(angle: float = 0.0, centre=(260, 330), size=(520, 660)) -> np.ndarray:
    return np.asarray(photographed(_sheet(), angle, centre, size=size)[0], np.float64) / 255.0


def test_a_sheet_seen_whole_is_flattened_to_its_rectangle():
    found = photographed_sheet(_photo(8.0), C)
    assert found is not None and "flattened" in found.note and "prep.crop.sheet_flatten" in found.note
    assert abs(found.shape[0] - 400) <= 3 and abs(found.shape[1] - 300) <= 3
    assert found.grey.shape == (found.shape[0] - 16, found.shape[1] - 16)     # less its 8-px rim
    assert found.corner == (8, 8) and len(found.corners) == 4
    assert found.grey.min() < 0.5 < np.median(found.grey)                     # the drawing on paper


def test_without_flattening_the_sheet_is_cut_out_and_the_desk_in_its_box_painted():
    grey = _photo(8.0)
    found = photographed_sheet(grey, NO_FLATTEN)
    assert found.corners is None and found.shape == grey.shape and "painted as paper" in found.note
    x0, y0 = found.corner
    h, w = found.grey.shape
    assert x0 % 16 == 0 and y0 % 16 == 0 and 0 < x0 < 130 and 0 < y0 < 150 and w < 330 and h < 430
    # its corners, desk in the photo, are paper-bright now
    assert found.grey[0, 0] > 0.6 and grey[y0, x0] < 0.6


def test_a_sheet_upright_in_its_box_needs_no_paint():
    found = photographed_sheet(_photo(0.0), NO_FLATTEN)
    assert "painted" not in found.note and found.note.endswith("(prep.crop; the curves are mapped back)")
    x0, y0 = found.corner
    np.testing.assert_array_equal(found.grey, _photo(0.0)[y0:y0 + found.grey.shape[0], x0:x0 + found.grey.shape[1]])


def test_a_drawing_on_a_plain_page_is_no_photographed_sheet():
    page = np.ones((500, 600))
    page[100:103, 100:400] = 0.0
    assert photographed_sheet(page, C) is None
    shaded = page * np.linspace(1.0, 0.6, 600)[None, :]                      # lighting's slope, no step
    assert photographed_sheet(shaded, C) is None
    assert photographed_sheet(np.ones((100, 100)), C) is None                # too small to tell


def test_strokes_that_cut_the_page_in_two_are_no_desk():
    """A found bug: a doubled wave across a grey page split its paper into two regions; the smaller one
    was taken for the desk (the 5th percentile of the cells, the strokes', was the 'ground'), and the
    strokes were painted over as paper: "blank image"."""
    img = Image.new("L", (512, 512), 222)
    xs = np.linspace(0, 512, 400)
    for dy in (0, 8):
        pts = [(float(x), float(250 + 60 * np.sin(x / 40.0) + dy)) for x in xs]
        ImageDraw.Draw(img).line(pts, fill=20, width=7)
    assert photographed_sheet(np.asarray(img, np.float64) / 255.0, C) is None
