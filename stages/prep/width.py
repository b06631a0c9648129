"""The strokes' width and edges, measured on the band: what decides a resampling.

:func:`stroke_width` (ink area per skeleton length) and :func:`soft_edges` (the share of grey pixels
bordering the band: anti-aliased or scanned ink against aliased ink) decide whether thin aliased strokes
are supersampled (:mod:`~stages.prep.supersampling`) or wide strokes downsampled
(:mod:`~stages.prep.downsampling`); :func:`width_words` names the width in the console's line.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def stroke_width(mask: np.ndarray) -> float:
    """Mean stroke width of a band: its area over the length of its skeleton (px, diagonal steps √2).

    Parameters
    ----------
    mask : numpy.ndarray
        bool (H, W) narrow band.

    Returns
    -------
    float
        Ink area per px of skeleton length (1.0 for a level one-pixel line, 0.71 for a diagonal one);
        0.0 without ink.
    """
    from skimage.morphology import skeletonize

    area = int(mask.sum())
    if area == 0:
        return 0.0
    rows, cols = np.nonzero(mask)
    sk = skeletonize(mask[rows.min():rows.max() + 1, cols.min():cols.max() + 1])
    # Skeleton length: 4-neighbour links count 1, diagonal steps (no 4-path beside them) √2, so that
    # a diagonal line is as wide as the same line drawn level (per pixel of skeleton it is 1/√2 wide).
    straight = int((sk[:, :-1] & sk[:, 1:]).sum() + (sk[:-1, :] & sk[1:, :]).sum())
    diagonal = int((sk[:-1, :-1] & sk[1:, 1:] & ~sk[:-1, 1:] & ~sk[1:, :-1]).sum()
                   + (sk[:-1, 1:] & sk[1:, :-1] & ~sk[:-1, :-1] & ~sk[1:, 1:]).sum())
    return area / max(1.0, straight + np.sqrt(2.0) * diagonal)


def soft_edges(grey: np.ndarray, mask: np.ndarray) -> float:
    """Share of the pixels bordering the band (8-neighbours outside it) whose grey is between 0.1 and 0.9.

    Anti-aliased and scanned strokes fade into the paper over a pixel or two (0.05–0.96 on the
    validation split and the 13 drawings); aliased ink (each pixel ink or paper) gives 0.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) contrast-normalised grey, 1 = paper.
    mask : numpy.ndarray
        bool (H, W) narrow band.

    Returns
    -------
    float
        In [0, 1]; 0.0 without ink.
    """
    ring = ndimage.binary_dilation(mask, structure=np.ones((3, 3), bool)) & ~mask
    g = np.asarray(grey)[ring]
    return float(((g > 0.1) & (g < 0.9)).mean()) if len(g) else 0.0


def width_words(width: float, mask: np.ndarray) -> str:
    """How the console names the ink's width: a filled area's skeleton is a few pixels long, so its
    area per skeleton length (thousands of px on a filled square) is no width to show a user.

    Only a width well beyond the ink's extent (twice) means a fill: a 1-px line's estimate (1.2 px)
    exceeds its 1-px extent across, and it is a stroke.

    Parameters
    ----------
    width : float
        :func:`stroke_width` of ``mask``.
    mask : numpy.ndarray
        bool (H, W) narrow band.

    Returns
    -------
    str
        "strokes about 3.2 px wide", or "ink filled in areas up to 40 px across, not drawn in strokes".
    """
    across = min(int(np.any(mask, axis=1).sum()), int(np.any(mask, axis=0).sum()))
    if width > 2 * across:
        return f"ink filled in areas up to {across} px across, not drawn in strokes"
    return f"strokes about {width:.1f} px wide"
