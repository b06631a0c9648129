"""Specks: what does not widen the crop's box (dust on a scanned sheet, a scan's dark page edge).

Helpers of :func:`~stages.prep.crop.ink_boxes`, on the labelled ink of the page: the page's own dark
edge (:func:`page_edge`), marks too small to count and dust (:func:`marks_and_strokes`), clusters of ink
far from the drawing with little ink (:func:`kept_clusters`), and what was so left out, for the console
(:func:`count_left_out`).

Choices made on purpose
-----------------------
* **Dust does not widen the crop's box** (``crop``; issue #14, not in the references): marks no larger
  than ``max_speck_px``, clusters with under ``min_cluster_share`` of the largest one's ink and the
  page's dark edge (ink along ``page_edge_fraction`` of a side) are left out, with a note (six specks
  kept the elephant's A4 sheet whole: 50 s and 280 curves; 0.02 is the geometric middle between the
  validation splits' smallest far stroke, 0.076, and grain, 0.005).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from stages.prep.pixels import CELL_PX, blocks

#: A page's dark edge is the ink, within this many pixels of the sides, of the components that run along
#: a side (an 18-px strip at 300 dpi, 36 at 600); the rest of such a component is a drawing touching it.
PAGE_EDGE_BAND_PX = 64


def page_edge(labels: np.ndarray, n: int, fraction: float) -> np.ndarray | None:
    """The page's dark edge: the pixels within :data:`PAGE_EDGE_BAND_PX` of the sides of the ink
    components that run along a side of the image for at least ``fraction`` of it.

    The page's own edge (a scanner's lid, the desk beyond the sheet, a dark scanned border) runs along
    a side of the image; a drawing's strokes leave it at a few points.  Its pixels near the sides are
    not ink for the crop: a drawing whose strokes touch a dark band along the top of the scan (the banana
    tree) is one component with it, and stays a drawing once the band is taken away.

    Parameters
    ----------
    labels : numpy.ndarray
        int (H, W) 8-connected components of the ink, 0 = paper.
    n : int
        Their count.
    fraction : float
        ``crop.page_edge_fraction``.

    Returns
    -------
    numpy.ndarray or None
        bool (H, W), or None when no component runs along a side.
    """
    h, w = labels.shape
    along = np.zeros(n + 1)
    for line, length in ((labels[0], w), (labels[-1], w), (labels[:, 0], h), (labels[:, -1], h)):
        along = np.maximum(along, np.bincount(line, minlength=n + 1) / length)
    running = along >= fraction
    running[0] = False
    if not running.any():
        return None
    edge = np.zeros(labels.shape, dtype=bool)
    b = min(PAGE_EDGE_BAND_PX, h // 2, w // 2)
    for rows, cols in ((slice(0, b), slice(0, w)), (slice(h - b, h), slice(0, w)),
                       (slice(b, h - b), slice(0, b)), (slice(b, h - b), slice(w - b, w))):
        edge[rows, cols] = running[labels[rows, cols]]
    return edge


def marks_and_strokes(labels: np.ndarray, n: int, min_component_px: int, max_speck_px: int
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which ink components are marks (not too small for the band) and which of those are strokes (not
    dust), with each one's bounding box.

    Parameters
    ----------
    labels : numpy.ndarray
        int (H, W) 8-connected components of the ink, 0 = paper, numbered 1 to ``n``.
    n : int
        Their count (at least 1).
    min_component_px : int
        ``prep.min_component_px``: smaller components are no marks (the band drops them).
    max_speck_px : int
        ``crop.max_speck_px``: marks no wider or taller than this are dust.

    Returns
    -------
    marks : numpy.ndarray
        bool (n,).
    bounds : numpy.ndarray
        int (n, 4): each component's ``(y0, y1, x0, x1)``.
    strokes : numpy.ndarray
        bool (n,): the marks wider or taller than ``max_speck_px``.
    """
    marks = np.bincount(labels.ravel(), minlength=n + 1)[1:] >= min_component_px
    # Each component's bounding box, (y0, y1, x0, x1): its span, and later whether it reaches past the box.
    bounds = np.array([(sl[0].start, sl[0].stop, sl[1].start, sl[1].stop) for sl in ndimage.find_objects(labels)])
    spans = np.maximum(bounds[:, 1] - bounds[:, 0], bounds[:, 3] - bounds[:, 2])
    return marks, bounds, marks & (spans > max_speck_px)


