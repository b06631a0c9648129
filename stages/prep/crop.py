"""The crop: a drawing on a much larger page is worked on in its ink's box (or its parts' boxes).

On the inverted, lighting-flattened grey, the ink that stands clear of the paper gives a box (dust and
the page's dark edge left out: :mod:`~stages.prep.specks`); when it keeps a small share of the page,
the contrast stretch and the band are found on the box alone, as on the same drawing cut out by hand.
When the one box would keep too much but the parts' own boxes do not, those are laid side by side
(:mod:`~stages.prep.layout`).

Choices made on purpose
-----------------------
* **A drawing on a larger page is cropped to its ink** (``crop``; issue #14, not in the references).
  When the band's bounding box grown by ``margin_px`` keeps at most ``max_area_fraction`` of the
  image (a sketch on a scanned sheet), the inverted and lighting-flattened grey is cut to it, its
  contrast stretch and band are found again there (on a sheet the page's percentiles are the paper's:
  ink under 0.5 % of the pixels stretched the paper's texture into the band), the resampling follows,
  and every later stage works on the box: ``origin`` in the data is its corner in the drawing's
  pixels (internal ``x = scale · (x_source − origin)``), which the export maps back.  Why: the
  field, graph, topology and network cost grew with the page, not the ink, and the page's stretch
  made paper texture band (the elephant on an A4 sheet at 300 dpi: 48.7 s and 269 curves against
  10.1 s and 100, 97 alone; stages/DECISIONS.md).  A drawing that fills its image, or an elongated
  one (``max_area_fraction`` 0.25, chosen on the validation splits), is left as it is, so its
  results do not move; a cropped one is processed as the same drawing cut out by hand.  The box is
  found on the unstretched grey (ink ``min_contrast`` and the grain's deviations below the paper: the
  page's stretch made faint pencil on a sheet "blank"), and dust does not widen it (:mod:`~stages.prep.specks`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import ndimage

from stages.prep import PrepConfig
from stages.prep.band import grey_and_band, paper_statistics
from stages.prep.layout import merged_boxes, mosaic
from stages.prep.pixels import CELL_PX, blocks
from stages.prep.specks import (
    count_left_out,
    kept_clusters,
    marks_and_strokes,
    page_edge,
)


class Cropped(NamedTuple):
    """A drawing cut to its ink: ``grey`` (contrast-normalised) and ``mask`` (its band) of the box or the
    mosaic, ``band_data`` (what :func:`~stages.prep.band.grey_and_band` found them with), ``origin``
    ([x, y] of the box's corner in the drawing's pixels; None for a mosaic), ``pieces`` (a mosaic's,
    :func:`~stages.prep.layout.mosaic`; None for one box) and the console's line."""

    grey: np.ndarray
    mask: np.ndarray
    band_data: dict
    origin: list[int] | None
    pieces: list[list[int]] | None
    note: str


def cropped(lit: np.ndarray, c: PrepConfig, corner: tuple[int, int] = (0, 0)) -> Cropped | None:
    """The step as prep runs it: ``lit`` cut to its ink's box (:func:`ink_boxes`), or its parts far apart
    laid side by side (:func:`~stages.prep.layout.mosaic`), with their contrast and band found there.

    Parameters
    ----------
    lit : numpy.ndarray
        float (H, W) in [0, 1], 1 = white: the inverted, lighting-flattened grey.
    c : PrepConfig
        The ``prep`` section.
    corner : tuple of int
        (x, y) of ``lit``'s corner in the drawing's pixels (a photographed sheet's; (0, 0) otherwise):
        the origin and the pieces' source corners are moved by it.

    Returns
    -------
    Cropped or None
        None when the ink keeps too much of the page to crop (the whole page is worked on).

    Raises
    ------
    InputError
        From the band of the box (or of every piece): no ink there, or too much.
    """
    found = ink_boxes(lit, c)
    if found is None:
        return None
    h, w = lit.shape
    boxes, left_out, edge = found
    what = [f"{left_out} small mark{'s' if left_out > 1 else ''} far from it"] if left_out else []
    what += ["the page's dark edge"] if edge else []
    marks = f", {' and '.join(what)} left out" if what else ""
    sx, sy = corner
    if len(boxes) == 1:
        (y0, y1, x0, x1), = boxes
        # The box's own contrast stretch and band: on a sheet the page's percentiles are the paper's
        # (a drawing's ink under 0.5 % of the pixels stretched its paper texture into the band).
        grey, mask, band_data = grey_and_band(lit[y0:y1, x0:x1], c)
        return Cropped(grey, mask, band_data, [x0 + sx, y0 + sy], None,
                       f"the drawing fills {(y1 - y0) * (x1 - x0) / (h * w):.0%} of the page: working on its "
                       f"{x1 - x0}×{y1 - y0} box at ({x0 + sx}, {y0 + sy}){marks} "
                       "(prep.crop; the curves are mapped back)")
    grey, mask, pieces, band_data = mosaic(lit, boxes, c, corner)
    return Cropped(grey, mask, band_data, None, pieces,
                   f"{len(boxes)} parts far apart on the page, {sum(p[4] * p[5] for p in pieces) / (h * w):.0%} "
                   f"of it: working on their boxes side by side ({grey.shape[1]}×{grey.shape[0]})"
                   f"{marks} (prep.crop; the curves are mapped back)")


