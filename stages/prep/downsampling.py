"""Downsampling: wide strokes (a high-resolution scan) are worked on at 1/k of the resolution.

The field, the tracing and the cross-sections cost grows with the lanes across a stroke times its
length; shrunk by block means, the strokes reach the later stages at the widths the keypoint network was
trained on, and the export maps the curves back (``scale`` = 1/k in the data).

Choices made on purpose
-----------------------
* **Wide strokes are downsampled** (``downsample``; issue #14, not in the references).  When the mean
  stroke width is at least ``above_width`` px (a high-resolution scan), the grey is shrunk by the
  integer ``k = min(max_factor, floor(width / target_width))`` (block means; internal ``x = x_source /
  k``) and banded again, so strokes reach the later stages about ``target_width``–``2·target_width`` px
  wide, the widths the keypoint network was trained on (1–12 px).  Why: the field, the tracing
  and the cross-sections cost grows with the lanes across a stroke times its length (a 4× scan took
  157 s and 3.5 GB), not with what the drawing shows; the curves come back in the drawing's pixels
  (``scale`` = 1/k).  Chosen on validation cases re-rendered 3× larger (stages/DECISIONS.md).
"""

from __future__ import annotations

import numpy as np

from stages.prep import DownsampleConfig
from stages.prep.width import width_words


def downsampled(grey: np.ndarray, mask: np.ndarray, width: float, cfg: DownsampleConfig
                ) -> tuple[np.ndarray, int, list[str]]:
    """The step as prep runs it (when the grey was not supersampled): ``grey`` at 1/``k`` of the
    resolution (:func:`downsample_factor`) when its strokes are wide, with the console's line.

    Its arguments are those of :func:`~stages.prep.supersampling.supersampled`, with the
    ``prep.downsample`` section as ``cfg``; it returns the downsampled grey (or ``grey`` itself), ``k``
    (source pixels per internal pixel, 1 = none) and the notes of what it did.
    """
    if not cfg.enabled:
        return grey, 1, []
    k = downsample_factor(width, cfg)
    if k == 1:
        return grey, 1, []
    note = f"{width_words(width, mask)}: working at 1/{k} resolution (prep.downsample; the curves are mapped back)"
    return downsample(grey, k), k, [note]


def downsample_factor(width: float, cfg) -> int:
    """The integer shrink factor ``k`` for strokes ``width`` px wide (1 = none).

    Parameters
    ----------
    width : float
        Mean stroke width (:func:`~stages.prep.width.stroke_width`).
    cfg : DownsampleConfig

    Returns
    -------
    int
        ``min(max_factor, floor(width / target_width))`` when ``width ≥ above_width``, else 1.
    """
    if not cfg.enabled or width < cfg.above_width:
        return 1
    return int(max(1, min(cfg.max_factor, np.floor(width / cfg.target_width + 1e-9))))


def downsample(grey: np.ndarray, factor: int) -> np.ndarray:
    """Grey image at 1/``factor`` of the resolution: the mean of each ``factor``² block.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) in [0, 1], 1 = paper.
    factor : int
        Internal pixel ``[i, j]`` covers source ``[factor·i, factor·(i + 1))`` (so internal
        ``x = x_source / factor``); the last row and column of blocks are padded with paper.

    Returns
    -------
    numpy.ndarray
        float32 (ceil(H / factor), ceil(W / factor)).
    """
    g = np.asarray(grey, np.float32)
    h, w = g.shape
    hh, ww = -(-h // factor), -(-w // factor)
    padded = np.ones((hh * factor, ww * factor), np.float32)
    padded[:h, :w] = g
    return padded.reshape(hh, factor, ww, factor).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)
