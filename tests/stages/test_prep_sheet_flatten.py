"""stages.prep.sheet_flatten: a photographed sheet's corners, its proportions, and the sheet flattened."""

from __future__ import annotations

import numpy as np
from photos import photographed, sheet_to_photo
from PIL import Image, ImageDraw
from scipy import ndimage

from stages.prep.sheet_flatten import flattened, sheet_aspect, sheet_corners

SHEET, CENTRE, PHOTO = (300, 400), (260, 330), (520, 660)


def _truth(angle: float, tilt: float) -> np.ndarray:
    """The sheet's outer pixel corners in the photo (top-left, top-right, bottom-right, bottom-left)."""
    hom = sheet_to_photo(SHEET, angle, tilt, CENTRE, PHOTO)
    w, h = SHEET
    pts = np.c_[[-0.5, w - 0.5, w - 0.5, -0.5], [-0.5, -0.5, h - 0.5, h - 0.5], np.ones(4)] @ hom.T
    return pts[:, :2] / pts[:, 2:]


def _photo(angle: float, tilt: float) -> np.ndarray:
    img = Image.new("L", SHEET, 255)
    ImageDraw.Draw(img).rectangle([90, 120, 210, 260], outline=0, width=3)
    return np.asarray(photographed(img, angle, CENTRE, size=PHOTO, tilt=tilt)[0], np.float64) / 255.0


def _cells(grey: np.ndarray) -> np.ndarray:
    hc, wc = grey.shape[0] // 16, grey.shape[1] // 16
    means = grey[:hc * 16, :wc * 16].reshape(hc, 16, wc, 16).mean(axis=(1, 3))
    return ndimage.binary_fill_holes(means > 0.6)


def test_the_corners_are_found_to_about_a_pixel_in_order():
    for angle, tilt in ((10, 0.001), (-15, 25)):
        grey = _photo(angle, tilt)
        corners, region, corner = sheet_corners(grey, _cells(grey), 16, 0.6)
        np.testing.assert_allclose(corners, _truth(angle, tilt), atol=1.5)
        assert region.dtype == bool and region.mean() > 0.3 and corner[0] % 16 == 0 and corner[1] % 16 == 0


def test_a_region_that_is_not_four_straight_sides_has_no_corners():
    yy, xx = np.mgrid[0:500, 0:500]
    grey = np.where((yy - 250) ** 2 + (xx - 250) ** 2 < 170 ** 2, 0.9, 0.3)     # a round sheet
    assert sheet_corners(grey, _cells(grey), 16, 0.6) is None


def test_the_proportions_seen_head_on_and_with_a_focal_length():
    corners = _truth(0, 0.001)
    assert abs(sheet_aspect(corners, PHOTO[::-1]) - 0.75) < 0.002
    leaned = _truth(0, 30)        # top and bottom parallel: the focal length is not determined by them ...
    focal_35mm = 1.0 * 43.27 * max(PHOTO) / np.hypot(*PHOTO)      # ... the camera's, in 35-mm terms
    assert abs(sheet_aspect(leaned, PHOTO[::-1], focal_35mm) - 0.75) < 0.004


def test_the_sheet_is_flattened_onto_a_rectangle_of_its_proportions():
    """Of the sheet's proportions and of its area in the photo (leaned back, it is smaller there)."""
    grey = _photo(12, 20)
    corners, region, corner = sheet_corners(grey, _cells(grey), 16, 0.6)
    flat, (height, width) = flattened(grey, corners, region, corner, 8)
    xs, ys = corners.T
    area = 0.5 * abs(xs @ np.roll(ys, -1) - ys @ np.roll(xs, -1))
    assert abs(width / height - 0.75) < 0.01 and abs(width * height - area) < 0.01 * area
    assert flat.shape == (height - 16, width - 16)
    # the drawn square's strokes come back where they were drawn on the sheet (less the rim)
    ink = flat < 0.5
    rows, cols = np.flatnonzero(ink.any(axis=1)), np.flatnonzero(ink.any(axis=0))
    assert abs(rows[0] + 8 - 120 * height / 400) <= 3 and abs(cols[0] + 8 - 90 * width / 300) <= 3
    assert abs(rows[-1] + 8 - 262 * height / 400) <= 3 and abs(cols[-1] + 8 - 212 * width / 300) <= 3
