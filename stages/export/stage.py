"""SVG (and curves JSON) of the selected flowed curves.

Coordinates are pixel units with x right, y down and the origin at the top-left *corner* of the image
(stages/INTERFACES.md), which is exactly SVG user space with ``viewBox="0 0 W H"``: the curves are
written as they are, with no half-pixel shift (the authors add +0.5 because their points are pixel
indices; ours are already corner-origin).

Output (data of the artifact; the engine writes the files):

* ``svg`` — one ``<path>`` per selected curve (polyline ``M … L …``), black stroke, no fill; stroke
  width ``stroke_width`` px, or each curve's mean stroke width from the graph (topology path
  ``widths``) when ``widths_from_graph`` is set;
* ``curves`` — ``{"id", "points", "end_types", "end_keypoints", "parts", "width", "corners"}`` per curve, in
  selection order (joined curves last);
* ``bezier_svg`` (when ``bezier``) — the same curves as piecewise cubic Béziers fitted within
  ``bezier_tolerance`` px (Schneider's algorithm, Graphics Gems 1990: chord-length parameters,
  least-squares control points for fixed end tangents, Newton re-parametrisation, split at the point
  of largest error).  The fit keeps the curve's ends exactly, and its pieces join with a common
  tangent, except at the curve's ``corners`` (fitted piece by piece between them).

The authors export raw polylines only (no Bézier fitting); this is an addition.

Ten clean-ups of the selected curves, each a choice beyond the paper (the authors export the
selection as it is); measurements in stages/DECISIONS.md.  Valences, and with them the junctions, are
unchanged by the first four (a curve passing a point counts twice, like two ends).

* **Joining continuations** (``join``).  The selection returns curves that end at every key vertex
  they meet, so a stroke crossing another or running on past a junction keypoint comes out as two
  curves meeting end to end: a split the drawing does not have.  At every junction keypoint and
  synthetic end (never at an endpoint or a sharp corner) the two curve ends whose directions
  continue each other best — turn below ``join.max_turn_deg`` over ``join.tangent_px`` of arc, every
  other end there turning off both by ``join.margin_deg`` more (a Y's stem continues neither branch)
  — are joined into one curve, repeatedly.  The authors glued such chains in their topology
  (``advancedGlueAllJunction``); we join the flowed curves.  Joined curves list their ``parts``
  (selected path ids) and keep the first part's ``id``.
* **Spurs** (``spurs``).  A stroke overshooting a crossing leaves a short curve from the junction to
  its tip beside the curve it continues, a dangling branch where the drawing has one stroke.  A curve
  no longer than ``max(spurs.max_px, spurs.max_widths · width)`` from a junction keypoint to an
  endpoint keypoint is joined to the piece at that junction that continues it best — another curve
  ending there, or one half of a curve passing within ``spurs.near_px`` (split there) — when the turn
  is at most ``spurs.max_turn_deg``.  With ``spurs.by_drawn_valence`` corner and junction keypoint
  ends count as drawn (a corner where ≥ 3 curve ends meet is a junction; a keypoint only this curve
  reaches is a free end), as the valence topology of the evaluation reads them.
* **Links below the drawing's resolution** (``collapse``).  One feature found twice a few pixels
  apart (a corner at the bottom of a vee, a corner next to a junction) gives a tiny curve between the
  two keypoints, which adds two ends where the drawing has one point.  A curve no longer than
  ``max(collapse.max_px, collapse.max_widths · width)`` (one stroke width: the drawing cannot
  resolve it) whose two ends both meet longer curves is contracted to its midpoint, as an edge in a
  graph (:func:`collapse_short_links`), before the joins, which then see one meeting point.
* **Overshoots** (``overshoot``).  When no keypoint marks the tip of an overshoot the topology ends
  the stroke at the junction and the ink beyond is lost.  A curve end at a junction or synthetic end
  is extended straight on to where the ink (prep ``mask``) stops, less half the stroke width (a
  centre line ends half a width inside its ink), when that is between ``max(min_px, min_widths·w)``
  and ``max(max_px, max_widths·w)`` and the new tip keeps ``clearance`` × its length from every other
  curve (:func:`extend_overshoots`; a plain T gives ≈ 0, a Y's gap fails the clearance).

* **Strokes through their corners** (``corners``).  Last, the two curves that meet at a sharp-corner
  keypoint (exactly two ends there) become one curve with a corner vertex (``corners`` in the curves
  JSON; the Bézier fit keeps it sharp), as an artist draws a zigzag: one path, not a path per leg.
  Why: a stroke crossing itself is then one curve, not two curves crossing — a junction the
  drawing does not have (:func:`join_at_corners`).

* **Passes of one line** (``passes``).  After the corner joins, a line drawn two or three times or
  doubled back comes out as side-by-side curves (or one curve folded on itself) where a person sees
  one line: pieces running near-parallel within ``passes.max_gap_widths`` widths over
  ``passes.min_run_widths`` widths become one centred curve (:func:`~stages.export.passes.merge_passes`).

* **A loop's seam** (``loops``).  A closed stroke with no keypoint on it is cut at a synthetic vertex,
  and the flow moves its two ends past each other: a tick on a smooth stretch, two free ends where the
  drawing has none.  A curve whose ends are both synthetic and whose first and last
  ``max(loops.max_tail_px, loops.max_tail_widths · w)`` of arc come within max(2 px, w) is cut at that
  closest pair and closed (:func:`~stages.export.loops.close_loops`).

* **Gaps in a stroke** (``gaps``).  Then a faint or grainy stroke whose ink breaks comes out
  as curves end to end, each with two free ends where the drawing has one stroke.  Two free ends (no
  other curve within max(2 px, w), or only the other's tip) of different curves at most
  ``max(gaps.max_px, gaps.max_widths · w)`` apart, each pointing at the other within
  ``gaps.max_turn_deg``, are joined across the gap, nearest first (:func:`~stages.export.gaps.close_gaps`).

* **A corner found twice** (``bridges``).  Then two free ends of different curves, each the other's
  nearest, at most ``max(bridges.max_px, bridges.max_widths · w)`` apart, one at a corner keypoint
  and neither at an endpoint keypoint (``bridges.corners_only``), that the ink connects between them
  (the band ``mask`` within their box) are one stroke turning where the detector put two corner
  keypoints beyond its suppression distance: joined at any turn, the joint a corner
  (:func:`~stages.export.gaps.join_bridged_ends`).

* **Ends that meet alone** (``meetings``).  After everything else, two curve ends of different curves
  that meet with nothing else near (each the other's only neighbour within max(2 px, w): valence two)
  are one stroke going on, whatever the turn, and are joined (:func:`~stages.export.gaps.join_lone_meetings`);
  a stroke crossing or touching itself later is then one curve meeting itself, not a junction.

Duplicated pieces (two curves converging on one centre line near a false junction) are left alone:
cutting them moves the false junction to where the curves part, which the ground truth rarely marks.
"""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

