"""Function-preserving widening of a trained keypoint network (a Net2Net-style warm start).

A wider :class:`~stages.keypoints.network.KeypointNet` (more channels in the stem and at every level)
starts from a trained narrow one and computes exactly the same heatmaps: every old weight is copied to
its place in the wide network, the new channels' incoming weights keep their random initialisation,
and every weight *reading* a new channel is zero. Training then grows the new channels from the narrow
network's function instead of from scratch (on this CPU a from-scratch run of a wider network would
need the ~40 k steps the narrow one has had).

Why zero fan-out and not Net2Net's channel copies: a copied channel and its twin receive identical
gradients and stay twins until noise separates them; zero fan-out lets the new channels learn at once
(their outgoing weights get a gradient from the first step) and needs no BatchNorm bookkeeping.
"""

from __future__ import annotations

import re

import torch

from stages.keypoints.net_config import NetConfig

# Convolutions whose input is a concatenation of equal-width parts: (name pattern, number of parts).
# Their input channels are remapped part by part (old part p, offset i -> new p * new_width + i).
_CONCAT_INPUTS = ((re.compile(r"^stem\.fuse\.0\.weight$"), 3), (re.compile(r"^up\.\d+\.fuse\.0\.weight$"), 2))


def can_widen(old: NetConfig, new: NetConfig) -> bool:
    """True when ``new`` is ``old`` with at least as many channels everywhere and nothing else changed."""
    return (old.depth == new.depth and old.bottleneck_blocks == new.bottleneck_blocks
            and old.negative_slope == new.negative_slope and old.class_dilations == new.class_dilations
            and (old.class_width or old.level_channels[0]) <= (new.class_width or new.level_channels[0])
            and old.stem_mid <= new.stem_mid
            and all(a <= b for a, b in zip(old.level_channels, new.level_channels)))


def _in_index(name: str, n_old: int, n_new: int) -> torch.Tensor:
    """New positions of a parameter's old input channels."""
    for pattern, parts in _CONCAT_INPUTS:
        if pattern.match(name):
            if n_old % parts or n_new % parts:
                raise ValueError(f"{name}: {n_old} -> {n_new} input channels do not split into {parts} parts")
            c_old, c_new = n_old // parts, n_new // parts
            return torch.cat([p * c_new + torch.arange(c_old) for p in range(parts)])
    # Plain inputs (and PixelShuffle outputs: new channels are appended, so the old groups of four
    # keep their places) keep their indices.
    return torch.arange(n_old)


def widen_state_dict(old_state: dict, new_model: torch.nn.Module) -> dict:
    """The state of ``new_model`` with ``old_state`` (a narrower network of the same layout) embedded.

    Parameters
    ----------
    old_state : dict
        ``state_dict`` of the trained narrow network.
    new_model : torch.nn.Module
        Freshly initialised wide network; its random weights fill the new channels.

    Returns
    -------
    dict
        A state dict for ``new_model`` that computes the same outputs as ``old_state`` in eval mode.
    """
    new_state = {k: v.detach().clone() for k, v in new_model.state_dict().items()}
    if set(old_state) != set(new_state):
        raise ValueError("the two networks differ in layout, not only in width: "
                         f"{sorted(set(old_state) ^ set(new_state))[:4]}")
    for name, new in new_state.items():
        old = old_state[name].to(new.dtype)
        if old.dim() == 0:
            new.copy_(old)
            continue
        if old.dim() != new.dim() or any(a > b for a, b in zip(old.shape, new.shape)):
            raise ValueError(f"{name}: {tuple(old.shape)} does not fit in {tuple(new.shape)}")
        if name.endswith("running_var"):
            new[old.shape[0]:] = 1.0
        elif name.endswith("running_mean"):
            new[old.shape[0]:] = 0.0
        out_idx = torch.arange(old.shape[0])
        if old.dim() == 4:  # conv weight (out, in, kh, kw): nothing old may read a new channel
            in_idx = _in_index(name, old.shape[1], new.shape[1])
            new[: old.shape[0]] = 0.0
            new[out_idx[:, None], in_idx[None, :]] = old
            # The new output channels keep their whole random fan-in: they start as new features.
        else:
            new[out_idx] = old
    return new_state


def widen(old_state: dict, old_cfg: NetConfig, new_cfg: NetConfig) -> dict:
    """Build the wide network's state from a narrow checkpoint (see the module docstring).

    Raises
    ------
    ValueError
        If ``new_cfg`` is not a widening of ``old_cfg``.
    """
    from stages.keypoints.network import KeypointNet

    if not can_widen(old_cfg, new_cfg):
        raise ValueError(f"network {new_cfg.to_dict()} is not a widening of {old_cfg.to_dict()}")
    # The wide network is built on the CPU; a checkpoint loaded onto a GPU is brought to it first.
    return widen_state_dict({k: v.detach().float().cpu() for k, v in old_state.items()}, KeypointNet(new_cfg))
