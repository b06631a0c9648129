"""Writing a training run's files: checkpoints atomically, and the shippable weights (both training loops).

A checkpoint is written to a temporary file and renamed over the old one (:func:`_atomic_save`), so
that a run stopped mid-write still resumes from the last complete one; the exported weights
(:func:`export_weights`) are fp16 with the network config and the training record, and the run names
the file it wrote (:func:`say_weights`; the typing perceptron's training does too).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from stages.keypoints.network import KeypointNet


def _atomic_save(obj, path: Path) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def export_weights(model: KeypointNet, path: Path, record: dict) -> None:
    """Write the shippable checkpoint: fp16 weights, network config and a training record.

    Parameters
    ----------
    model : KeypointNet
        The trained network (its floating-point tensors are written as fp16).
    path : Path
        The file to write (``keypoints.pt``), replaced atomically.
    record : dict
        The training record stored with the weights.
    """
    sd = {k: (v.half() if v.is_floating_point() else v) for k, v in model.state_dict().items()}
    _atomic_save({"network": model.cfg.to_dict(), "state_dict": sd, "record": record}, path)
    say_weights(path)


def say_weights(path: Path) -> None:
    """One line naming the weights file just written (the user would otherwise have to search for it).

    Parameters
    ----------
    path : Path
        The weights file.
    """
    print(f"weights written to {Path(path).resolve()} (copy it to stages/keypoints/weights/ to ship it)",
          flush=True)
