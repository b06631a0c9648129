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


def ring_profiles(rings: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Runs of ink on circular sample vectors, one per row.

    Parameters
    ----------
    rings : numpy.ndarray
        bool (N, S): ink along N circles, each counter-clockwise.

    Returns
    -------
    runs : numpy.ndarray
        int (N,) number of separate ink arcs (0 when the ring is all paper or all ink).
    coverage : numpy.ndarray
        float64 (N,) fraction of the ring on ink.
    widest : numpy.ndarray
        float64 (N,) largest arc as a fraction of the circle.
    cos_pair : numpy.ndarray
        float64 (N,) cosine of the angle between the two arc centres when there are exactly two, else 1
        (a straight continuation has cos = −1, a hairpin cos ≈ 1).
    """
    rings = np.asarray(rings, bool)
    n, s = rings.shape
    coverage = rings.mean(axis=1)
    mixed = (coverage > 0.0) & (coverage < 1.0)
    # Rotate each ring so it starts on paper: no arc wraps around the end of the vector.
    start = np.argmin(rings, axis=1)
    r = np.take_along_axis(rings, (start[:, None] + np.arange(s)) % s, axis=1) & mixed[:, None]
    edges = np.diff(np.pad(r.astype(np.int8), ((0, 0), (1, 1))), axis=1)
    row_b, begins = np.nonzero(edges == 1)    # row-major: each row's arcs in order,
    _, ends = np.nonzero(edges == -1)         # so the k-th begin and the k-th end are one arc
    runs = np.bincount(row_b, minlength=n)
    longest = np.zeros(n, np.int64)
    np.maximum.at(longest, row_b, ends - begins)
    widest = np.where(mixed, longest / s, coverage)
    cos_pair = np.ones(n)
    pair = np.flatnonzero(runs == 2)
    if len(pair):
        first = np.searchsorted(row_b, pair)  # index of each pair row's first arc
        centres = 2 * np.pi * ((begins[[first, first + 1]] + ends[[first, first + 1]] - 1) / 2.0 + start[pair]) / s
        cos_pair[pair] = np.cos(centres[0] - centres[1])
    return runs, coverage, widest, cos_pair


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
_LABEL_CHUNK = 1 << 22  # window pixels labelled per call: bounds the memory of a drawing with many keypoints


def _connected_rings(mask: np.ndarray, points: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Ink along a circle around each point, counting only the stroke the point lies on.

    Within the disk of radius ``radius + 1.5`` the band is split into 8-connected components; only the
    one holding the point (or, when the point sits just off the ink, the one nearest to it, the first
    in row-major order among equals) is sampled, so a neighbouring stroke that passes near an end without
    touching it does not look like a branch. Points whose windows have the same size are labelled in one
    call (a stack of windows whose structure does not connect them), which is what makes this fast.

    Returns
    -------
    numpy.ndarray
        bool (N, RING_SAMPLES).
    """
    h, w = mask.shape
    n = len(points)
    rings = np.zeros((n, RING_SAMPLES), bool)
    x, y = points[:, 0].astype(np.float64), points[:, 1].astype(np.float64)
    reach = np.ceil(radii).astype(np.int64) + 2
    xi, yi = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    # Windows clipped to the image (a blob's rings are as wide as its width): a window wholly off the
    # image sees no ink and its ring stays empty.
    i0, i1 = np.maximum(yi - reach, 0), np.minimum(yi + reach + 1, h)
    j0, j1 = np.maximum(xi - reach, 0), np.minimum(xi + reach + 1, w)
    fits = (i1 > i0) & (j1 > j0)
    shape_key = np.where(fits, (i1 - i0) * (w + 1) + (j1 - j0), -1)
    plane = np.zeros((3, 3, 3), bool)
    plane[1] = True  # 8-connected within a window, never across windows
    cos_t, sin_t = np.cos(_THETA), np.sin(_THETA)
    for key in np.unique(shape_key[fits]):
        members = np.flatnonzero(shape_key == key)
        hh, ww = divmod(int(key), w + 1)
        for chunk in np.array_split(members, -(-len(members) * hh * ww // _LABEL_CHUNK)):
            rows = i0[chunk, None] + np.arange(hh)          # absolute pixel rows (k, hh)
            cols = j0[chunk, None] + np.arange(ww)
            px, py = x[chunk, None, None], y[chunk, None, None]
            dist2 = (cols[:, None, :] + 0.5 - px) ** 2 + (rows[:, :, None] + 0.5 - py) ** 2
            disk = mask[rows[:, :, None], cols[:, None, :]] & (dist2 <= (radii[chunk, None, None] + 1.5) ** 2)
            labels, count = ndimage.label(disk, structure=plane)
            if count == 0:
                continue
            nearest = np.argmin(np.where(labels > 0, dist2, np.inf).reshape(len(chunk), -1), axis=1)
            stroke_label = labels.reshape(len(chunk), -1)[np.arange(len(chunk)), nearest]
            xs = np.floor(x[chunk, None] + radii[chunk, None] * cos_t).astype(np.int64) - j0[chunk, None]
            ys = np.floor(y[chunk, None] + radii[chunk, None] * sin_t).astype(np.int64) - i0[chunk, None]
            inside = (xs >= 0) & (xs < ww) & (ys >= 0) & (ys < hh)
            sampled = labels[np.arange(len(chunk))[:, None], np.clip(ys, 0, hh - 1), np.clip(xs, 0, ww - 1)]
            rings[chunk] = inside & (sampled == stroke_label[:, None]) & (stroke_label[:, None] > 0)
    return rings


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
    rows = np.arange(n)
    col = 3
    for a, b in RING_RADII:
        runs, coverage, widest, cos_pair = ring_profiles(_connected_rings(mask, points, a * width + b))
        out[rows, col + np.minimum(runs, MAX_RUNS)] = 1.0
        out[:, col + MAX_RUNS + 1:col + MAX_RUNS + 4] = np.stack([coverage, widest, cos_pair], axis=1)
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
