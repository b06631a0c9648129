"""Keypoint typing from the network's class maps *and* the local valence of the stroke.

Why this exists
---------------
The paper types a keypoint by the argmax of the three class maps H2..H4. Our network was trained on a
CPU (no GPU was lent; see ``weights/MODEL_CARD.md``), and its class maps confuse the three types on
real drawings (realvec_dev class accuracy 0.78): the ends of thick strokes are called corners, acute
vees endpoints. The topology stage needs the type because it sets the valence a key vertex must get
(1 / 2 / 3), so a wrong type costs junction connectivity downstream.

What decides a type is mostly visible in the narrow band around the point: how many stroke branches
leave a circle around it (one → an end or a closed acute vee, two → a corner or a smooth bend, three
or more → a junction), how wide the arcs are, and the angle between two branches. This module measures
that *ring profile* at five radii scaled by the local stroke width and feeds it, with the class-map
values at the peak, to a small multilayer perceptron (:class:`TypeClassifier`, 44 → 32 → 3, about 1.5 k
parameters). The perceptron is trained on the same procedural drawings as the network (never on
realvec_dev), by ``python -m pipeline.train --type-classifier`` (:func:`stages.keypoints.training.train_type_classifier`),
and shipped as ``weights/type_classifier.npz``. The stage option ``keypoints.typing`` chooses between it
(``valence``, the default) and the paper's plain argmax (``argmax``); both are measured in the model card.

Choices
-------
* Radii ``r = a · w + b`` with ``(a, b)`` in ``RING_RADII`` and ``w`` the local stroke width (twice the
  largest distance-transform value within 2 px): a branch count is only meaningful at a radius beyond
  the stroke's own half width, and wide strokes need wider rings.
* Each ring is sampled at 96 points by nearest pixel from the narrow band (the prep stage's mask,
  already thresholded and repaired), so the profile does not depend on pencil tone.
* Only the stroke the point lies on counts: within the disk of each ring the band is split into
  8-connected components and the one holding the point is sampled. An end that stops short of another
  stroke (an endpoint by the labelling rule, metrics.md §4.2) then has one branch, not three. On
  realvec_dev this raised the accuracy from 0.834 to 0.862 (the perceptron trained on 700 generated
  drawings in both cases; the plain rings are kept out, adding them changed it by +0.002).
* A ring entirely inside ink (a blob) counts as 0 runs with coverage 1.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

RING_RADII: tuple[tuple[float, float], ...] = ((0.5, 2.0), (1.0, 3.0), (1.0, 6.0), (1.5, 9.0), (2.0, 12.0))
RING_SAMPLES = 96
MAX_RUNS = 4  # run counts one-hot encoded as 0, 1, 2, 3, ≥4
FEATURES = 3 + len(RING_RADII) * (MAX_RUNS + 1 + 3) + 1


def local_width(mask: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Stroke width near each point: twice the largest distance-to-paper within 2 px.

    Parameters
    ----------
    mask : numpy.ndarray
        bool (H, W) narrow band.
    points : numpy.ndarray
        (N, 2) in (x, y).

    Returns
    -------
    numpy.ndarray
        float64 (N,) widths in px, at least 1.
    """
    edt = ndimage.distance_transform_edt(mask)
    local_max = ndimage.maximum_filter(edt, size=5)
    h, w = mask.shape
    j = np.clip(np.floor(points[:, 0]).astype(int), 0, w - 1)
    i = np.clip(np.floor(points[:, 1]).astype(int), 0, h - 1)
    return np.maximum(2.0 * local_max[i, j], 1.0)


def ring_profile(ring: np.ndarray) -> tuple[int, float, float, float]:
    """Runs of ink on one circular sample vector.

    Parameters
    ----------
    ring : numpy.ndarray
        bool (S,) ink along a circle, counter-clockwise.

    Returns
    -------
    runs : int
        Number of separate ink arcs (0 when the ring is all paper or all ink).
    coverage : float
        Fraction of the ring on ink.
    widest : float
        Largest arc as a fraction of the circle.
    cos_pair : float
        Cosine of the angle between the two arc centres when there are exactly two, else 1 (a
        straight continuation has cos = −1, a hairpin cos ≈ 1).
    """
    s = len(ring)
    coverage = float(ring.mean())
    if coverage == 0.0 or coverage == 1.0:
        return 0, coverage, coverage, 1.0
    start = int(np.argmin(ring))  # rotate so the vector starts on paper: no arc wraps around
    r = np.roll(ring, -start)
    edges = np.diff(np.concatenate([[0], r.astype(np.int8), [0]]))
    begins, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    lengths = ends - begins
    cos_pair = 1.0
    if len(begins) == 2:
        centres = 2 * np.pi * ((begins + ends - 1) / 2.0 + start) / s
        cos_pair = float(np.cos(centres[0] - centres[1]))
    return len(begins), coverage, float(lengths.max()) / s, cos_pair


def class_scores_at(heatmaps: np.ndarray, points: np.ndarray) -> np.ndarray:
    """H2..H4 (endpoint, junction, corner) at the pixels holding ``points``.

    Parameters
    ----------
    heatmaps : numpy.ndarray
        (4, H, W) as stored in the keypoints artifact (clipped to [0, 1]).
    points : numpy.ndarray
        (N, 2) in (x, y), pixel centres at +0.5.

    Returns
    -------
    numpy.ndarray
        float32 (N, 3).
    """
    points = np.asarray(points, np.float64).reshape(-1, 2)
    _, h, w = heatmaps.shape
    j = np.clip(np.floor(points[:, 0]).astype(int), 0, w - 1)
    i = np.clip(np.floor(points[:, 1]).astype(int), 0, h - 1)
    return np.asarray(heatmaps[1:4, i, j], np.float32).T


