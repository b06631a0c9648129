"""Stage ``field``: the PolyVector frame field of the narrow band.

``STAGE_VERSION`` and the config dataclass. Its code, and the docstring that describes it and its
choices, are in :mod:`stages.field.stage`; ``run`` and its other public names load from there when
first used (:mod:`stages.lazy`).
"""

from __future__ import annotations

from dataclasses import dataclass

from stages.lazy import lazy_names

STAGE_VERSION = "5"  # 2: the solve in real form; 3: the extension moved to its own stage, smart weights kept;
#                    4: a mosaic's pieces (prep) get their tangents and coherence weights each on its own;
#                    5: solves by blocks of band components (a band over 2¹⁶ pixels moves within cg_rtol)

__all__ = [
    "FieldConfig", "STAGE_VERSION", "run", "compute_field", "image_tangents", "coherence_weights",
    "smart_weights", "polyvector_roots", "root_matching", "singular_cells", "singular_pixels",
    "render_field",
]


@dataclass
class FieldConfig:
    """The ``field`` config section (``conf/field/default.yaml``), one field per key."""

    alpha: float
    beta: float
    gradient_cutoff: float
    cg_rtol: float
    cg_max_iterations: int
    warm_start: bool
    max_singularity_iterations: int
    tie_tolerance: float
    tie_sigma: float


__getattr__, __dir__ = lazy_names(__name__, {
    "stages.field.stage": ("run", "compute_field"),
    "stages.field.data_terms": ("image_tangents", "coherence_weights", "smart_weights"),
    "stages.field.roots": ("polyvector_roots", "root_matching", "singular_cells", "singular_pixels"),
    "stages.field.field_picture": ("render_field",),
})