import numpy as np

from stages.artifact import Artifact, unpack_ragged
from stages.config import from_section
from stages.errors import InputError
from stages.export import ExportConfig
from stages.export.bezier import fit_with_corners
from stages.export.corners import join_at_corners
from stages.export.gaps import close_gaps, ends_at_keypoints, join_bridged_ends, join_lone_meetings
from stages.export.joins import collapse_short_links, join_continuations
from stages.export.loops import close_loops
from stages.export.overshoots import extend_overshoots
from stages.export.passes import merge_passes
from stages.export.spurs import attach_spurs
from stages.geometry import polyline_length
from stages.prep import internal_is_source, internal_scale, to_source


# ---------------------------------------------------------------------------------------------
# SVG
# ---------------------------------------------------------------------------------------------

def _fmt(v: float, precision: int) -> str:
    s = f"{v:.{precision}f}"
    if "." in s:
        s = s.rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _fmt_many(values: np.ndarray, precision: int) -> list[str]:
    """:func:`_fmt` of many numbers (rounded once with numpy, then one format call per number)."""
    v = np.round(np.asarray(values, np.float64), precision) + 0.0          # + 0.0: no "-0"
    return [_fmt(x, precision) for x in v.tolist()] if precision else [str(int(x)) for x in v.tolist()]


