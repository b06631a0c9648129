"""Keypoint detection metrics (reference/metrics.md §3; paper Appendix B "Validation").

Two F1 scores, because they answer different questions:

* :func:`f1_authors` — the authors' ``SketchyImage.compute_f1_score``: radius ρ = 1 % of the
  (padded) image height, strict ``<``; a ground-truth point is found if *any* prediction lies within
  ρ, a prediction is false if *no* ground-truth point lies within ρ (no one-to-one matching, so one
  prediction can satisfy several GT points). Special cases: more than 600 predictions → 0, no
  prediction → 0, no GT point → 0.5, no true positive → 0. Per class, the same restricted to one
  label.
* :func:`match_keypoints` — one-to-one matching within a radius (5 px, as the paper's Appendix B
  validation), by the Hungarian algorithm on distances; gives TP/FP/FN, F1, and the classification
  accuracy on the correctly detected (matched) points.

Points are (x, y) in pixels; types are the codes 1 endpoint, 3 junction, 5 sharp corner.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

TYPES = (1, 3, 5)


def _as_pts(p) -> np.ndarray:
    return np.asarray(p, dtype=np.float64).reshape(-1, 2)


def f1_authors(gt: np.ndarray, pred: np.ndarray, height: float, rel_radius: float = 0.01) -> float:
    """The authors' keypoint F1 (metrics.md §3).

    Parameters
    ----------
    gt, pred : numpy.ndarray
        (N, 2) and (M, 2) points.
    height : float
        Height of the network input (the authors' padded image) in pixels.
    rel_radius : float
        ρ as a fraction of ``height``.

    Returns
    -------
    float
    """
    gt, pred = _as_pts(gt), _as_pts(pred)
    rho = height * rel_radius
    if len(pred) > 600 or len(pred) == 0:
        return 0.0
    if len(gt) == 0:
        return 0.5
    d = np.hypot(gt[:, None, 0] - pred[None, :, 0], gt[:, None, 1] - pred[None, :, 1])
    tp = int((d.min(axis=1) < rho).sum())
    fn = len(gt) - tp
    fp = int((d.min(axis=0) >= rho).sum())
    if tp == 0:
        return 0.0
    p, r = tp / (tp + fp), tp / (tp + fn)
    return 2 * p * r / (p + r)


def f1_authors_per_class(gt: np.ndarray, gt_types: np.ndarray, pred: np.ndarray, pred_types: np.ndarray,
                         height: float, rel_radius: float = 0.01) -> dict[int, float]:
    """:func:`f1_authors` restricted to each label (``compute_classification_score``)."""
    gt, pred = _as_pts(gt), _as_pts(pred)
    gt_types, pred_types = np.asarray(gt_types).reshape(-1), np.asarray(pred_types).reshape(-1)
    return {t: f1_authors(gt[gt_types == t], pred[pred_types == t], height, rel_radius) for t in TYPES}


@dataclass
class MatchResult:
    """Outcome of one-to-one matching for one image (or pooled over many: add them)."""

    tp: int = 0
    fp: int = 0
    fn: int = 0
    correct_type: int = 0
    per_class: dict = field(default_factory=lambda: {t: [0, 0, 0] for t in TYPES})  # tp, fp, fn

    def __add__(self, other: "MatchResult") -> "MatchResult":
        pc = {t: [a + b for a, b in zip(self.per_class[t], other.per_class[t])] for t in TYPES}
        return MatchResult(self.tp + other.tp, self.fp + other.fp, self.fn + other.fn,
                           self.correct_type + other.correct_type, pc)

    @property
    def precision(self) -> float:
        return self.tp / (self.tp + self.fp) if self.tp + self.fp else 0.0

    @property
    def recall(self) -> float:
        return self.tp / (self.tp + self.fn) if self.tp + self.fn else 0.0

    @property
    def f1(self) -> float:
        """Detection F1 (types ignored)."""
        return 2 * self.tp / (2 * self.tp + self.fp + self.fn) if self.tp else 0.0

    @property
    def accuracy(self) -> float:
        """Classification accuracy on correctly detected (matched) points."""
        return self.correct_type / self.tp if self.tp else 0.0

    def class_f1(self, t: int) -> float:
        """F1 of one class, a match counting only when the types agree too."""
        tp, fp, fn = self.per_class[t]
        return 2 * tp / (2 * tp + fp + fn) if tp else 0.0


def match_keypoints(gt: np.ndarray, gt_types: np.ndarray, pred: np.ndarray, pred_types: np.ndarray,
                    radius: float = 5.0) -> MatchResult:
    """One-to-one matching of predictions to ground truth within ``radius`` pixels.

    The matching minimises the total distance among pairs closer than ``radius`` (Hungarian
    algorithm), ignoring types; classification accuracy counts matched pairs of equal type. Per-class
    counts match each class separately.

    Parameters
    ----------
    gt, pred : numpy.ndarray
        (N, 2), (M, 2) points in (x, y).
    gt_types, pred_types : numpy.ndarray
        (N,), (M,) codes 1, 3, 5.
    radius : float
        Largest distance of a match, inclusive.

    Returns
    -------
    MatchResult
    """
    gt, pred = _as_pts(gt), _as_pts(pred)
    gt_types, pred_types = np.asarray(gt_types).reshape(-1), np.asarray(pred_types).reshape(-1)
    rows, cols = _match(gt, pred, radius)
    res = MatchResult(tp=len(rows), fp=len(pred) - len(rows), fn=len(gt) - len(rows),
                      correct_type=int((gt_types[rows] == pred_types[cols]).sum()))
    for t in TYPES:
        g, p = gt[gt_types == t], pred[pred_types == t]
        r, _ = _match(g, p, radius)
        res.per_class[t] = [len(r), len(p) - len(r), len(g) - len(r)]
    return res


def _match(gt: np.ndarray, pred: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    if len(gt) == 0 or len(pred) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    d = np.hypot(gt[:, None, 0] - pred[None, :, 0], gt[:, None, 1] - pred[None, :, 1])
    big = 1e6
    cost = np.where(d <= radius, d, big)
    r, c = linear_sum_assignment(cost)
    ok = cost[r, c] < big
    return r[ok], c[ok]


def read_pts(text: str) -> tuple[np.ndarray, np.ndarray]:
    """Parse the authors' ``.pts`` format: ``N`` then ``row col type`` lines (y first).

    Returns
    -------
    points : numpy.ndarray
        (N, 2) in (x, y) — the authors' integer pixel indices converted to pixel centres (+0.5).
    types : numpy.ndarray
        int8 (N,).
    """
    lines = [ln.split() for ln in text.strip().splitlines()]
    rows = [ln for ln in lines[1:] if len(ln) >= 2]
    a = np.array([[float(v) for v in ln[:3]] + ([] if len(ln) >= 3 else [1.0]) for ln in rows]).reshape(-1, 3)
    return np.stack([a[:, 1] + 0.5, a[:, 0] + 0.5], axis=1), a[:, 2].astype(np.int8)
