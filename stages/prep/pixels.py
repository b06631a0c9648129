"""Helpers on pixel grids that several of prep's steps share (each exists here once).

The crop (:mod:`~stages.prep.crop`, :mod:`~stages.prep.specks`) and the photographed sheet
(:mod:`~stages.prep.sheet`) look at the page in cells of :data:`CELL_PX` px, and :func:`blocks` takes
such a grid back to pixel size (as it does the lighting's shrunk copy, :mod:`~stages.prep.lighting`);
:func:`smoothed` is the Gaussian blur of the band's grey on grainy paper (:mod:`~stages.prep.band`) and
of the grey round a photographed sheet's edge (:mod:`~stages.prep.sheet_flatten`).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

#: Side of the cells the crop looks at the page in (the ink's clusters, the photographed sheet): px.
CELL_PX = 16


def blocks(cells: np.ndarray, fy: int, fx: int) -> np.ndarray:
    """Each cell's value over its ``fy`` × ``fx`` block of pixels (a cell grid back at pixel size).

    Parameters
    ----------
    cells : numpy.ndarray
        (h, w) grid, any dtype.
    fy, fx : int
        Pixels per cell down and across.

    Returns
    -------
    numpy.ndarray
        (h·fy, w·fx), the dtype of ``cells``.
    """
    return np.repeat(np.repeat(cells, fy, axis=0), fx, axis=1)


def smoothed(grey: np.ndarray, sigma: float) -> np.ndarray:
    """``grey`` blurred by a Gaussian of ``sigma`` px (itself when ``sigma`` is 0).

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) grey levels.
    sigma : float
        Gaussian σ in pixels; 0 (or less) for none.

    Returns
    -------
    numpy.ndarray
        The blurred grey (scipy's Gaussian filter keeps the dtype), or ``grey`` itself.
    """
    return ndimage.gaussian_filter(grey, sigma) if sigma > 0 else grey