_THETA = 2 * np.pi * np.arange(RING_SAMPLES) / RING_SAMPLES


def _connected_ring(mask: np.ndarray, point: np.ndarray, radius: float) -> np.ndarray:
    """Ink along a circle, counting only the stroke the point lies on.

    The band inside the disk is split into 8-connected components; only the one holding the point
    (or, when the point sits just off the ink, the one nearest to it) is sampled, so a neighbouring
    stroke that passes near an end without touching it does not look like a branch.
    """
    h, w = mask.shape
    x, y = float(point[0]), float(point[1])
    reach = int(np.ceil(radius)) + 2
    xi, yi = int(np.floor(x)), int(np.floor(y))
    i0, i1, j0, j1 = max(yi - reach, 0), min(yi + reach + 1, h), max(xi - reach, 0), min(xi + reach + 1, w)
    ring = np.zeros(RING_SAMPLES, bool)
    if i0 >= i1 or j0 >= j1:
        return ring
    yy, xx = np.mgrid[i0:i1, j0:j1]
    disk = mask[i0:i1, j0:j1] & (((xx + 0.5 - x) ** 2 + (yy + 0.5 - y) ** 2) <= (radius + 1.5) ** 2)
    labels, count = ndimage.label(disk, structure=np.ones((3, 3), bool))
    if count == 0:
        return ring
    ii, jj = np.nonzero(labels)
    nearest = np.argmin((jj + j0 + 0.5 - x) ** 2 + (ii + i0 + 0.5 - y) ** 2)
    stroke = labels == labels[ii[nearest], jj[nearest]]
    xs = np.floor(x + radius * np.cos(_THETA)).astype(int) - j0
    ys = np.floor(y + radius * np.sin(_THETA)).astype(int) - i0
    inside = (xs >= 0) & (xs < j1 - j0) & (ys >= 0) & (ys < i1 - i0)
    ring[inside] = stroke[ys[inside], xs[inside]]
    return ring


def valence_features(mask: np.ndarray, points: np.ndarray, class_scores: np.ndarray) -> np.ndarray:
    """Feature vectors of keypoints for :class:`TypeClassifier`.

    Parameters
    ----------
    mask : numpy.ndarray
        bool (H, W) narrow band of the drawing.
    points : numpy.ndarray
        (N, 2) keypoints in (x, y).
    class_scores : numpy.ndarray
        (N, 3) values of H2..H4 (endpoint, junction, corner) at the keypoints.

    Returns
    -------
    numpy.ndarray
        float32 (N, FEATURES): class scores; per ring a one-hot run count (0..≥4), coverage, widest arc,
        pair cosine; and the width / 10.
    """
    points = np.asarray(points, np.float64).reshape(-1, 2)
    n = len(points)
    out = np.zeros((n, FEATURES), np.float32)
    if n == 0:
        return out
    mask = np.asarray(mask, bool)
    width = local_width(mask, points)
    out[:, :3] = np.asarray(class_scores, np.float32).reshape(n, 3)
    for k in range(n):
        col = 3
        for a, b in RING_RADII:
            ring = _connected_ring(mask, points[k], a * width[k] + b)
            runs, coverage, widest, cos_pair = ring_profile(ring)
            out[k, col + min(runs, MAX_RUNS)] = 1.0
            out[k, col + MAX_RUNS + 1:col + MAX_RUNS + 4] = (coverage, widest, cos_pair)
            col += MAX_RUNS + 4
    out[:, -1] = width / 10.0
    return out


class TypeClassifier:
    """A 2-layer perceptron over :func:`valence_features`, evaluated with numpy.

    Parameters
    ----------
    params : dict of numpy.ndarray
        ``mean``, ``std`` (feature standardisation), ``w1`` (F, H), ``b1`` (H,), ``w2`` (H, 3), ``b2`` (3,).
    """

    def __init__(self, params: dict):
        self.params = {k: np.asarray(v, np.float64) for k, v in params.items()}
        if self.params["w1"].shape[0] != FEATURES:
            raise ValueError(f"type classifier expects {self.params['w1'].shape[0]} features, "
                             f"this code makes {FEATURES}")

    @classmethod
    def load(cls, path) -> "TypeClassifier":
        """Read the ``.npz`` written by :meth:`save`."""
        with np.load(path) as z:
            return cls({k: z[k] for k in z.files})

    def save(self, path) -> None:
        """Write the parameters as an ``.npz``."""
        np.savez(path, **{k: v.astype(np.float32) for k, v in self.params.items()})

    def logits(self, features: np.ndarray) -> np.ndarray:
        """(N, 3) logits for endpoint, junction, corner."""
        p = self.params
        z = (np.asarray(features, np.float64) - p["mean"]) / p["std"]
        hidden = np.maximum(z @ p["w1"] + p["b1"], 0.0)
        return hidden @ p["w2"] + p["b2"]

    def predict(self, features: np.ndarray) -> np.ndarray:
        """(N,) class index 0, 1, 2 (endpoint, junction, corner)."""
        if len(features) == 0:
            return np.zeros(0, np.int64)
        return np.argmax(self.logits(features), axis=1)