def ink_boxes(lit: np.ndarray, c: PrepConfig) -> tuple[list[tuple[int, int, int, int]], int, bool] | None:
    """The box a drawing on a larger page is cut to, as ``[(y0, y1, x0, x1)]``, or the boxes of its parts
    far apart, with the count of small marks left out of them and whether the page's edge was; None
    when they would keep more than ``crop.max_area_fraction`` of the image.

    The ink here is what stands clear of the paper in the inverted, lighting-flattened ``lit``, before
    any stretch: ``min_contrast`` and ``paper_grain_sigmas`` grain deviations below the paper level (the
    page's percentiles are the paper's on a sheet, and its stretched band was noise or nothing).  Its
    components smaller than ``min_component_px`` are dropped; components no wider or taller than
    ``crop.max_speck_px`` (dust), the pixels near the sides (:data:`~stages.prep.specks.PAGE_EDGE_BAND_PX`)
    of components running along a side of the image for at least ``crop.page_edge_fraction`` of it (the
    page's dark edge in a scan) and clusters of ink (pieces about ``crop.cluster_gap_px`` apart at most, on a grid
    of 16-px cells) holding less than ``crop.min_cluster_share`` of the largest one's ink do not widen
    the box.  The box bounds the rest, grown by ``crop.margin_px`` and clipped to the image; when it
    keeps too much of the page, each kept cluster's box so grown (overlapping ones merged) is returned
    instead, if together they keep little enough (parts far apart: :func:`~stages.prep.layout.mosaic`).
    Linear in the page (the merge is quadratic in the clusters, which the 16-px cells and the share bound).

    Parameters
    ----------
    lit : numpy.ndarray
        float (H, W) in [0, 1], 1 = white: the inverted, lighting-flattened grey.
    c : PrepConfig
        The ``prep`` section (``crop``, ``contrast.min_contrast``, ``paper_grain_sigmas``,
        ``min_component_px``).

    Returns
    -------
    tuple or None
        ``(boxes, left_out, edge)``: ``(y0, y1, x0, x1)`` boxes (one, or two and more far apart), the
        count of marks left out of them, whether the page's dark edge was; None when the image is not
        cropped.
    """
    crop = c.crop
    paper, grain = paper_statistics(lit)
    ink = lit < paper - max(c.contrast.min_contrast, c.paper_grain_sigmas * grain)
    labels, n = ndimage.label(ink, structure=np.ones((3, 3)))
    if n == 0:
        return None
    # The page's own edge is not ink here (a drawing touching it stays a drawing once it is taken away).
    edge = page_edge(labels, n, crop.page_edge_fraction)
    if edge is not None:
        ink &= ~edge
        labels, n = ndimage.label(ink, structure=np.ones((3, 3)))
        if n == 0:
            return None
    marks, bounds, strokes = marks_and_strokes(labels, n, c.min_component_px, crop.max_speck_px)
    if not strokes.any():
        return None
    padded, clusters, kept_cells = kept_clusters(labels, strokes, crop.cluster_gap_px, crop.min_cluster_share)
    h, w = labels.shape
    cell = CELL_PX
    rows, cols = np.flatnonzero(padded.any(axis=1)), np.flatnonzero(padded.any(axis=0))
    margin = crop.margin_px
    y0, y1 = max(0, rows[0] - margin), min(h, rows[-1] + 1 + margin)
    x0, x1 = max(0, cols[0] - margin), min(w, cols[-1] + 1 + margin)
    boxes = [(int(y0), int(y1), int(x0), int(x1))]
    if (y1 - y0) * (x1 - x0) > crop.max_area_fraction * h * w:
        # Parts of a drawing (or several drawings) far apart on the page: each kept cluster's box,
        # overlapping ones merged, when together they keep at most max_area_fraction of the page.
        pixel_cluster = blocks(np.where(kept_cells, clusters, 0), cell, cell) * padded
        boxes = merged_boxes([(max(0, sl[0].start - margin), min(h, sl[0].stop + margin),
                               max(0, sl[1].start - margin), min(w, sl[1].stop + margin))
                              for sl in ndimage.find_objects(pixel_cluster) if sl is not None])
        if len(boxes) < 2 or sum((b[1] - b[0]) * (b[3] - b[2]) for b in boxes) > crop.max_area_fraction * h * w:
            return None
    return (boxes, *count_left_out(marks, bounds, boxes, edge))

