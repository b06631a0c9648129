"""The keypoint network (paper §3, Appendix B, Fig. 21; authors' notes §2 "PyramidalNet").

A ResNeXt stem, an hourglass that downsamples with learned 2×2 stride-2 convolutions and upsamples
with PixelShuffle, skip connections at every level, four full-resolution heads (H1 any keypoint,
H2 endpoint, H3 junction, H4 sharp corner) and two intermediate H1 heads at 0.25× and 0.5× (H5, H6)
that only serve training.

Choices made on purpose
-----------------------
* **Width grows with depth** (``level_channels``), where the authors keep 96 channels at every level.
  A 96-channel full-resolution tensor costs far more than 2 CPU cores can afford for a 700×700
  drawing in 2 s; the receptive field comes from the coarse levels, where channels are cheap.
* **LeakyReLU everywhere**, as Appendix B says. The authors' code uses sin (SIREN) activations in
  the 1/8 bottleneck; the paper does not mention them and they gain nothing measurable here.
* **Class heads** share one full-resolution class branch on the decoder features (``class_width``
  channels, one 3×3 conv per entry of ``class_dilations``, then a 1×1 conv to three maps), instead of
  three separate ResNeXt modules: the class maps are only read at detected peaks (argmax), so a light
  branch keeps inference fast. The first shipped model used a single 3×3 conv on 8 channels
  (``class_width 0, class_dilations [1]``); it never let the corner map win. Dilations 1, 2, 4, 8 give
  the branch ±15 px of context, enough to see both arms of a corner. The branch can be re-trained alone
  on a frozen detector (``python -m pipeline.train --class-branch``); the shipped one has 16 channels,
  distilled from phase 22g's 32 (``train.class_branch.distill``): a third of the network's time on a
  CPU without bf16 for the same types (MODEL_CARD, phase 26d).
* All heads end in ``tanh``. The authors end H1 in ``tanh`` but the class maps in ``sigmoid``; with
  the masked L1-like loss of Eq. 1, whose targets are 0 on almost every band pixel, a sigmoid head is
  driven into saturation at 0 where its gradient vanishes: our first model's class maps stayed ≈ 0
  and every keypoint came out an endpoint (classification accuracy 0.42 on realvec_dev). ``tanh`` has
  slope 1 at 0, so the class maps keep learning. Consumers clip the maps to [0, 1].
* Skips are concatenated then fused by a 3×3 convolution (the authors' code); Fig. 21 says "add".
"""

from __future__ import annotations


import torch
from torch import nn

from stages.keypoints.net_config import NetConfig


