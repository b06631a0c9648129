"""Scoring the keypoint network on a validation set during training (both training loops).

The detector's loop (:func:`stages.keypoints.training.loop.train`) scores the network every
``val.every`` steps, and the class branch's (:func:`stages.keypoints.training.class_branch.train_class_branch`)
once at the end, on the drawings of :func:`stages.keypoints.training.data.validation_set`: the stage's
own peak finding, then a one-to-one match within 5 px (:func:`stages.evaluate.keypoints.match_keypoints`).
"""

from __future__ import annotations

import numpy as np
import torch

from stages.evaluate.keypoints import MatchResult, match_keypoints
from stages.keypoints.inference import find_keypoints
from stages.keypoints.network import KeypointNet


def evaluate(model: KeypointNet, val, kcfg: dict, device: torch.device) -> MatchResult:
    """One-to-one (5 px) matching result of ``model`` on a validation set.

    Parameters
    ----------
    model : KeypointNet
        Put in eval mode for the pass and back in train mode after it.
    val : iterable
        ``(x, band, points, types)`` per drawing (:func:`stages.keypoints.training.data.validation_set`).
    kcfg : dict
        The ``keypoints`` config section: its peak finding settings.
    device : torch.device
        Where the model runs.

    Returns
    -------
    MatchResult
        The matches of all the drawings together.
    """
    model.eval()
    total = MatchResult()
    with torch.inference_mode():
        for x, band, pts, types in val:
            m = model.multiple
            h, w = x.shape
            xp = np.pad(x, ((0, m - h % m), (0, m - w % m)))
            hm = model(torch.from_numpy(xp)[None, None].to(device))[0][0].float().cpu().numpy()[:, :h, :w]
            p, t, _ = find_keypoints(hm, float(kcfg["threshold"]), int(kcfg["min_distance"]),
                                     band if kcfg["restrict_to_band"] else None, bool(kcfg["subpixel"]))
            total = total + match_keypoints(pts, types, p, t, 5.0)
    model.train()
    return total
