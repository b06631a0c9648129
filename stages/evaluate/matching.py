"""One-to-one matching of point sets within a radius, and the F1 that follows from it."""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

__all__ = ["match_one_to_one", "prf1"]


def match_one_to_one(pred: np.ndarray, gt: np.ndarray, radius: float) -> np.ndarray:
    """Largest one-to-one matching of predicted to ground-truth points within ``radius``.

    Among the matchings with the most pairs, the one of least total distance (an assignment problem:
    pairs farther than ``radius`` cost more than any set of admissible pairs together, so the solver
    first maximises their number).

    Parameters
    ----------
    pred, gt : numpy.ndarray
        (n, 2) and (m, 2) points in (x, y).
    radius : float
        Inclusive matching radius in the same units.

    Returns
    -------
    numpy.ndarray
        int (k, 2): rows ``(i_pred, j_gt)`` of the matched pairs.
    """
    pred = np.asarray(pred, dtype=np.float64).reshape(-1, 2)
    gt = np.asarray(gt, dtype=np.float64).reshape(-1, 2)
    if len(pred) == 0 or len(gt) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    d = cdist(pred, gt)
    ok = d <= radius
    big = (radius + 1.0) * (min(d.shape) + 1)
    rows, cols = linear_sum_assignment(np.where(ok, d, big))
    keep = ok[rows, cols]
    return np.stack([rows[keep], cols[keep]], axis=1).astype(np.int64)


def prf1(tp: int, fp: int, fn: int) -> tuple[float, float, float]:
    """Precision, recall and F1 from counts.

    Conventions: with nothing to find and nothing found, all three are 1 (the answer is exactly
    right); otherwise an empty denominator gives 0.
    """
    if tp + fp + fn == 0:
        return 1.0, 1.0, 1.0
    p = tp / (tp + fp) if tp + fp else 0.0
    r = tp / (tp + fn) if tp + fn else 0.0
    return p, r, 2.0 * tp / (2.0 * tp + fp + fn)
