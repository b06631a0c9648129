"""Stage ``select``: the binary program that chooses the final curves.

``STAGE_VERSION`` and the config dataclasses. Its code, and the docstring that describes it and its
choices, are in :mod:`stages.select.stage`; ``run`` and its other public names load from there when
first used (:mod:`stages.lazy`).
"""

from __future__ import annotations

from dataclasses import dataclass

from stages.errors import InputError
from stages.lazy import lazy_names

STAGE_VERSION = "1"

#: Keypoint type codes (stages/INTERFACES.md) → config key of their required valence.
_TYPE_NAMES = {1: "endpoint", 5: "corner", 3: "junction"}


@dataclass
class ValenceConfig:
    """``select.valence``: required valence per keypoint type (paper §4.3: ≥ 1 / 2 / 3)."""

    endpoint: int
    corner: int
    junction: int


@dataclass
class MaxEndsConfig:
    """``select.max_ends``: soft upper bound on the curve ends at a keypoint of each type (None = none)."""

    endpoint: int | None
    corner: int | None
    junction: int | None


@dataclass
class SelectConfig:
    """The ``select`` config section (``conf/select/default.yaml``), one field per key."""

    time_limit: float
    threads: int
    gap_rel: float
    cap_valence: bool
    cap_branches: bool
    valence: ValenceConfig
    max_ends: MaxEndsConfig
    excess_penalty: float
    curve_cost: float

    def __post_init__(self) -> None:
        if self.time_limit <= 0 or self.threads < 1 or self.gap_rel < 0 or self.excess_penalty < 0 or self.curve_cost < 0:
            raise InputError("select config: need time_limit > 0, threads ≥ 1, gap_rel ≥ 0, excess_penalty ≥ 0, "
                             "curve_cost ≥ 0")

    def valence_by_type(self) -> dict[int, int]:
        """Required valence by keypoint type code."""
        return {t: getattr(self.valence, name) for t, name in _TYPE_NAMES.items()}

    def max_ends_by_type(self) -> dict[int, int]:
        """Upper bound on curve ends by keypoint type code, for the types that have one."""
        return {t: getattr(self.max_ends, name) for t, name in _TYPE_NAMES.items()
                if getattr(self.max_ends, name) is not None}


__getattr__, __dir__ = lazy_names(__name__, {
    "stages.select.stage": ("run", "SelectionProblem", "build_problem", "satisfies", "greedy_selection", "solve_mip",
                            "select_paths"),
})
