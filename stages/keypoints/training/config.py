"""The ``train`` config group (``conf/train/default.yaml``) as dataclasses, one field per key.

:class:`TrainConfig` is registered as a Hydra structured config (:mod:`pipeline.engine.config`), and
``python -m pipeline.train --plain`` checks its YAML with :func:`stages.config.from_section`, so the
YAML and these classes cannot disagree. The training code reads the plain dict; the sections with a
class of their own (``network``, ``generator``, ``labels``) are built with ``from_section`` where used.

The classes of ``generator`` and ``labels`` are here rather than beside their code
(:mod:`~stages.keypoints.training.generator`, :mod:`~stages.keypoints.training.labels`, which import
them from here), and ``network``'s is in :mod:`stages.keypoints.net_config`: the configs need them at
every start-up, and that code imports numba, scipy and torch, which a vectorisation whose artifacts are
stored never needs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from stages.keypoints.net_config import NetConfig


@dataclass
class GeneratorConfig:
    """Distribution of the procedural drawings (``conf/train/default.yaml`` ``generator``)."""

    size_min: int
    size_max: int
    primitives_min: int
    primitives_max: int
    width_min: float
    width_max: float
    width_log_mean: float     # log(px) of the typical base width (e ≈ 2.7 px)
    width_log_std: float
    width_vary_prob: float    # per-stroke widths differ within a drawing
    pressure_prob: float      # width modulated along the stroke, tapered ends
    jitter_px: float          # hand tremor amplitude (low-frequency), px
    pencil_prob: float
    blur_max: float           # Gaussian blur sigma, px
    paper_noise_max: float    # std of paper noise (1 = black-to-white)
    ink_min: float            # lightest ink darkness (pencil)
    gap_max: float            # T-ends stop short / overshoot by up to this × width
    thin_prob: float          # share of drawings in thin grey aliased ink (1–2 px, hard edges)


@dataclass
class LabelRules:
    """Thresholds of the labelling rules (``conf/train/default.yaml`` ``labels``)."""

    min_radius: float
    corner_turn_deg: float
    crossing_min_deg: float
    step: float
    own_stroke_tee: bool


@dataclass
class ValConfig:
    """``train.val``: the fixed validation drawings and how often they are scored."""

    count: int
    seed: int
    vector_count: int
    every: int


@dataclass
class ClassBranchConfig:
    """``train.class_branch``: re-training the class branch alone on a frozen detector."""

    drawings: int
    seed: int
    val_drawings: int
    val_seed: int
    patch: int
    supervised_margin: int
    epochs: int
    batch_size: int
    lr: float
    balance_power: float
    distill: bool
    peak_threshold: float


@dataclass
class TypeClassifierConfig:
    """``train.type_classifier``: the keypoint typing perceptron (stages/keypoints/valence.py)."""

    drawings: int
    seed: int
    val_drawings: int
    val_seed: int
    hidden: int
    epochs: int
    lr: float
    weight_decay: float
    balance_power: float
    vector: bool
    vector_drawings: int | None


@dataclass
class VectorConfig:
    """``train.vector``: the human strokes (Quick, Draw! categories, Omniglot stroke-3 symbols)."""

    files: list[str]
    holdout: int
    split_seed: int
    skip: int
    stroke3: list[str]
    stroke3_prob: float
    stroke3_size: list[int]
    stroke3_simplify: float
    renders: int
    size: list[int]
    stroke_count_power: float     # detector training: Quick, Draw! draws weighted by strokes^power (0 = uniform)
    compose_prob: float           # share of Quick, Draw! draws with a second drawing laid over (detector and typing data)
    compose_scale: list[float]    # the second drawing's side as a share of the canvas, [lo, hi]


@dataclass
class TrainConfig:
    """The ``train`` config group (``conf/train/default.yaml``), one field per key."""

    seed: int
    out_dir: str
    resume: bool
    device: str
    cpu_threads: int
    amp: bool
    cpu_amp: Any                  # true, false or "auto" (bf16 where the CPU has native bf16)
    channels_last: bool
    steps: int
    schedule_minutes: float | None
    batch_size: int
    lr: float
    weight_decay: float
    crop_schedule: list[Any]      # [fraction of steps, crop side px] pairs
    crops_per_image: int
    keypoint_crop_prob: float
    keypoint_crop_type_weights: list[float]   # endpoint, junction, corner
    init_weights: str | None
    init_reset: list[str]
    train_only: list[str]
    num_workers: Any              # a count, or "auto"
    sigma: float
    loss_weights: list[float]
    fp_weight: float
    junction_loss_weight: float
    class_ce_weight: float
    band_dilation: int
    log_every: int
    checkpoint_every: int
    max_minutes: float | None
    val: ValConfig
    network: NetConfig
    class_branch: ClassBranchConfig
    labels: LabelRules
    generator: GeneratorConfig
    type_classifier: TypeClassifierConfig
    vector: VectorConfig
    vector_prob: float
    vector_crops_per_image: int
