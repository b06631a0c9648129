"""stages.prep.crop: a drawing on a much larger page is worked on in its ink's box."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from stages.config import from_section
from stages.prep import PrepConfig
from stages.prep.band import grey_and_band
from stages.prep.crop import cropped, ink_boxes

CFG = yaml.safe_load((Path(__file__).resolve().parents[2] / "conf" / "prep" / "default.yaml").read_text())
C = from_section(PrepConfig, CFG, "prep")
M = C.crop.margin_px


def _page(h: int = 400, w: int = 500) -> np.ndarray:
    """White paper with a 3-px square outline, rows 100–159, columns 200–279."""
    grey = np.ones((h, w))
    grey[100:160, 200:203] = grey[100:160, 277:280] = grey[100:103, 200:280] = grey[157:160, 200:280] = 0.0
    return grey


def test_the_box_is_the_inks_grown_by_the_margin():
    assert ink_boxes(_page(), C) == ([(100 - M, 160 + M, 200 - M, 280 + M)], 0, False)


def test_a_drawing_that_fills_its_page_is_not_cropped():
    page = _page()[60:200, 160:320]
    assert ink_boxes(page, C) is None and cropped(page, C) is None


def test_the_crop_is_the_drawing_cut_out_by_hand():
    page = _page()
    out = cropped(page, C, corner=(7, 5))
    y0, y1, x0, x1 = 100 - M, 160 + M, 200 - M, 280 + M
    by_hand = grey_and_band(page[y0:y1, x0:x1], C)
    np.testing.assert_array_equal(out.grey, by_hand[0])
    np.testing.assert_array_equal(out.mask, by_hand[1])
    assert out.band_data == by_hand[2] and out.pieces is None
    assert out.origin == [x0 + 7, y0 + 5]         # moved by the corner of a photographed sheet
    assert out.note.startswith(f"the drawing fills {(y1 - y0) * (x1 - x0) / (400 * 500):.0%} of the page: "
                               f"working on its {x1 - x0}×{y1 - y0} box at ({x0 + 7}, {y0 + 5}) (prep.crop")


def test_dust_far_away_is_left_out_of_the_box_and_counted():
    page = _page()
    page[380:383, 20:23] = 0.0                    # a 3-px speck of dust in a far corner
    boxes, left_out, edge = ink_boxes(page, C)
    assert boxes == [(100 - M, 160 + M, 200 - M, 280 + M)] and left_out == 1 and not edge
    assert ", 1 small mark far from it left out" in cropped(page, C).note
