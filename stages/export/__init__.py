"""Stage ``export``: the chosen curves joined and written as SVG.

``STAGE_VERSION`` and the config dataclasses. Its code, and the docstring that describes it and its
choices, are in :mod:`stages.export.stage`; ``run`` and its other public names load from there when
first used (:mod:`stages.lazy`).
"""

from __future__ import annotations

from dataclasses import dataclass

from stages.errors import InputError
from stages.lazy import lazy_names

STAGE_VERSION = "14"  # 4: no curve shorter than min_length_px; 5: curves joined through sharp corners;
#                     6: curves mapped back from a supersampled prep; 7: gaps in a stroke closed;
#                     8: a gap closes between ends closer than the free radius (only each other near);
#                     9: curves whose ends meet alone joined (export.meetings), passes of the pen
#                        over one line merged into one curve (export.passes);
#                     10: free ends the ink bridges joined at a corner (export.bridges);
#                     11: ... never at an endpoint keypoint; 12: passes and bridges together, no meeting
#                        joined at a keypoint the user edited; 13: a loop's overlapping seam closed
#                        (export.loops); 14: passes that close up into one end merged to that end,
#                        where one goes on past the slack and both stay beside each other to their ends


@dataclass
class CollapseConfig:
    """``export.collapse``: contract links shorter than ~a stroke width between met ends."""

    enabled: bool
    max_px: float
    max_widths: float


@dataclass
class JoinConfig:
    """``export.join``: join curves continuing each other at junctions and synthetic ends."""

    enabled: bool
    max_turn_deg: float
    tangent_px: float
    margin_deg: float
    same_branch_deg: float
    max_ends: int


@dataclass
class SpursConfig:
    """``export.spurs``: attach short junction-to-endpoint curves to the piece they continue."""

    enabled: bool
    max_px: float
    max_widths: float
    max_turn_deg: float
    near_px: float
    by_drawn_valence: bool


@dataclass
class OvershootConfig:
    """``export.overshoot``: extend ends at junctions over an ink overshoot no keypoint marks."""

    enabled: bool
    min_px: float
    min_widths: float
    max_px: float
    clearance: float
    max_widths: float


@dataclass
class CornersConfig:
    """``export.corners``: join the two curves meeting at a sharp-corner keypoint into one."""

    enabled: bool


@dataclass
class GapsConfig:
    """``export.gaps``: join free curve ends facing each other across a small gap (a broken faint stroke)."""

    enabled: bool
    max_px: float
    max_widths: float
    max_turn_deg: float


@dataclass
class PassesConfig:
    """``export.passes``: curves that are passes of the pen over one line merged into one centred curve."""

    enabled: bool
    max_gap_widths: float
    min_run_widths: float
    max_angle_deg: float
    end_slack_widths: float


@dataclass
class MeetingsConfig:
    """``export.meetings``: join the two curves whose ends meet alone (valence two) into one."""

    enabled: bool


@dataclass
class LoopsConfig:
    """``export.loops``: close a loop whose two synthetic ends overlap or cross (its seam)."""

    enabled: bool
    max_tail_px: float
    max_tail_widths: float


@dataclass
class BridgesConfig:
    """``export.bridges``: join two free curve ends the ink bridges (one corner found twice)."""

    enabled: bool
    max_px: float
    max_widths: float
    corners_only: bool


@dataclass
class ExportConfig:
    """The ``export`` config section (``conf/export/default.yaml``), one field per key."""

    stroke_width: float
    widths_from_graph: bool
    precision: int
    bezier: bool
    bezier_tolerance: float
    max_curves: int
    min_length_px: float
    collapse: CollapseConfig
    join: JoinConfig
    spurs: SpursConfig
    overshoot: OvershootConfig
    corners: CornersConfig
    gaps: GapsConfig
    passes: PassesConfig
    meetings: MeetingsConfig
    bridges: BridgesConfig
    loops: LoopsConfig

    def __post_init__(self) -> None:
        if self.stroke_width <= 0 or not 0 <= self.precision <= 8 or self.bezier_tolerance <= 0:
            raise InputError("export config: need stroke_width > 0, 0 ≤ precision ≤ 8, bezier_tolerance > 0")
        if not 0 <= self.join.max_turn_deg <= 180 or self.join.tangent_px <= 0:
            raise InputError("export config: need 0 ≤ join.max_turn_deg ≤ 180 and join.tangent_px > 0")
        if self.gaps.max_px < 0 or self.gaps.max_widths < 0 or not 0 <= self.gaps.max_turn_deg <= 90:
            raise InputError("export config: need gaps.max_px ≥ 0, gaps.max_widths ≥ 0, 0 ≤ gaps.max_turn_deg ≤ 90")
        if self.passes.max_gap_widths < 0 or self.passes.min_run_widths < 0 or not 0 <= self.passes.max_angle_deg <= 90:
            raise InputError("export config: need passes.max_gap_widths ≥ 0, passes.min_run_widths ≥ 0, "
                             "0 ≤ passes.max_angle_deg ≤ 90")
        if self.bridges.max_px < 0 or self.bridges.max_widths < 0:
            raise InputError("export config: need bridges.max_px ≥ 0 and bridges.max_widths ≥ 0")
        if self.loops.max_tail_px < 0 or self.loops.max_tail_widths < 0:
            raise InputError("export config: need loops.max_tail_px ≥ 0 and loops.max_tail_widths ≥ 0")


__getattr__, __dir__ = lazy_names(__name__, {
    "stages.export.stage": ("run", "svg_document"),
    "stages.export.bezier": ("fit_cubic_beziers", "fit_with_corners"),
    "stages.export.corners": ("join_at_corners", "join_linked"),
    "stages.export.gaps": ("close_gaps", "join_bridged_ends", "join_lone_meetings"),
    "stages.export.passes": ("merge_passes",),
    "stages.export.loops": ("close_loops",),
    "stages.export.joins": ("collapse_short_links", "join_continuations"),
    "stages.export.spurs": ("attach_spurs",),
    "stages.export.overshoots": ("extend_overshoots",),
})
