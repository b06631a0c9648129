"""A photographed sheet: found on the darker ground round it (a desk) and cut out, or flattened.

The first step after decoding, before the inversion and the lighting: a phone photo of a sheet on a
desk becomes the sheet (its box in the photo, the desk inside the box painted as paper), or, when the
sheet is seen whole with four straight sides, the sheet flattened to its rectangle
(:mod:`~stages.prep.sheet_flatten`).  An image that is no such photo is left to the later steps.

Choices made on purpose
-----------------------
* **A photographed sheet is cut out of the ground round it** (``crop.sheet_rim_share``,
  ``crop.sheet_min_contrast``; issue #14, not in the references).  First of all, before the inversion
  and the lighting, the largest bright region of 16-px cells' means (holes filled) is the sheet when
  solid darker ground (48 px and wider) runs along at least ``sheet_rim_share`` (0.4) of the image's
  border, at least ``sheet_min_contrast`` (0.2) below the paper, the sheet's edge is a step (not
  lighting's slope) and half its cells are plain paper; the later steps work on the box of the sheet
  less one cell, whatever its shape (turned, in perspective, running off the photo), the ground inside
  the box painted with the nearest paper's grey, and ``origin``/``pieces`` are moved by its corner.
  Why: divided by its own brightness, the desk became speckle and the sheet's border a frame of band
  (``photo_desk.png``: 83 curves at 1/4 resolution); a desk over half the photo made the paper level
  dark, so the photo was inverted (a turned sheet: 31 curves, most of them across the paper); a turned
  sheet's corners of desk stayed in the box.  The validation splits' drawings, and the same drawings
  inverted (chalk), have at most 0.2 of their border solid and darker (the banana tree's scan: a shaded
  corner); none of them, and none of the same drawings turned on a page lit from one corner, passes the
  four tests (stages/DECISIONS.md).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import ndimage

from stages.prep import PrepConfig
from stages.prep.pixels import CELL_PX, blocks
from stages.prep.sheet_flatten import SHEET_RIM_PX, flattened, sheet_corners

#: A photographed sheet's ground is solid: its cells survive an opening by this many cells (48 px), which
#: strokes and a scan's dark page edge do not.
SHEET_SOLID_CELLS = 3
#: ... and so is most of the sheet: at least this share of its cells are plain paper that survives the same
#: opening (on an inverted drawing's dark paper the bright "region" is strokes, hatching and grain).
SHEET_MIN_SOLID = 0.5
#: ... and its edge a step: the median grey drop from a sheet cell to its neighbour outside is at least this
#: share of the paper's contrast with the ground (turned sheets on desks: 0.43-0.67; lighting that darkens
#: one side of a page, the same drawings without a desk: 0.01-0.10).
SHEET_MIN_STEP = 0.25


class Sheet(NamedTuple):
    """A photographed sheet as prep works on it: ``grey`` (the sheet flattened, or its box in the photo),
    ``corner`` (x, y) of ``grey``'s corner in the drawing's pixels, ``shape`` (height, width) of the
    drawing (the flattened sheet, or the photo), the console's line, and the flattened sheet's four
    corners in the photo (None when it is cut out as it lies)."""

    grey: np.ndarray
    corner: tuple[int, int]
    shape: tuple[int, int]
    note: str
    corners: list[list[float]] | None


def photographed_sheet(grey: np.ndarray, c: PrepConfig, focal_35mm: float | None = None) -> Sheet | None:
    """A sheet photographed on a darker ground (a desk), flattened or cut out; None when the image is no
    such photo.

    On :data:`~stages.prep.pixels.CELL_PX` cells' mean grey, the sheet is the largest 8-connected region of
    cells within ``max(min_contrast, half the range of the cells' 5th–90th percentiles)`` of the paper (the
    90th percentile), its holes (the drawing) filled.  It is a sheet on a ground only when

    - the ground is solid (cells surviving an opening by :data:`SHEET_SOLID_CELLS`, 48 px: strokes and a
      scan's dark page edge are narrower) along at least ``crop.sheet_rim_share`` of the image's border
      (a sheet running off the photograph on two sides leaves about half of it);
    - the paper is at least ``crop.sheet_min_contrast`` brighter than the ground (the percentiles above,
      and the solid ground's own median: strokes that cut the page in two leave paper on both sides);
    - its edge is a step (:data:`SHEET_MIN_STEP`), not the slope of uneven lighting;
    - at least :data:`SHEET_MIN_SOLID` of the sheet's cells are solid plain paper (bright cells whose grey
      varies by at most ``contrast.min_contrast``; an inverted drawing's strokes, hatching and grain form
      no such region).

    A sheet seen whole (no cell of it on the image's border, once the ground's opening has cut off any
    lighter patches of desk joined to it by narrow bridges) whose edge is four straight sides
    (:func:`~stages.prep.sheet_flatten.sheet_corners`) is flattened (``crop.sheet_flatten``): its
    quadrilateral is mapped onto a rectangle of its proportions, the side nearest the photo's top on top,
    and the drawing is that rectangle (:func:`~stages.prep.sheet_flatten.flattened`).  Otherwise the sheet
    less one cell all round (its shadowed rim) is kept, whatever its shape (turned, in perspective,
    running off the photograph); the box is its bounding box, and the ground inside the box takes the grey
    of the nearest bright cell of the sheet, so that later steps see paper there.  Linear in the image.

    Parameters
    ----------
    grey : numpy.ndarray
        float (H, W) in [0, 1], 1 = white: the decoded image, as photographed.
    c : PrepConfig
        The ``prep`` section (``crop.sheet_*``, ``contrast.min_contrast``).
    focal_35mm : float or None
        The photo's EXIF focal length in 35-mm film terms (:func:`~stages.prep.decode.decode_image`).

    Returns
    -------
    Sheet or None
        The sheet to work on, where it lies and the console's line; None when the image is no such photo.
    """
    cell = CELL_PX
    h, w = grey.shape
    hc, wc = h // cell, w // cell
    if hc < 8 or wc < 8:
        return None
    # Cells' means (a median took 2.3 s on a 600-dpi A4 sheet): a stroke darkens its cells, which are
    # holes of the sheet, filled, unless they touch the image's border.
    cells = grey[:hc * cell, :wc * cell].reshape(hc, cell, wc, cell)
    means = cells.mean(axis=(1, 3), dtype=np.float64)
    paper, ground = np.percentile(means, (90, 5))
    if paper - ground < c.crop.sheet_min_contrast:
        return None
    bright = means >= paper - max(c.contrast.min_contrast, 0.5 * (paper - ground))
    labels, n = ndimage.label(bright, structure=np.ones((3, 3)))
    if n == 0:
        return None
    largest = labels == 1 + np.argmax(np.bincount(labels.ravel())[1:])
    sheet = ndimage.binary_fill_holes(largest)
    solid = np.ones((SHEET_SOLID_CELLS, SHEET_SOLID_CELLS), dtype=bool)
    ground_cells = ndimage.binary_opening(~sheet, structure=solid)
    rim = np.concatenate([ground_cells[0], ground_cells[-1], ground_cells[:, 0], ground_cells[:, -1]])
    if rim.mean() < c.crop.sheet_rim_share:
        return None
    # The ground itself is darker than the paper: strokes that cut the page in two leave paper on both
    # sides, and the 5th percentile above was theirs (a doubled wave across a grey page was "a sheet").
    ground_level = float(np.median(means[ground_cells]))
    if paper - ground_level < c.crop.sheet_min_contrast:
        return None
    # The sheet's edge is a step: across it, a cell of the sheet is much brighter than its neighbour
    # outside (uneven lighting's slope changes the grey by a hundredth from cell to cell).
    steps = []
    for m, s in ((means, sheet), (means.T, sheet.T)):
        steps += [(m[:-1] - m[1:])[s[:-1] & ~s[1:]], (m[1:] - m[:-1])[s[1:] & ~s[:-1]]]
    steps = np.concatenate(steps)
    if not steps.size or np.median(steps) < SHEET_MIN_STEP * (paper - ground):
        return None
    # Plain paper: bright cells whose grey varies less than ink stands out (hatching's cells do not).
    # A band of cell rows at a time: a float64 square of a 600-dpi page would be 280 MB.
    spread = np.empty_like(means)
    for r in range(0, hc, 64):
        band = cells[r:r + 64]
        spread[r:r + 64] = np.sqrt(np.maximum(
            np.square(band, dtype=np.float64).mean(axis=(1, 3)) - means[r:r + 64] ** 2, 0.0))
    plain = largest & (spread <= c.contrast.min_contrast)
    if ndimage.binary_opening(plain, structure=solid).sum() < SHEET_MIN_SOLID * sheet.sum():
        return None
    if c.crop.sheet_flatten and (whole := _seen_whole(sheet, solid)) is not None:
        found = sheet_corners(grey, whole, cell, 0.5 * (paper + ground_level))
        if found is not None:
            corners = found[0]
            flat, shape = flattened(grey, *found, SHEET_RIM_PX, focal_35mm)
            where = ", ".join(f"({x:.0f}, {y:.0f})" for x, y in corners)
            return Sheet(flat, (SHEET_RIM_PX, SHEET_RIM_PX), shape, corners=corners.round(2).tolist(), note=(
                f"a sheet on a darker ground (a photograph): flattened from its corners {where} to a "
                f"{shape[1]}×{shape[0]} rectangle, the curves in its pixels (prep.crop.sheet_flatten)"))
    # One cell less all round, at the image's border too: a cell there may hold a sliver of desk between
    # the sheet's edge and the border, with no ground cell beside it to show it.
    inside = ndimage.binary_erosion(sheet, structure=np.ones((3, 3)))
    rows, cols = np.flatnonzero(inside.any(axis=1)), np.flatnonzero(inside.any(axis=0))
    if len(rows) < 8 or len(cols) < 8:
        return None
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    y0, y1, x0, x1 = r0 * cell, r1 * cell, c0 * cell, c1 * cell
    box = grey[y0:y1, x0:x1]
    off = ~inside[r0:r1, c0:c1]
    line = f"a sheet on a darker ground (a photograph): working on the sheet, its {x1 - x0}×{y1 - y0} box at ({x0}, {y0})"
    if not off.any():
        return Sheet(box, (int(x0), int(y0)), (h, w), f"{line} (prep.crop; the curves are mapped back)", None)
    # The ground inside the box (a turned sheet's corners) takes the nearest bright sheet cell's grey.
    source = inside[r0:r1, c0:c1] & bright[r0:r1, c0:c1]
    if not source.any():
        return None
    nearest = ndimage.distance_transform_edt(~source, return_distances=False, return_indices=True)
    fill = means[r0:r1, c0:c1][nearest[0], nearest[1]]
    painted = np.where(blocks(off, cell, cell), blocks(fill.astype(grey.dtype), cell, cell), box)
    return Sheet(painted, (int(x0), int(y0)), (h, w), f"{line}, the ground inside the box painted as paper "
                 "(prep.crop; the curves are mapped back)", None)


def _seen_whole(sheet: np.ndarray, solid: np.ndarray) -> np.ndarray | None:
    """A photographed sheet's cells when none of them is on the image's border, else None.  Bright
    patches of a lighter desk can join the sheet by narrow bridges and run it off the photo: a sheet
    found on the border is taken again without them (the largest region the ground's opening by
    ``solid`` leaves, holes filled)."""
    def on_border(cells: np.ndarray) -> bool:
        return bool(cells[0].any() or cells[-1].any() or cells[:, 0].any() or cells[:, -1].any())

    if not on_border(sheet):
        return sheet
    labels, n = ndimage.label(ndimage.binary_opening(sheet, structure=solid), structure=np.ones((3, 3)))
    if n == 0:
        return None
    whole = ndimage.binary_fill_holes(labels == 1 + np.argmax(np.bincount(labels.ravel())[1:]))
    return None if on_border(whole) else whole
