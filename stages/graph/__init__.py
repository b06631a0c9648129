"""Stage ``graph``: the topological graph of the drawing's strokes.

``STAGE_VERSION`` and the config dataclasses. Its code, and the docstring that describes it and its
choices, are in :mod:`stages.graph.stage`; ``run`` and its other public names load from there when
first used (:mod:`stages.lazy`).
"""

from __future__ import annotations

from dataclasses import dataclass

from stages.errors import InputError
from stages.lazy import lazy_names

STAGE_VERSION = "3"  # 3: narrow loop caps closed (ends.close_loop_caps)

__all__ = ["STAGE_VERSION", "GraphConfig", "run", "build_graph", "render_graph"]


@dataclass
class TraceConfig:
    """``graph.trace``: streamline tracing (see :func:`stages.graph.trace.trace_streamlines`)."""

    step: float
    max_half_samples: int
    merge_distance: float
    merge_cos: float
    self_merge_lag: int
    tie: float

    #: The tracing kernel keeps room for the longest curve one seed can add (2 · max_half_samples + 2
    #: samples, 28 bytes each) before each seed; this bound keeps that room under 60 MB.
    MAX_HALF_SAMPLES = 1_000_000

    def __post_init__(self) -> None:
        if not 1 <= self.max_half_samples <= self.MAX_HALF_SAMPLES:
            raise InputError(f"graph.trace.max_half_samples must be in [1, {self.MAX_HALF_SAMPLES}] "
                             f"(samples of {self.step} px), got {self.max_half_samples}")


@dataclass
class SectionConfig:
    """``graph.sections``: cross-sections (see :func:`stages.graph.raw_graph.build_cross_sections`)."""

    station_spacing: float
    cover_factor: float
    min_station_gap: float
    max_gap: float
    max_section_length: float
    ambiguity: float
    lane_pad: float


@dataclass
class CleanupConfig:
    """``graph.cleanup``: see :mod:`stages.graph.cleanup`."""

    merge_distance: float
    merge_min_cos: float
    singular_branches: bool
    min_component_area: float
    max_loop_background: int
    max_cycle_vertices: int
    max_loop_searches: int
    spur_max_length: float
    spur_min_covered: float
    tip_hook_angle: float
    cover_margin: float
    join_singular_distance: float
    join_singular_min_hops: int
    close_caps_widths: float
    close_caps_min_hops: int


@dataclass
class GraphConfig:
    """The ``graph`` config section (``conf/graph/default.yaml``), one field per key."""

    trace: TraceConfig
    sections: SectionConfig
    cleanup: CleanupConfig
    width_smoothing: float
    store_every: int


__getattr__, __dir__ = lazy_names(__name__, {
    "stages.graph.stage": ("run", "build_graph"),
    "stages.graph.graph_picture": ("render_graph",),
})
