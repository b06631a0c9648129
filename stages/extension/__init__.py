"""Stage ``extension``: the PolyVector field extended beyond the narrow band, for the flow.

``STAGE_VERSION`` and the config dataclass. Its code, and the docstring that describes it and its
choices, are in :mod:`stages.extension.stage`; ``run`` and its other public names load from there when
first used (:mod:`stages.lazy`).
"""

from __future__ import annotations

from dataclasses import dataclass

from stages.errors import InputError
from stages.lazy import lazy_names

STAGE_VERSION = "2"  # 2: the ring solved by blocks of components (a ring over 2¹⁶ pixels moves within cg_rtol)

__all__ = ["ExtensionConfig", "STAGE_VERSION", "run", "extend_field"]


@dataclass
class ExtensionConfig:
    """The ``extension`` config section (``conf/extension/default.yaml``), one field per key."""

    radius: int
    scale: float
    cg_rtol: float
    cg_max_iterations: int

    def __post_init__(self) -> None:
        if self.radius < 0 or self.scale < 0 or self.cg_rtol <= 0 or self.cg_max_iterations < 1:
            raise InputError("extension config: need radius ≥ 0, scale ≥ 0, cg_rtol > 0, cg_max_iterations ≥ 1")


__getattr__, __dir__ = lazy_names(__name__, {"stages.extension.stage": ("run", "extend_field")})