def _polyline_d(points: np.ndarray, precision: int) -> str:
    pts = np.asarray(points, np.float64)
    xs, ys = _fmt_many(pts[:, 0], precision), _fmt_many(pts[:, 1], precision)
    coords = [f"{x} {y}" for x, y in zip(xs, ys)]
    return "M " + coords[0] + "".join(" L " + c for c in coords[1:])


def _bezier_d(pieces: list[np.ndarray], precision: int) -> str:
    f = lambda p: f"{_fmt(p[0], precision)} {_fmt(p[1], precision)}"  # noqa: E731
    return "M " + f(pieces[0][0]) + "".join(" C " + " ".join(f(q) for q in c[1:]) for c in pieces)


def svg_document(width: int, height: int, curves: list[dict], ds: list[str], params: ExportConfig) -> str:
    """An SVG document with one black, unfilled ``<path>`` per curve.

    Parameters
    ----------
    width, height : int
        Image size in pixels (also the viewBox).
    curves : list of dict
        With ``id`` and ``width`` (used when ``widths_from_graph``).
    ds : list of str
        Path data per curve.
    params : ExportConfig
    """
    lines = ['<?xml version="1.0" encoding="UTF-8" standalone="no"?>',
             f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" width="{width}" height="{height}" '
             f'viewBox="0 0 {width} {height}">',
             f'  <g fill="none" stroke="#000000" stroke-width="{_fmt(params.stroke_width, 3)}" '
             'stroke-linecap="round" stroke-linejoin="round">']
    for c, d in zip(curves, ds):
        extra = ""
        if params.widths_from_graph and c.get("width"):
            extra = f' stroke-width="{_fmt(c["width"], 3)}"'
        lines.append(f'    <path id={quoteattr("curve-" + str(c["id"]))}{extra} d="{d}"/>')
    lines += ["  </g>", "</svg>", ""]
    return "\n".join(lines)