def kept_clusters(labels: np.ndarray, strokes: np.ndarray, gap_px: int, min_share: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The strokes' pixels less the clusters of ink far from the drawing that hold little of it.

    Strokes about ``gap_px`` apart at most are one cluster, on a grid of :data:`~stages.prep.pixels.CELL_PX`
    cells; a cluster with less than ``min_share`` of the largest one's ink is left out.

    Parameters
    ----------
    labels : numpy.ndarray
        int (H, W) 8-connected components of the ink, 0 = paper.
    strokes : numpy.ndarray
        bool (n,): which components count (:func:`marks_and_strokes`).
    gap_px : int
        ``crop.cluster_gap_px``.
    min_share : float
        ``crop.min_cluster_share``.

    Returns
    -------
    padded : numpy.ndarray
        bool (H', W'), the image padded to whole cells: the kept strokes' pixels.
    clusters : numpy.ndarray
        int (H' / cell, W' / cell): each cell's cluster, 0 = none.
    kept_cells : numpy.ndarray
        bool, the same shape: the cells of the kept clusters.
    """
    h, w = labels.shape
    cell = CELL_PX
    hc, wc = -(-h // cell), -(-w // cell)
    padded = np.zeros((hc * cell, wc * cell), dtype=bool)
    padded[:h, :w] = np.concatenate([[False], strokes])[labels]
    counts = padded.reshape(hc, cell, wc, cell).sum(axis=(1, 3))
    # Dilating every occupied cell by `reach` joins cells up to 2·reach + 1 cells apart: about the gap.
    reach = max(0, int(round(gap_px / (2 * cell))))
    near = ndimage.maximum_filter(counts > 0, size=2 * reach + 1) if reach else counts > 0
    clusters, m = ndimage.label(near, structure=np.ones((3, 3)))
    cluster_ink = ndimage.sum_labels(counts, clusters, index=np.arange(1, m + 1))
    keep = cluster_ink >= min_share * cluster_ink.max()
    kept_cells = np.concatenate([[False], keep])[clusters]
    if not keep.all():
        padded &= blocks(kept_cells, cell, cell)
    return padded, clusters, kept_cells


def count_left_out(marks: np.ndarray, bounds: np.ndarray, boxes: list[tuple[int, int, int, int]],
                   edge: np.ndarray | None) -> tuple[int, bool]:
    """What the crop's boxes leave out: the specks and small clusters whose bounding box reaches past
    every box, and the page's edge where it lies outside them.

    Parameters
    ----------
    marks : numpy.ndarray
        bool (n,) (:func:`marks_and_strokes`).
    bounds : numpy.ndarray
        int (n, 4): each component's ``(y0, y1, x0, x1)``.
    boxes : list of tuple of int
        The crop's ``(y0, y1, x0, x1)`` boxes.
    edge : numpy.ndarray or None
        The page's dark edge (:func:`page_edge`), or None.

    Returns
    -------
    count : int
        Marks outside every box.
    edge_left_out : bool
        Whether some of the page's edge lies outside every box.
    """
    inside = np.zeros(len(marks), dtype=bool)
    outside = None if edge is None else edge.copy()
    for by0, by1, bx0, bx1 in boxes:
        inside |= ((bounds[:, 0] >= by0) & (bounds[:, 1] <= by1) & (bounds[:, 2] >= bx0) & (bounds[:, 3] <= bx1))
        if outside is not None:
            outside[by0:by1, bx0:bx1] = False
    return int(np.count_nonzero(marks & ~inside)), outside is not None and bool(outside.any())
