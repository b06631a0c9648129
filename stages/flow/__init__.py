"""Stage ``flow``: the PolyVector flow of every candidate path.

``STAGE_VERSION`` and the config dataclasses. Its code, and the docstring that describes it and its
choices, are in :mod:`stages.flow.stage`; ``run`` and its other public names load from there when
first used (:mod:`stages.lazy`).
"""

from __future__ import annotations

from dataclasses import dataclass

from stages.errors import InputError
from stages.lazy import lazy_names

STAGE_VERSION = "3"  # 3: each path prepared on its own arc length (last bits; per-path reuse)


@dataclass
class BarrierConfig:
    """``flow.barrier``: the Eq. 5 barrier round the initial path (σ = width / sigma_scale ≥ sigma_min)."""

    sigma_scale: float
    sigma_min: float
    spacing: float
    cutoff: float


@dataclass
class StepScaleConfig:
    """``flow.step_scale``: per-vertex time-step factor ``clip(d0 / d, min, max)``."""

    d0: float
    min: float
    max: float


@dataclass
class FlowConfig:
    """The ``flow`` config section (``conf/flow/default.yaml``), one field per key."""

    iterations: int
    dt: float
    lam: float
    eps: float
    spacing: float
    max_vertices: int
    resample_factor: float
    barrier: BarrierConfig
    step_scale: StepScaleConfig

    def __post_init__(self) -> None:
        b, s = self.barrier, self.step_scale
        if self.iterations < 0 or self.dt <= 0 or self.lam < 0 or self.eps < 0 or self.spacing <= 0:
            raise InputError("flow config: need iterations ≥ 0, dt > 0, lam ≥ 0, eps ≥ 0, spacing > 0")
        if self.resample_factor <= 1 or b.sigma_scale <= 0 or b.sigma_min <= 0 or b.spacing <= 0:
            raise InputError("flow config: need resample_factor > 1, barrier sigma_scale, sigma_min, spacing > 0")
        if not (0 < s.min <= s.max) or s.d0 <= 0:
            raise InputError("flow config: need 0 < step_scale.min ≤ step_scale.max and d0 > 0")


__getattr__, __dir__ = lazy_names(__name__, {
    "stages.flow.stage": ("run", "plan_items", "run_items", "assemble", "ITEM_INPUTS", "ITEM_NAME", "step_scale",
                          "FlowResult", "polyvector_flow", "path_energy"),
    "stages.flow.kernel": ("bilinear_with_gradient",),
    "stages.flow.paths": ("prepare_paths",),
})
