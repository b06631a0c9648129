"""Training targets and loss of the keypoint network (paper §3.1, Eq. 1).

* Ground-truth heatmaps Ĥ place a Gaussian (σ = 2 px) on every keypoint: Ĥ1 on all of them, Ĥ2..Ĥ4
  on the endpoints, junctions and sharp corners; overlapping Gaussians combine by max, so every peak
  is exactly 1. The intermediate targets Ĥ5 (0.25×) and Ĥ6 (0.5×) are max-pooled from Ĥ1, keeping
  their peaks at 1.
* Eq. 1: L = Σ_i w_i φ(H_i − Ĥ_i) with φ(x) = 0.6 x for x ≥ 0 (false positive), |x| otherwise (false
  negative), averaged over the **narrow band** only — the authors stress that without the mask the
  network collapses to all-zero predictions. The band is the prep stage's ink mask dilated by a few
  pixels so that the Gaussian tails just beyond a stroke end are supervised too.
* Weights (paper): w1 = 1, w2 = w3 = w4 = 0.2, w5 = 0.4, w6 = 0.6; we take H5 = 0.25× and
  H6 = 0.5× (the paper lists them in that order).
* :func:`class_cross_entropy` is an optional auxiliary term (weight ``class_ce_weight``, 0 = the
  paper's loss alone): softmax cross-entropy of the three class logits at the pixels near a keypoint
  (Ĥ1 > 0.5). Eq. 1 trains each class map towards a 0.625-quantile, i.e. a hard "is it this class"
  decision per map; with short training the majority class (endpoint) fires everywhere and the
  argmax is biased. The cross-entropy trains the one thing the argmax reads: which map is highest.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from stages.keypoints.codes import TYPE_CODES


def gaussian_heatmaps(shape: tuple[int, int], points: np.ndarray, types: np.ndarray, sigma: float) -> np.ndarray:
    """Target heatmaps Ĥ1..Ĥ4 for keypoints.

    Parameters
    ----------
    shape : (H, W)
    points : numpy.ndarray
        (N, 2) keypoints in (x, y), pixel centres at +0.5.
    types : numpy.ndarray
        (N,) codes 1, 3, 5.
    sigma : float
        Gaussian standard deviation in pixels (paper: 2).

    Returns
    -------
    numpy.ndarray
        float32 (4, H, W) in [0, 1]: detection, endpoint, junction, corner.
    """
    h, w = shape
    out = np.zeros((4, h, w), np.float32)
    rad = int(np.ceil(3 * sigma))
    for (x, y), t in zip(np.asarray(points, float).reshape(-1, 2), np.asarray(types).reshape(-1)):
        ci, cj = int(np.floor(y)), int(np.floor(x))
        i0, i1 = max(ci - rad, 0), min(ci + rad + 1, h)
        j0, j1 = max(cj - rad, 0), min(cj + rad + 1, w)
        if i0 >= i1 or j0 >= j1:
            continue
        yy = np.arange(i0, i1)[:, None] + 0.5 - y
        xx = np.arange(j0, j1)[None, :] + 0.5 - x
        g = np.exp(-(xx * xx + yy * yy) / (2 * sigma * sigma)).astype(np.float32)
        ch = 1 + TYPE_CODES.index(int(t))
        np.maximum(out[0, i0:i1, j0:j1], g, out=out[0, i0:i1, j0:j1])
        np.maximum(out[ch, i0:i1, j0:j1], g, out=out[ch, i0:i1, j0:j1])
    return out


def asymmetric_l1(pred: torch.Tensor, target: torch.Tensor, fp_weight: float = 0.6) -> torch.Tensor:
    """φ(H − Ĥ) of Eq. 1, elementwise: ``fp_weight``·x where x ≥ 0, |x| where x < 0."""
    x = pred - target
    return torch.where(x >= 0, fp_weight * x, -x)


def keypoint_loss(final: torch.Tensor, intermediate: list[torch.Tensor], target: torch.Tensor,
                  band: torch.Tensor, weights: tuple[float, ...], fp_weight: float = 0.6
                  ) -> tuple[torch.Tensor, dict[str, float]]:
    """The masked loss of Eq. 1.

    Parameters
    ----------
    final : torch.Tensor
        (B, 4, H, W) predictions H1..H4.
    intermediate : list of torch.Tensor
        Predictions of H1 at coarser levels, coarsest first: [(B,1,H/4,W/4), (B,1,H/2,W/2)].
    target : torch.Tensor
        (B, 4, H, W) Gaussian targets.
    band : torch.Tensor
        (B, 1, H, W) float, 1 inside the (dilated) narrow band.
    weights : tuple of 6 float
        w1..w6 (H5 = 0.25×, H6 = 0.5×).
    fp_weight : float
        Slope of φ for false positives (paper: 0.6).

    Returns
    -------
    loss : torch.Tensor
        Scalar.
    parts : dict
        The six weighted terms, as floats (for logging).
    """
    if len(weights) != 6:
        raise ValueError("keypoint_loss needs six weights w1..w6")
    terms = []
    denom = band.sum().clamp_min(1.0)
    for c in range(4):
        terms.append((asymmetric_l1(final[:, c:c + 1], target[:, c:c + 1], fp_weight) * band).sum() / denom)
    h1 = target[:, :1]
    for k, pred in enumerate(intermediate[-2:]):
        f = h1.shape[-1] // pred.shape[-1]
        t = F.max_pool2d(h1, f)
        b = F.max_pool2d(band, f)
        terms.append((asymmetric_l1(pred, t, fp_weight) * b).sum() / b.sum().clamp_min(1.0))
    while len(terms) < 6:
        terms.append(final.new_zeros(()))
    w = torch.as_tensor(weights, dtype=final.dtype, device=final.device)
    stacked = torch.stack(terms) * w
    names = ("h1", "h2", "h3", "h4", "h5", "h6")
    return stacked.sum(), {n: float(v) for n, v in zip(names, stacked.detach().cpu())}


def junction_weighted_band(band: torch.Tensor, target: torch.Tensor, weight: float) -> torch.Tensor:
    """The loss mask with the pixels around junctions counted ``1 + weight·Ĥ3`` times.

    Not in the paper. Junction class F1 trails the other classes because crossings a few pixels apart
    (knots of three or four strokes) share one predicted peak; weighting Eq. 1 there makes a missed
    second peak cost more than the rest of the band. ``weight`` 0 returns ``band`` itself.

    Parameters
    ----------
    band : torch.Tensor
        (B, 1, H, W) loss mask.
    target : torch.Tensor
        (B, 4, H, W) Gaussian targets (channel 2 = junctions).
    weight : float
        Extra weight at a junction's centre.

    Returns
    -------
    torch.Tensor
        (B, 1, H, W) weighted mask, zero outside ``band``.
    """
    if weight == 0:
        return band
    return band * (1.0 + float(weight) * target[:, 2:3])


def class_cross_entropy(logits: torch.Tensor, target: torch.Tensor, band: torch.Tensor,
                        near: float = 0.5) -> torch.Tensor:
    """Cross-entropy of the class logits against the keypoint type, at pixels near keypoints.

    Parameters
    ----------
    logits : torch.Tensor
        (B, 3, H, W) pre-activation class maps (endpoint, junction, corner).
    target : torch.Tensor
        (B, 4, H, W) Gaussian targets; the type of a pixel is the argmax of channels 1..3.
    band : torch.Tensor
        (B, 1, H, W) loss mask.
    near : float
        Pixels with Ĥ1 above this count.

    Returns
    -------
    torch.Tensor
        Scalar (0 when no pixel qualifies).
    """
    sel = (target[:, 0] > near) & (band[:, 0] > 0)
    if not bool(sel.any()):
        return logits.sum() * 0.0
    cls = target[:, 1:4].argmax(dim=1)
    ce = F.cross_entropy(logits, cls, reduction="none")
    return ce[sel].mean()
