"""Contrast normalisation: the grey stretched so that the paper is white and the darkest ink black.

Faint pencil and ink then meet the band's one threshold (:mod:`~stages.prep.band`); a uniform page
(no ink at all) is a clear "blank image" error here.  Run on the whole page, or again on the crop's box
and on each piece of a mosaic (:mod:`~stages.prep.crop`, :mod:`~stages.prep.layout`), where the page's
percentiles would be the paper's.

Choices made on purpose
-----------------------
* **Contrast normalisation** is done here, not by hand as in the paper: the grey levels at the
  ``low_percentile`` and ``high_percentile`` are stretched to 0 and 1. With mostly-white drawings the
  high percentile is paper, the low one the darkest ink, so faint pencil reaches the same mask
  threshold as ink. Stretching is skipped when the black level is already below ``max_black`` and
  only applied upward when the ink is faint, so clean drawings are left as they are.
"""

from __future__ import annotations

import numpy as np

from stages.errors import InputError
from stages.prep import ContrastConfig

#: Percentile of the ink (the pixels ``min_contrast`` below the paper) stretched to black when the page's
#: percentiles are both paper (:func:`normalise_contrast`).
SPARSE_INK_BLACK_PERCENTILE = 25.0


def stretched(lit: np.ndarray, cfg: ContrastConfig) -> np.ndarray:
    """The step as prep runs it: :func:`normalise_contrast` when ``prep.contrast`` is enabled, else the
    grey as it is (float32), refused when blank all the same.

    ``lit`` is the inverted, lighting-flattened grey (or a box of it), float (H, W) in [0, 1], 1 =
    white; ``cfg`` the ``prep.contrast`` section. Returns and raises as :func:`normalise_contrast`.
    """
    if cfg.enabled:
        return normalise_contrast(lit, cfg.low_percentile, cfg.high_percentile, cfg.min_contrast)
    if lit.max() - lit.min() < cfg.min_contrast:
        raise InputError("blank image: no ink found (uniform grey levels)")
    return lit.astype(np.float32)


def normalise_contrast(grey: np.ndarray, low_percentile: float, high_percentile: float,
                       min_contrast: float) -> np.ndarray:
    """Stretch grey levels so the paper is white and the darkest ink is black.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) in [0, 1], 1 = white.
    low_percentile, high_percentile : float
        Percentiles taken as the ink (black) and paper (white) levels.
    min_contrast : float
        If paper and ink levels differ by less than this the image is blank.

    Returns
    -------
    numpy.ndarray
        float32 (H, W) in [0, 1].

    Raises
    ------
    InputError
        When the image is uniform (no ink at all).
    """
    lo, hi = np.percentile(grey, [low_percentile, high_percentile])
    # Blank means uniform grey levels, judged on the extremes only: the percentiles of a sparse drawing
    # (one 2-px line on a 600×600 page is 0.3 % ink, below low_percentile) are both paper.
    if grey.max() - grey.min() < min_contrast:
        raise InputError("blank image: no ink found (uniform grey levels)")
    if hi - lo < min_contrast:
        # Percentiles miss very sparse ink (a few strokes on a big page): the ink is then what stands
        # min_contrast below the paper, and black is its lower quartile, where the page's percentile
        # falls on the validation splits' median drawing (1.9 % ink). Not the darkest pixel: on a scanned
        # sheet that is a noise pixel, and faint pencil stayed lighter than the threshold ("blank image").
        darker = grey[grey < hi - min_contrast]
        lo = float(np.percentile(darker, SPARSE_INK_BLACK_PERCENTILE)) if darker.size else float(grey.min())
        if hi - lo < min_contrast:
            hi = float(grey.max())
    return np.clip((grey - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)
