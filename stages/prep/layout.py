"""Layout: a drawing's parts far apart on the page, cut out and laid side by side on one picture.

When the crop's one box round the ink would keep too much of the page (two sketches in opposite corners
of a sheet) but the parts' own boxes do not (:func:`~stages.prep.crop.ink_boxes`), each box is cut out,
its contrast and band found on it alone, and the boxes are laid in rows (:func:`mosaic`); ``pieces`` in
the data maps each one back (:func:`~stages.prep.to_source`).

Choices made on purpose
-----------------------
* **Parts far apart are laid side by side** (``crop``; issue #14, not in the references).  When the one
  box round the kept clusters keeps more than ``max_area_fraction`` of the page (two sketches in
  opposite corners of a sheet) but each cluster's box grown by ``margin_px`` (overlapping ones merged)
  keeps at most that share together, those boxes are cut out, their contrast and band found on each
  (as if cut out by hand), and laid in rows, ``margin_px`` of paper between them, on one picture (a
  mosaic);
  ``pieces`` in the data holds each one's corner in the mosaic and in the drawing, which
  :func:`~stages.prep.to_source` maps each point back by.  Why: every later stage grew with the
  page, not the ink (the elephant and the kitten on an A4 sheet: 33 s and 1.7 GB, against 14 s for
  the two alone); the field, the graph and the topology see the same disjoint strokes, and the
  keypoint network runs on each piece alone (:func:`~stages.prep.piece_windows`).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from stages.errors import InputError
from stages.prep import PrepConfig
from stages.prep.band import grey_and_band


def merged_boxes(boxes: list[tuple[int, int, int, int]]) -> list[tuple[int, int, int, int]]:
    """``(y0, y1, x0, x1)`` boxes with each group of overlapping ones replaced by its bounding box, again
    until none overlap (a merged box can reach a third one), in the order of their top-left corners.

    Parameters
    ----------
    boxes : list of tuple of int
        ``(y0, y1, x0, x1)``, end-exclusive.

    Returns
    -------
    list of tuple of int
        The merged boxes, none overlapping, sorted.
    """
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    b = np.asarray(boxes, np.int64).reshape(-1, 4)
    while len(b) > 1:
        overlap = ((b[:, None, 0] < b[None, :, 1]) & (b[None, :, 0] < b[:, None, 1])
                   & (b[:, None, 2] < b[None, :, 3]) & (b[None, :, 2] < b[:, None, 3]))
        n, group = connected_components(csr_matrix(overlap), directed=False)
        if n == len(b):
            break
        b = np.stack([ndimage.minimum(b[:, 0], group, np.arange(n)), ndimage.maximum(b[:, 1], group, np.arange(n)),
                      ndimage.minimum(b[:, 2], group, np.arange(n)), ndimage.maximum(b[:, 3], group, np.arange(n))],
                     axis=1).astype(np.int64)
    return sorted(tuple(int(v) for v in row) for row in b)


def mosaic(lit: np.ndarray, boxes: list[tuple[int, int, int, int]], c: PrepConfig, offset: tuple[int, int]
           ) -> tuple[np.ndarray, np.ndarray, list[list[int]], dict]:
    """The ``boxes`` of ``lit``, each contrast-normalised and banded on its own (as if cut out by hand),
    laid side by side in rows (tallest first) with ``crop.margin_px`` of white paper between them.

    Corners sit on multiples of 12, so every downsampling factor cuts each piece into the blocks it
    would cut it into alone.  Returns the grey, the band, each piece's ``[mosaic x, mosaic y, source
    x, source y, width, height]`` (the source corner moved by ``offset``, (x, y): the corner of a
    photographed sheet ``lit`` was cut from) and the band data: the largest piece's, with every piece's in
    ``pieces_band``.  A piece with no band of its own (nothing but paper once it is stretched on its
    own) is left out; when every one is, its error is raised.

    Parameters
    ----------
    lit : numpy.ndarray
        float (H, W) in [0, 1], 1 = white: the inverted, lighting-flattened grey.
    boxes : list of tuple of int
        ``(y0, y1, x0, x1)`` of each part (:func:`~stages.prep.crop.ink_boxes`), not overlapping.
    c : PrepConfig
        The ``prep`` section (the band's keys; ``crop.margin_px``, the paper between pieces).
    offset : tuple of int
        (x, y) of ``lit``'s corner in the drawing's pixels.

    Returns
    -------
    grey : numpy.ndarray
        float32 the mosaic, paper (1) between the pieces.
    mask : numpy.ndarray
        bool, the same shape: each piece's band.
    pieces : list of list of int
        ``[mosaic x, mosaic y, source x, source y, width, height]`` of each piece.
    band_data : dict
        The largest piece's band data, the mosaic's ``ink_fraction`` and every piece's in ``pieces_band``.

    Raises
    ------
    InputError
        The first piece's error when no piece has a band of its own.
    """
    def up(v: int) -> int:
        return -(-v // 12) * 12

    found, errors = [], []
    for y0, y1, x0, x1 in boxes:
        try:
            found.append(((y0, y1, x0, x1), *grey_and_band(lit[y0:y1, x0:x1], c)))
        except InputError as error:
            errors.append(error)
    if not found:
        raise errors[0]
    gap = c.crop.margin_px
    sizes = [g.shape for _, g, _, _ in found]
    row_limit = max(max(wd for _, wd in sizes), int(np.sqrt(sum((hh + gap) * (wd + gap) for hh, wd in sizes))))
    places: dict[int, tuple[int, int]] = {}
    x = y = row_height = 0
    for i in sorted(range(len(found)), key=lambda i: (-sizes[i][0], i)):
        hh, wd = sizes[i]
        if x > 0 and x + wd > row_limit:
            x, y, row_height = 0, up(y + row_height + gap), 0
        places[i] = (y, x)
        x, row_height = up(x + wd + gap), max(row_height, hh)
    shape = (max(places[i][0] + sizes[i][0] for i in places), max(places[i][1] + sizes[i][1] for i in places))
    grey, mask = np.ones(shape, np.float32), np.zeros(shape, bool)
    pieces = []
    for i, ((y0, y1, x0, x1), g, m, _) in enumerate(found):
        my, mx = places[i]
        grey[my:my + y1 - y0, mx:mx + x1 - x0], mask[my:my + y1 - y0, mx:mx + x1 - x0] = g, m
        pieces.append([mx, my, x0 + offset[0], y0 + offset[1], x1 - x0, y1 - y0])
    bands = [bd for _, _, _, bd in found]
    largest = max(range(len(found)), key=lambda i: found[i][2].sum())
    return grey, mask, pieces, dict(bands[largest], ink_fraction=float(mask.mean()), pieces_band=bands)