def run(cfg: dict, **inputs: Artifact) -> Artifact:
    """Stage entry: SVG and curves of the selected flowed paths.

    Parameters
    ----------
    cfg : dict
        The ``export`` config section.
    prep, topology, flow, select : Artifact
        Image size (``prep`` data ``height``/``width`` or its ``grey``) and internal ``scale``
        (supersampled thin strokes: curves are divided by it), candidate paths (end types, widths),
        flowed curves (topology order) and the chosen path ids.

    Returns
    -------
    Artifact
        data ``svg``, ``curves`` and (optional) ``bezier_svg``.
    """
    params = from_section(ExportConfig, cfg, "export")
    for name in ("prep", "topology", "flow", "select"):
        if name not in inputs:
            raise InputError(f"export stage needs the '{name}' artifact")
    prep, topo, fl, sel = (inputs[k] for k in ("prep", "topology", "flow", "select"))
    if "height" in prep.data and "width" in prep.data:
        height, width = int(prep.data["height"]), int(prep.data["width"])
    elif "grey" in prep.arrays:
        height, width = prep.arrays["grey"].shape
    else:
        raise InputError("export: the prep artifact gives no image size")
    paths = topo.data.get("paths", [])
    curves_xy = unpack_ragged(np.asarray(fl["curve_xy"]).reshape(-1, 2), np.asarray(fl["curve_xy_offsets"]))
    if len(curves_xy) != len(paths):
        raise InputError(f"export: {len(paths)} topology paths but {len(curves_xy)} flowed curves")
    index = {int(p["id"]): k for k, p in enumerate(paths)}
    curves, ds, bds = [], [], []
    for cid in sel.data.get("chosen", []):
        if int(cid) not in index:
            raise InputError(f"export: chosen path {cid} is not a topology path")
        k = index[int(cid)]
        pts = np.asarray(curves_xy[k], np.float64)
        if len(pts) < 2 or not np.all(np.isfinite(pts)):
            continue
        w = paths[k].get("widths") or []
        curves.append({"id": int(cid), "points": pts, "parts": [int(cid)],
                       "end_types": [int(t) for t in paths[k].get("end_types", [0, 0])],
                       "end_keypoints": [int(t) for t in paths[k].get("end_keypoints", [-1, -1])],
                       "width": float(np.mean(w)) if len(w) else None})
    notes = []
    tidy = len(curves) <= params.max_curves
    if not tidy:
        # A guard, not a choice: the edits below are near-linear, but a drawing with more curves than
        # this is not a line drawing we can tidy in bounded time; its curves are written as selected.
        notes.append(f"{len(curves)} curves, more than export.max_curves ({params.max_curves}): written as "
                     "selected, without link contraction, joins, spurs or overshoot extension")
    if tidy and params.collapse.enabled:
        curves = collapse_short_links(curves, params.collapse.max_px, params.collapse.max_widths)
    if tidy and params.join.enabled:
        crowded: set = set()
        curves = join_continuations(curves, params.join.max_turn_deg, params.join.tangent_px,
                                    params.join.margin_deg, params.join.same_branch_deg, params.join.max_ends,
                                    crowded)
        if crowded:
            notes.append(f"{len(crowded)} joints where more than export.join.max_ends ({params.join.max_ends}) "
                         "curve ends meet: no curves joined there")
    if tidy and params.spurs.enabled:
        curves = attach_spurs(curves, params.spurs.max_px, params.spurs.max_widths, params.spurs.max_turn_deg,
                              params.join.tangent_px, params.spurs.near_px, params.spurs.by_drawn_valence)
    mask = prep.arrays.get("mask")
    if tidy and params.overshoot.enabled and mask is not None:
        curves = extend_overshoots(curves, np.asarray(mask, bool), params.join.tangent_px, params.overshoot.min_px,
                                   params.overshoot.min_widths, params.overshoot.max_px,
                                   params.overshoot.max_widths, params.overshoot.clearance)
    if tidy and params.corners.enabled:
        curves = join_at_corners(curves)
    # Keypoints the user added or retyped: the curves ending there are neither merged nor joined away.
    edited = frozenset(topo.data.get("edited_keypoints") or ())
    if tidy and params.passes.enabled:
        held = [c for c in curves if ends_at_keypoints(c, edited)]
        curves = merge_passes([c for c in curves if not ends_at_keypoints(c, edited)], params.passes.max_gap_widths,
                              params.passes.min_run_widths, params.passes.max_angle_deg,
                              params.passes.end_slack_widths) + held
    if tidy and params.loops.enabled:
        curves = close_loops(curves, params.loops.max_tail_px, params.loops.max_tail_widths)
    if tidy and params.gaps.enabled:
        curves = close_gaps(curves, params.gaps.max_px, params.gaps.max_widths, params.gaps.max_turn_deg,
                            params.join.tangent_px, edited)
    if tidy and params.bridges.enabled and mask is not None:
        # Keypoint types (end_types codes): 0 none, 1 endpoint, 3 junction, 5 corner.
        if params.bridges.corners_only:
            at_one, at_other = (5,), (0, 3, 5)     # a corner found twice; never across an endpoint keypoint
        else:
            at_one = at_other = (0, 1, 3, 5)
        curves = join_bridged_ends(curves, np.asarray(mask, bool), params.bridges.max_px, params.bridges.max_widths,
                                   at_one, at_other, edited)
    if tidy and params.meetings.enabled:
        curves = join_lone_meetings(curves, edited)
    if not internal_is_source(prep.data):
        # prep supersampled thin or downsampled wide strokes, or cropped the drawing out of its page:
        # every stage so far worked at internal x = scale · (source x − origin), the pixel corners
        # aligned; the SVG is the source's.
        scale = internal_scale(prep.data)
        curves = [dict(c, points=to_source(c["points"], prep.data),
                       width=None if c.get("width") is None else float(c["width"]) / scale) for c in curves]
    # A curve shorter than a pixel draws nothing an artist can edit (a selected path that flowed onto
    # one point: `M x y L x y`), and has no tangent for the Bézier fit.
    curves = [dict(c, corners=list(c.get("corners", []))) for c in curves
              if polyline_length(c["points"]) >= params.min_length_px]
    for c in curves:
        pts = np.asarray(c["points"], np.float64)
        c["points"] = pts.tolist()
        ds.append(_polyline_d(pts, params.precision))
        if params.bezier:
            bds.append(_bezier_d(fit_with_corners(pts, c["corners"], params.bezier_tolerance), params.precision))
    data = {"svg": svg_document(width, height, curves, ds, params), "curves": curves}
    if params.bezier:
        data["bezier_svg"] = svg_document(width, height, curves, bds, params)
    return Artifact(data=data, notes=notes)
