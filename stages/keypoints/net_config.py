"""Width and depth of the keypoint network, apart from the network itself.

Why a module of its own: the configs (:mod:`pipeline.engine.config`) need this dataclass at every start-up,
and :mod:`stages.keypoints.network` imports torch (about 1.5 s), which a run whose keypoints are
cached never needs.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class NetConfig:
    """Width and depth of :class:`KeypointNet` (``conf/train/default.yaml`` ``network``).

    Attributes
    ----------
    stem_mid : int
        Channels inside the three ResNeXt branches of the stem.
    level_channels : tuple of int
        Feature channels at resolution 1, 1/2, 1/4, …, 1/2**depth (length ``depth + 1``); all but the
        first must be divisible by 4 (PixelShuffle).
    bottleneck_blocks : int
        Residual blocks at the coarsest level (the paper uses 3, with twice the channels inside).
    negative_slope : float
        LeakyReLU slope.
    class_width : int
        Channels of the class branch (0 = ``level_channels[0]``, the first shipped model's head).
    class_dilations : tuple of int
        Dilation of each 3×3 conv of the class branch; ``(1,)`` is the first shipped model's head.
        Checkpoints written before these two keys existed load with (0, (1,)).
    """

    stem_mid: int
    level_channels: tuple[int, ...]
    bottleneck_blocks: int
    negative_slope: float
    class_width: int
    class_dilations: tuple[int, ...]

    @property
    def depth(self) -> int:
        return len(self.level_channels) - 1

    @classmethod
    def from_dict(cls, d: dict) -> "NetConfig":
        """From the ``network`` record of a checkpoint (configs go through :func:`stages.config.from_section`)."""
        # The two class-branch keys are absent from checkpoints of the first shipped model; their
        # legacy values rebuild exactly that model's head.
        return cls(stem_mid=int(d["stem_mid"]), level_channels=tuple(int(c) for c in d["level_channels"]),
                   bottleneck_blocks=int(d["bottleneck_blocks"]), negative_slope=float(d["negative_slope"]),
                   class_width=int(d.get("class_width", 0)),
                   class_dilations=tuple(int(k) for k in d.get("class_dilations", (1,))))

    def to_dict(self) -> dict:
        return {"stem_mid": self.stem_mid, "level_channels": list(self.level_channels),
                "bottleneck_blocks": self.bottleneck_blocks, "negative_slope": self.negative_slope,
                "class_width": self.class_width, "class_dilations": list(self.class_dilations)}
