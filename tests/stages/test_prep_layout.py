"""stages.prep.layout: parts far apart on a page are cut out and laid side by side."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from stages.config import from_section
from stages.errors import InputError
from stages.prep import PrepConfig
from stages.prep.band import grey_and_band
from stages.prep.layout import merged_boxes, mosaic

CFG = yaml.safe_load((Path(__file__).resolve().parents[2] / "conf" / "prep" / "default.yaml").read_text())
C = from_section(PrepConfig, CFG, "prep")


def test_overlapping_boxes_are_merged_until_none_overlap():
    # a overlaps b; their union reaches c; d is apart
    a, b, c, d = (0, 10, 0, 10), (5, 15, 5, 15), (12, 20, 14, 30), (50, 60, 50, 60)
    assert merged_boxes([d, b, a, c]) == [(0, 20, 0, 30), d]
    assert merged_boxes([d, (0, 10, 0, 10)]) == [(0, 10, 0, 10), d]          # touching is not overlapping
    assert merged_boxes([(0, 10, 0, 10), (10, 20, 0, 10)]) == [(0, 10, 0, 10), (10, 20, 0, 10)]


def _two_squares() -> tuple[np.ndarray, list[tuple[int, int, int, int]]]:
    grey = np.ones((600, 700))
    for y, x in ((40, 50), (450, 560)):
        grey[y:y + 60, x:x + 3] = grey[y:y + 60, x + 57:x + 60] = 0.0
        grey[y:y + 3, x:x + 60] = grey[y + 57:y + 60, x:x + 60] = 0.0
    return grey, [(8, 132, 18, 142), (418, 542, 528, 652)]


def test_each_piece_is_its_box_cut_out_by_hand_on_multiples_of_twelve():
    grey, boxes = _two_squares()
    out, mask, pieces, data = mosaic(grey, boxes, C, (3, 4))
    assert len(pieces) == 2 and all(mx % 12 == 0 and my % 12 == 0 for mx, my, *_ in pieces)
    for (mx, my, sx, sy, w, h), (y0, y1, x0, x1) in zip(pieces, boxes):
        assert (sx, sy, w, h) == (x0 + 3, y0 + 4, x1 - x0, y1 - y0)      # source corner moved by the offset
        alone = grey_and_band(grey[y0:y1, x0:x1], C)
        np.testing.assert_array_equal(out[my:my + h, mx:mx + w], alone[0])
        np.testing.assert_array_equal(mask[my:my + h, mx:mx + w], alone[1])
    assert mask.sum() == sum(grey_and_band(grey[y0:y1, x0:x1], C)[1].sum() for y0, y1, x0, x1 in boxes)
    assert out.dtype == np.float32 and (out[~mask] > 0.5).all()           # paper between the pieces
    assert len(data["pieces_band"]) == 2 and data["ink_fraction"] == mask.mean()


def test_a_piece_with_no_ink_of_its_own_is_left_out_and_all_blank_is_an_error():
    grey, boxes = _two_squares()
    pieces = mosaic(grey, boxes + [(300, 340, 300, 340)], C, (0, 0))[2]
    assert len(pieces) == 2
    with pytest.raises(InputError, match="blank image"):
        mosaic(grey, [(300, 340, 300, 340), (200, 240, 300, 340)], C, (0, 0))
