"""Stage ``keypoints``: CNN heatmaps, peaks and keypoint types.

The shipped weights files, ``STAGE_VERSION`` (it carries a short hash of each, so new weights
invalidate cached results) and the config dataclass. Its code, and the docstring that describes it
and its choices, are in :mod:`stages.keypoints.stage`; ``run`` and its other public names load from
there when first used (:mod:`stages.lazy`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

from stages.errors import InputError
from stages.lazy import lazy_names

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
PACKAGED_WEIGHTS = WEIGHTS_DIR / "keypoints.pt"
PACKAGED_TYPE_CLASSIFIER = WEIGHTS_DIR / "type_classifier.npz"
# The procedural-only detector (keypoints.pt before it was fine-tuned on human strokes): its H1 is
# averaged with the main network's (``detection_ensemble``); see MODEL_CARD.md.
PACKAGED_PROCEDURAL = WEIGHTS_DIR / "keypoints_procedural.pt"


#: Test-time views (``test_time_views``): each an involution of the last two axes, so it also maps the
#: view's output back onto the drawing (:func:`stages.keypoints.inference.predict_views`).
VIEWS = {
    "flip_x": lambda a: a[..., ::-1],
    "flip_y": lambda a: a[..., ::-1, :],
    "rot180": lambda a: a[..., ::-1, ::-1],
    "transpose": lambda a: a.swapaxes(-1, -2),
}


def _file_hash(path: Path) -> str:
    if not path.is_file():
        return "missing"  # load_model refuses to run without it
    return hashlib.sha256(path.read_bytes()).hexdigest()[:10]


# 4: BatchNorms folded into the convolutions at load (heatmaps move by float rounding)
# 7: 1×1 convolutions by oneDNN (network.use_onednn_pointwise; heatmaps move by float rounding)
# 8: concatenations fused part by part, one-channel 1×1 convolutions as a scaling (float rounding)
STAGE_VERSION = "8+" + "+".join(_file_hash(p) for p in (PACKAGED_WEIGHTS, PACKAGED_TYPE_CLASSIFIER, PACKAGED_PROCEDURAL))


@dataclass
class KeypointsConfig:
    """The ``keypoints`` config section (``conf/keypoints/default.yaml``), one field per key."""

    weights: str
    detection_ensemble: list[str]
    test_time_views: list[str]
    typing: str
    type_classifier: str | None
    threshold: float
    junction_threshold: float | None
    min_distance: int
    restrict_to_band: bool
    band_dilation: int
    subpixel: bool
    contrast_floor: float
    single_pass_max: int
    tile_size: int
    tile_overlap: int
    max_keypoints: int
    torch_threads: int
    precision: str

    def __post_init__(self) -> None:
        if self.typing not in ("valence", "argmax"):
            raise InputError(f"typing must be 'valence' or 'argmax', got {self.typing!r}")
        bad = [v for v in self.test_time_views if v not in VIEWS]
        if bad or len(set(self.test_time_views)) != len(self.test_time_views):
            raise InputError(f"keypoints.test_time_views must be distinct names among {list(VIEWS)}, "
                             f"got {list(self.test_time_views)}")
        if self.precision not in ("fp32", "bf16", "auto"):
            raise InputError(f"keypoints.precision must be 'fp32', 'bf16' or 'auto', got {self.precision!r}")
        for key in ("threshold", "junction_threshold"):
            value = getattr(self, key)
            if value is not None and not 0.0 < value <= 1.0:
                raise InputError(f"keypoints.{key} must be in (0, 1], got {value}")


__getattr__, __dir__ = lazy_names(__name__, {
    "stages.keypoints.stage": ("run", "preload", "load_model", "load_type_classifier", "keypoints_from_heatmaps",
                               "render_keypoints"),
})
