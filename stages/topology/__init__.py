"""Stage ``topology``: key vertices and candidate paths.

``STAGE_VERSION`` and the config dataclass (``conf/topology/default.yaml`` one to one). Its code,
and the docstring that describes it and its choices, are in :mod:`stages.topology.stage`; ``run``
and its other public names load from there when first used (:mod:`stages.lazy`).
"""

from __future__ import annotations

from dataclasses import dataclass

from stages.errors import InputError
from stages.lazy import lazy_names

STAGE_VERSION = "6"  # 5: a subgraph chain no kept candidate covers is offered as a candidate;
#                    6: the keypoints the user edited listed (edited_keypoints)

__all__ = ["STAGE_VERSION", "run", "render_topology", "TopologyConfig", "candidate_paths"]


@dataclass
class TopologyConfig:
    """See ``conf/topology/default.yaml`` for the meaning and origin of every value."""

    keypoint_radius_px: float
    merge_graph_dist_px: float
    keypoint_min_depth: float
    steiner_method: str
    coverage_margin_px: float
    min_new_vertices: int
    min_new_pixels: int
    robust_far_px: float
    robust_min_new_vertices: int
    robust_min_new_pixels: int
    turn_probe_px: float
    turn_min_cos: float
    turn_probe_max_px: float
    junction_zone_px: float
    pass_through_junctions: bool
    pass_through_endpoints: bool
    pass_through_probe_px: float
    pass_through_max_turn_deg: float
    pass_through_margin_deg: float
    max_pass_through: int
    max_paths_per_pair: int
    max_enumeration_steps: int
    min_component_vertices: int

    def __post_init__(self) -> None:
        if self.steiner_method not in ("mehlhorn", "kou"):
            raise InputError(f"topology config: steiner_method must be 'mehlhorn' or 'kou', not {self.steiner_method!r}")
        if self.min_new_vertices < 1 or self.robust_min_new_vertices < 1:
            raise InputError("topology config: min_new_vertices and robust_min_new_vertices must be ≥ 1")


__getattr__, __dir__ = lazy_names(__name__, {
    "stages.topology.stage": ("run",),
    "stages.topology.candidates": ("candidate_paths",),
    "stages.topology.topology_picture": ("render_topology",),
})