def _cbr(cin: int, cout: int, k: int, slope: float, dilation: int = 1, act: bool = True) -> nn.Sequential:
    """Conv + BatchNorm (+ LeakyReLU); 'same' padding."""
    pad = dilation * (k // 2)
    layers: list[nn.Module] = [nn.Conv2d(cin, cout, k, padding=pad, dilation=dilation, bias=False),
                               nn.BatchNorm2d(cout)]
    if act:
        layers.append(nn.LeakyReLU(slope, inplace=True))
    return nn.Sequential(*layers)


def _fuse_parts(fuse: nn.Module, parts: list[torch.Tensor]) -> torch.Tensor:
    """``fuse`` of the channel concatenation of ``parts``; without the concatenation where ``fuse`` was
    split for inference (:class:`PartwiseFuse`)."""
    if isinstance(fuse, PartwiseFuse):
        return fuse(parts)
    return fuse(torch.cat(parts, dim=1))


class ResNeXtModule(nn.Module):
    """The stem: three parallel branches with growing receptive field, fused by 1×1 conv.

    Branches: 1×1 → 3×3; 3×3 → 3×3 (dilation 2); 3×3 (dil. 2) → 3×3 (dil. 2), each ending in a 1×1
    conv to ``cout``; concatenated, fused by 1×1 conv + BN, plus a 1×1 skip (authors' notes §2).
    """

    def __init__(self, cin: int, cout: int, mid: int, slope: float):
        super().__init__()
        self.branches = nn.ModuleList([
            nn.Sequential(_cbr(cin, mid, 1, slope), _cbr(mid, mid, 3, slope), _cbr(mid, cout, 1, slope)),
            nn.Sequential(_cbr(cin, mid, 3, slope), _cbr(mid, mid, 3, slope, 2), _cbr(mid, cout, 1, slope)),
            nn.Sequential(_cbr(cin, mid, 3, slope, 2), _cbr(mid, mid, 3, slope, 2), _cbr(mid, cout, 1, slope)),
        ])
        self.fuse = _cbr(3 * cout, cout, 1, slope, act=False)
        self.skip = nn.Conv2d(cin, cout, 1)
        self.act = nn.LeakyReLU(slope, inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = _fuse_parts(self.fuse, [b(x) for b in self.branches])
        return self.act(y + self.skip(x))


class ResidualModule(nn.Module):
    """Bottleneck residual block 1×1 → 3×3 → 1×1 with a 1×1 conv + BN skip."""

    def __init__(self, cin: int, cout: int, slope: float, mid: int | None = None):
        super().__init__()
        mid = mid or max(cout // 2, 4)
        self.body = nn.Sequential(_cbr(cin, mid, 1, slope), _cbr(mid, mid, 3, slope), _cbr(mid, cout, 1, slope, act=False))
        self.skip = nn.Identity() if cin == cout else _cbr(cin, cout, 1, slope, act=False)
        self.act = nn.LeakyReLU(slope, inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.body(x) + self.skip(x))


class _Up(nn.Module):
    """PixelShuffle(2), 3×3 conv to the finer level's width, concat skip, fuse, residual block."""

    def __init__(self, cin: int, cout: int, slope: float):
        super().__init__()
        self.shuffle = nn.PixelShuffle(2)
        self.expand = _cbr(cin // 4, cout, 3, slope, act=False)
        self.fuse = _cbr(2 * cout, cout, 3, slope)
        self.res = ResidualModule(cout, cout, slope)

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        x = self.expand(self.shuffle(x))
        return self.res(_fuse_parts(self.fuse, [x, skip]))


class KeypointNet(nn.Module):
    """Hourglass keypoint detector producing H1..H6.

    Input: (B, 1, H, W) contrast-normalised ink (1 = ink, 0 = paper), H and W multiples of
    ``2**depth``. Output of :meth:`forward`: ``(final, intermediate)`` where ``final`` is (B, 4, H, W)
    = [H1 detection, H2 endpoint, H3 junction, H4 corner], all four ending in ``tanh`` and ``intermediate`` is the
    list of H1 predictions at the coarser levels, coarsest first (0.25×, 0.5× for depth 3).
    """

    def __init__(self, cfg: NetConfig):
        super().__init__()
        self.cfg = cfg
        ch, s = cfg.level_channels, cfg.negative_slope
        for c in ch[1:]:
            if c % 4:
                raise ValueError(f"level_channels {ch}: coarse widths must be divisible by 4 (PixelShuffle)")
        self.stem = ResNeXtModule(1, ch[0], cfg.stem_mid, s)
        self.shortcuts = nn.ModuleList([_cbr(c, c, 1, s, act=False) for c in ch[:-1]])
        self.down_res = nn.ModuleList([ResidualModule(c, c, s) for c in ch[:-1]])
        self.down = nn.ModuleList([nn.Sequential(nn.Conv2d(ch[k], ch[k + 1], 2, stride=2, bias=False),
                                                 nn.BatchNorm2d(ch[k + 1]), nn.LeakyReLU(s, inplace=True))
                                   for k in range(cfg.depth)])
        c = ch[-1]
        blocks = []
        for b in range(cfg.bottleneck_blocks):
            blocks.append(ResidualModule(c, c, s, mid=2 * c))
        self.bottleneck = nn.Sequential(*blocks)
        self.up = nn.ModuleList([_Up(ch[k + 1], ch[k], s) for k in range(cfg.depth)])
        # Side heads: one per up level (index k = resolution 1/2**k); k = 0 is H1.
        self.side = nn.ModuleList([nn.Conv2d(ch[k], 1, 3, padding=1) for k in range(min(cfg.depth, 3))])
        cw = cfg.class_width or ch[0]
        branch: list[nn.Module] = []
        for k, dil in enumerate(cfg.class_dilations):
            branch.append(_cbr(ch[0] if k == 0 else cw, cw, 3, s, dilation=int(dil)))
        branch.append(nn.Conv2d(cw, 3, 1))
        self.class_head = nn.Sequential(*branch)

    @property
    def multiple(self) -> int:
        """Input sides must be multiples of this."""
        return 2 ** self.cfg.depth

    def trunk(self, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Full-resolution decoder features (input of H1 and the class branch) and H5, H6."""
        f = self.stem(x)
        skips = []
        for k in range(self.cfg.depth):
            skips.append(self.shortcuts[k](f))
            f = self.down[k](self.down_res[k](f))
        f = self.bottleneck(f)
        intermediate = []
        for k in reversed(range(self.cfg.depth)):
            f = self.up[k](f, skips[k])
            if 0 < k < len(self.side):  # the paper's H5 (0.25×) and H6 (0.5×)
                intermediate.append(torch.tanh(self.side[k](f)))
        return f, intermediate

    def detect(self, x: torch.Tensor) -> torch.Tensor:
        """H1 alone, (B, 1, H, W): skips the full-resolution class branch (a detection ensemble
        member only contributes H1)."""
        return torch.tanh(self.side[0](self.trunk(x)[0]))

    def forward(self, x: torch.Tensor, return_logits: bool = False):
        f, intermediate = self.trunk(x)
        h1 = torch.tanh(self.side[0](f))
        logits = self.class_head(f)
        out = torch.cat([h1, torch.tanh(logits)], dim=1)
        if return_logits:  # training: the auxiliary classification loss uses the class logits
            return out, intermediate, logits
        return out, intermediate


def fold_batch_norms(model: nn.Module) -> nn.Module:
    """Fold every BatchNorm that follows a convolution into that convolution, in place (inference).

    In eval mode a BatchNorm is an affine map per channel, so conv → BN is one conv with scaled
    weights and a bias. Folding removes a third of the network's passes over full-resolution tensors
    (the heatmaps change by float rounding only: ≤ 2e-5 on a 704² drawing). Every conv → BN pair of this network sits
    in an ``nn.Sequential`` (``_cbr`` and the downsampling steps).

    Parameters
    ----------
    model : torch.nn.Module
        A network in eval mode; training it after folding is not meaningful.

    Returns
    -------
    torch.nn.Module
        ``model``, with each folded BatchNorm replaced by ``nn.Identity``.
    """
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    if model.training:
        raise ValueError("fold_batch_norms needs a model in eval mode")
    for seq in [m for m in model.modules() if isinstance(m, nn.Sequential)]:
        for i in range(len(seq) - 1):
            if isinstance(seq[i], nn.Conv2d) and isinstance(seq[i + 1], nn.BatchNorm2d):
                seq[i] = fuse_conv_bn_eval(seq[i], seq[i + 1])
                seq[i + 1] = nn.Identity()
    return model


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


class OneDNNPointwise(nn.Module):
    """A 1×1 convolution run by oneDNN on channels-last tensors (inference on the CPU).

    PyTorch sends a 1×1 float32 convolution on one thread to its generic im2col path, which is 3–4×
    slower than oneDNN here and hands back a contiguous (not channels-last) tensor that the next 3×3
    convolution must reorder. This module calls oneDNN directly; anything else (bfloat16 autocast,
    gradients) takes the usual ``conv2d``. :func:`use_onednn_pointwise` makes none on a build without oneDNN.

    Parameters
    ----------
    conv : torch.nn.Conv2d
        A 1×1, stride-1, ungrouped convolution; its weight and bias are shared, not copied.
    """

    def __init__(self, conv: nn.Conv2d):
        super().__init__()
        self.weight, self.bias = conv.weight, conv.bias

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return _conv(x, self.weight, self.bias, [0, 0], [1, 1])


def use_onednn_pointwise(model: nn.Module) -> nn.Module:
    """Replace the 1×1 stride-1 convolutions of ``model`` by :class:`OneDNNPointwise` (none where torch
    was built without oneDNN), those from one input channel by :class:`ChannelScale`, in place.

    Parameters
    ----------
    model : torch.nn.Module
        A network for inference (the state dict keys stay the same).

    Returns
    -------
    torch.nn.Module
        ``model``.
    """
    for parent in list(model.modules()):
        for name, child in parent.named_children():
            if isinstance(child, nn.Conv2d) and child.kernel_size == (1, 1) and child.stride == (1, 1) \
                    and child.dilation == (1, 1) and child.groups == 1 and child.padding == (0, 0):
                # On one input channel (the drawing itself) oneDNN is slower than conv2d's generic path
                # (63 vs 24 ms at 704², which returns the plain layout the next convolution reorders); a
                # scaling per output channel into a channels-last tensor takes 3 ms.
                if child.in_channels == 1:
                    setattr(parent, name, ChannelScale(child))
                elif _ONEDNN:
                    setattr(parent, name, OneDNNPointwise(child))
    return model


class ChannelScale(nn.Module):
    """A 1×1 convolution from one input channel: each output channel is the input times its weight plus
    its bias, written channels-last (what the next convolution reads; inference on the CPU in float32,
    else ``conv2d``).

    Parameters
    ----------
    conv : torch.nn.Conv2d
        A 1×1, stride-1 convolution with one input channel; its weight and bias are shared, not copied.
    """

    def __init__(self, conv: nn.Conv2d):
        super().__init__()
        self.weight, self.bias = conv.weight, conv.bias

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not (_plain_inference(x, self.weight) and x.shape[1] == 1):
            return nn.functional.conv2d(x, self.weight, self.bias)
        n, _, h, w = x.shape
        c = self.weight.shape[0]
        out = torch.empty((n, c, h, w), dtype=x.dtype, memory_format=torch.channels_last)
        bias = self.bias.view(1, c, 1, 1) if self.bias is not None else torch.zeros(1, c, 1, 1, dtype=x.dtype)
        return torch.addcmul(bias, x, self.weight.view(1, c, 1, 1), out=out)


def _plain_inference(x: torch.Tensor, weight: torch.Tensor) -> bool:
    """float32 inference on the CPU: no gradients, no autocast (where ``conv2d`` itself must run)."""
    return (x.dtype == weight.dtype == torch.float32 and x.device.type == "cpu" and not torch.is_grad_enabled()
            and not torch.is_autocast_enabled("cpu"))


#: Whether this torch was built with oneDNN (decided once: it cannot change in a process).
_ONEDNN = torch.backends.mkldnn.is_available()


def _conv(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, padding: list[int],
          dilation: list[int]) -> torch.Tensor:
    """A stride-1 ungrouped convolution: by oneDNN on a channels-last input for float32 inference on the
    CPU (:func:`_plain_inference`, a build with oneDNN), else by ``conv2d``."""
    if _ONEDNN and _plain_inference(x, weight):
        return torch.ops.aten.mkldnn_convolution(x.contiguous(memory_format=torch.channels_last), weight, bias,
                                                 padding, [1, 1], dilation, 1)
    return nn.functional.conv2d(x, weight, bias, padding=padding, dilation=dilation)


class PartwiseFuse(nn.Module):
    """A folded ``conv → (Identity) → activation`` over a channel concatenation, run part by part.

    ``conv(cat(parts))`` is the sum of each part's convolution with its slice of the input channels,
    so the concatenated tensor is never made: at 704² the stem's is 95 MB and the finest decoder
    level's 63 MB, over glibc's 32-MiB mmap ceiling, so each was a fresh mapping faulted in page by
    page, and concatenating channels-last tensors copies them once more. Inference only (the
    weights are sliced copies).

    Parameters
    ----------
    fuse : torch.nn.Sequential
        A convolution (BatchNorm already folded into it) followed by identities and an optional activation.
    widths : list of int
        The channels of each part, in concatenation order; they sum to the convolution's input channels.
    """

    def __init__(self, fuse: nn.Sequential, widths: list[int]):
        super().__init__()
        conv = fuse[0]
        if not isinstance(conv, nn.Conv2d) or conv.groups != 1 or conv.stride != (1, 1) or sum(widths) != conv.in_channels:
            raise ValueError(f"PartwiseFuse needs an ungrouped stride-1 Conv2d over {sum(widths)} channels, got {conv}")
        if any(isinstance(m, nn.BatchNorm2d) for m in fuse):
            raise ValueError("PartwiseFuse needs its BatchNorm folded first (fold_batch_norms)")
        starts = [sum(widths[:k]) for k in range(len(widths))]
        self.weights = nn.ParameterList([nn.Parameter(conv.weight[:, a:a + w].detach().clone(), requires_grad=False)
                                         for a, w in zip(starts, widths)])
        self.bias = conv.bias
        self.padding, self.dilation = list(conv.padding), list(conv.dilation)
        self.rest = nn.Sequential(*fuse[1:])

    def forward(self, parts: list[torch.Tensor]) -> torch.Tensor:
        out = None
        for k, (x, w) in enumerate(zip(parts, self.weights)):
            y = _conv(x, w, self.bias if k == 0 else None, self.padding, self.dilation)
            out = y if out is None else out.add_(y)
        return self.rest(out)


def split_concatenations(model: nn.Module) -> nn.Module:
    """Run the fusions of the stem's branches and of each decoder level's skip (:class:`PartwiseFuse`)
    part by part, in place; call after :func:`fold_batch_norms` (the state dict keys change: inference only).

    Parameters
    ----------
    model : KeypointNet
        A network in eval mode with its BatchNorms folded.

    Returns
    -------
    KeypointNet
        ``model``.
    """
    for m in model.modules():
        # Equal parts: the stem's branches all end in its width, a decoder level's upsampled map and skip in its own.
        parts = len(m.branches) if isinstance(m, ResNeXtModule) else 2 if isinstance(m, _Up) else 0
        if parts and not isinstance(m.fuse, PartwiseFuse):
            m.fuse = PartwiseFuse(m.fuse, [m.fuse[0].in_channels // parts] * parts)
    return model
