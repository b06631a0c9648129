"""SVG (and curves JSON) of the selected flowed curves.

Coordinates are pixel units with x right, y down and the origin at the top-left *corner* of the image
(stages/INTERFACES.md), which is exactly SVG user space with ``viewBox="0 0 W H"``: the curves are
written as they are, with no half-pixel shift (the authors add +0.5 because their points are pixel
indices; ours are already corner-origin).

Output (data of the artifact; the engine writes the files):

* ``svg`` — one ``<path>`` per selected curve (polyline ``M … L …``), black stroke, no fill; stroke
  width ``stroke_width`` px, or each curve's mean stroke width from the graph (topology path
  ``widths``) when ``widths_from_graph`` is set;
* ``curves`` — ``{"id", "points", "end_types", "end_keypoints", "parts", "width"}`` per curve, in
  selection order (joined curves last);
* ``bezier_svg`` (when ``bezier``) — the same curves as piecewise cubic Béziers fitted within
  ``bezier_tolerance`` px (Schneider's algorithm, Graphics Gems 1990: chord-length parameters,
  least-squares control points for fixed end tangents, Newton re-parametrisation, split at the point
  of largest error).  The fit keeps the curve's ends exactly, and its pieces join with a common
  tangent (only keypoints are corners, and they are the curves' ends).

The authors export raw polylines only (no Bézier fitting); this is an addition.

Joining continuations (``join.enabled``; a choice beyond the paper).  The selection returns curves
that end at every key vertex they meet, so a stroke crossing another one, or running on past a
junction keypoint, often comes out as two curves meeting there end to end — and a stroke that
overshoots a crossing by a few pixels leaves a short curve from the junction to its end (a "dangling
branch" in the topology metrics, 0.68 per drawing on realvec_dev with ground-truth keypoints, against
0.11 in the ground truth).  The authors' topology glued such chains at unexpected ends
(``advancedGlueAllJunction``); we join the flowed curves instead: at every junction keypoint and
synthetic end (never at an endpoint or a sharp corner), the two curve ends whose directions continue
each other best — turn below ``join.max_turn_deg``, directions taken over ``join.tangent_px`` of arc,
and every other end there turning off both by ``join.margin_deg`` more (a Y's stem continues neither
branch) — are joined into one curve, repeatedly.  Valences, and with them the junctions, are unchanged (a
curve passing a point counts twice, like two ends); only the split disappears.  Joined curves list
their ``parts`` (selected path ids) and keep the first part's ``id``.

Spurs (``spurs.enabled``; a choice beyond the paper).  realvec_dev labels the tip of a stroke that
overshoots a crossing as an endpoint, and the selection then returns a short curve from the junction
to that tip next to the curve it continues: a "dangling branch" (the ground-truth stroke is one
long curve).  A curve no longer than ``max(spurs.max_px, spurs.max_widths · width)`` from a junction
keypoint to an endpoint keypoint is joined to the piece at that junction that continues it best —
another curve ending there, or one half of a curve passing within ``spurs.near_px`` (which is
split there) — when the turn is at most ``spurs.max_turn_deg``.  The drawn points and the
valences are unchanged.  With ``max_turn_deg`` 60° → 75° dangling fell from 0.35 to 0.30 per
drawing (realvec_dev, GT keypoints) and junction F1 stayed 0.831.

Spur ends by their drawn valence (``spurs.by_drawn_valence``).  The spur rule reads "junction" and
"free end" off the keypoint types, but a corner keypoint where three or more curve ends meet is drawn
as a junction, and a corner or junction keypoint that only one curve reaches (nothing else ends or
passes there) is drawn as a free end — which is also how the valence topology of the evaluation
reads them.  With the option, such ends count as what is drawn: a short curve from a corner with
≥ 3 ends to an endpoint, or from a junction to a corner nobody else reaches, is a spur too.
realvec_dev, detector keypoints: dangling 27 → 20 in 106 drawings (0.25 → 0.19 per drawing); every
other metric unchanged but in one tangled blob (qd_panda_02_clean, junction F1 0.68 → 0.67) and
one F1@2 (−0.001).  Ground-truth keypoints (with the link contraction below): dangling 0.35 → 0.21
per drawing, medians unchanged, junction F1 mean 0.8213 → 0.8181 (qd_whale_01_pencil 1.0 → 0.67:
the tail's junction is read as a continuation after the split).

Links below the drawing's resolution (``collapse.enabled``; a choice beyond the paper).  When one
feature gets two keypoints a few pixels apart (a corner found twice at the bottom of a vee, a corner
next to a junction), the selection draws a tiny curve between them and the other curves end at
either keypoint; at the scale of the stroke width all those ends meet at one point, where the link
adds two more ends (two corner arms + the link read as a junction).  A curve no longer than
``max(collapse.max_px, collapse.max_widths · width)`` (one stroke width: the drawing cannot resolve
it) whose two ends both meet longer curves is contracted to its midpoint, as an edge is contracted
in a graph: it is removed and the ends that met it move to the midpoint (≤ half its length; see
:func:`collapse_short_links`).  It runs before the joins, which then see one meeting point.
realvec_dev with spurs by drawn valence on: detector keypoints junction F1 mean 0.6935 → 0.6962
(median 0.703 → 0.708), dangling 20 → 20 per 106, one Hausdorff 3.0 → 3.16 px; GT keypoints
Hausdorff and F1@2 unchanged, junction F1 mean 0.8185 → 0.8181.  Tried: links up to 1.5 widths
(detector junction mean 0.6968, but with GT keypoints — resolvable pairs of real keypoints — one
Hausdorff 3.0 → 3.6 px moved the median 3.08 → 3.16 and junction F1 mean fell 0.8213 → 0.8147);
contracting after the joins (mean 0.6948); joining the link onto the neighbour that continues it
instead of moving ends (mean 0.6950, one more dangling branch: the other ends stay a link's length
away and still meet as a junction).

Duplicated pieces were measured and left alone.  About 90 of the ~125 false junctions where three
or more curve ends meet (detector keypoints) have two of those ends running along the same stroke
for ≥ 2 stroke widths (within 0.75 px: flowed paths that took different graph routes through one
band converge on one centre line; the selection keeps both because their *unflowed* routes cover
different pixels).  Cutting the shared end run off the shorter curve (or dropping curves lying
wholly within 0.75 px of others) halves the duplicated length (median 49.6 → 7 px) but moves the
false junction to where the two curves part, which the ground truth rarely marks (junction FPs with
nothing in the ground truth 122 → 193): junction F1 mean +0.001 (median +0.02), endpoint F1 mean
−0.006, dangling +3, F1@2 of 60 drawings slightly lower; a band-width tolerance (0.5 w) cut the
second of two touching parallel strokes.  Only 1 of the 13 false crossings is two duplicates
crossing at a shallow angle.  In the selection, coverage from the flowed curves instead of the
topology paths was much worse (more curves, duplicated median 420 px), and ``cap_branches`` raised
the Hausdorff median 3.16 → 3.38 px.

Overshoots (``overshoot.enabled``; a choice beyond the paper).  When no keypoint marks the tip of an
overshoot, the topology ends the stroke at the junction and the few pixels of ink beyond are lost;
on realvec_dev that tip was the largest Hausdorff error in about a quarter of the drawings.  A curve
end at a junction or synthetic end is extended straight on to where the ink (prep ``mask``) stops,
less half the stroke width (a stroke's centre line ends half a width inside its ink), when that is
between ``max(min_px, min_widths·w)`` and ``max(max_px, max_widths·w)`` and the new tip keeps
``clearance`` × its length from every other curve (see :func:`extend_overshoots`; a plain T gives
≈ 0, a Y's gap fails the clearance).  realvec_dev with GT keypoints, spurs and overshoots together:
Hausdorff median 3.38 → 3.08 px (min 2 px / 1 width: 3.16), dangling 0.50 → 0.31 per drawing,
endpoint F1 0.909 (unchanged median, mean 0.858 → 0.864), junction F1 0.831 (unchanged).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from xml.sax.saxutils import quoteattr

import numpy as np

from stages.artifact import Artifact, unpack_ragged
from stages.errors import InputError

STAGE_VERSION = "4"  # 4: no curve shorter than min_length_px


@dataclass(frozen=True)
class ExportParams:
    """The ``export`` config section (``conf/export/default.yaml``)."""

    stroke_width: float
    widths_from_graph: bool
    precision: int
    bezier: bool
    bezier_tolerance: float
    min_length_px: float
    join: bool
    join_max_turn_deg: float
    join_tangent_px: float
    join_margin_deg: float
    join_same_branch_deg: float
    join_max_ends: int
    spurs: bool
    spur_max_px: float
    spur_max_widths: float
    spur_max_turn_deg: float
    spur_near_px: float
    spur_by_valence: bool
    overshoot: bool
    overshoot_min_px: float
    overshoot_min_widths: float
    overshoot_max_px: float
    overshoot_max_widths: float
    overshoot_clearance: float
    collapse: bool
    collapse_max_px: float
    collapse_max_widths: float
    max_curves: int

    @classmethod
    def from_cfg(cls, cfg: dict) -> "ExportParams":
        """Build from the config dict; every key must be present."""
        try:
            p = cls(stroke_width=float(cfg["stroke_width"]), widths_from_graph=bool(cfg["widths_from_graph"]),
                    precision=int(cfg["precision"]), bezier=_flag(cfg["bezier"], "export.bezier"),
                    bezier_tolerance=float(cfg["bezier_tolerance"]),
                    min_length_px=float(cfg["min_length_px"]), join=bool(cfg["join"]["enabled"]),
                    join_max_turn_deg=float(cfg["join"]["max_turn_deg"]),
                    join_tangent_px=float(cfg["join"]["tangent_px"]),
                    join_margin_deg=float(cfg["join"]["margin_deg"]),
                    join_same_branch_deg=float(cfg["join"]["same_branch_deg"]),
                    join_max_ends=int(cfg["join"]["max_ends"]),
                    spurs=bool(cfg["spurs"]["enabled"]), spur_max_px=float(cfg["spurs"]["max_px"]),
                    spur_max_widths=float(cfg["spurs"]["max_widths"]),
                    spur_max_turn_deg=float(cfg["spurs"]["max_turn_deg"]),
                    spur_near_px=float(cfg["spurs"]["near_px"]),
                    spur_by_valence=bool(cfg["spurs"]["by_drawn_valence"]),
                    overshoot=bool(cfg["overshoot"]["enabled"]),
                    overshoot_min_px=float(cfg["overshoot"]["min_px"]),
                    overshoot_min_widths=float(cfg["overshoot"]["min_widths"]),
                    overshoot_max_px=float(cfg["overshoot"]["max_px"]),
                    overshoot_max_widths=float(cfg["overshoot"]["max_widths"]),
                    overshoot_clearance=float(cfg["overshoot"]["clearance"]),
                    collapse=bool(cfg["collapse"]["enabled"]),
                    collapse_max_px=float(cfg["collapse"]["max_px"]),
                    collapse_max_widths=float(cfg["collapse"]["max_widths"]),
                    max_curves=int(cfg["max_curves"]))
        except KeyError as e:
            raise InputError(f"export config is missing key {e}") from None
        if p.stroke_width <= 0 or not 0 <= p.precision <= 8 or p.bezier_tolerance <= 0:
            raise InputError("export config: need stroke_width > 0, 0 ≤ precision ≤ 8, bezier_tolerance > 0")
        if not 0 <= p.join_max_turn_deg <= 180 or p.join_tangent_px <= 0:
            raise InputError("export config: need 0 ≤ join.max_turn_deg ≤ 180 and join.tangent_px > 0")
        return p


def _flag(value, name: str) -> bool:
    """A true/false config value; anything else (``export.bezier.enabled``, the old spelling) is an error."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    raise InputError(f"{name} must be true or false (got {value!r}; write {name}=true)")


# ---------------------------------------------------------------------------------------------
# Joining continuations at junctions and synthetic ends
# ---------------------------------------------------------------------------------------------

JOINABLE_TYPES = (0, 3)      # synthetic ends and junctions; never endpoints (1) or sharp corners (5)


def end_direction(points: np.ndarray, at_start: bool, arc_px: float) -> np.ndarray:
    """Unit direction pointing *out of* a curve end: from the point ``arc_px`` along it to the end."""
    pts = np.asarray(points, np.float64)
    if not at_start:
        pts = pts[::-1]
    s = np.r_[0, np.cumsum(np.hypot(*np.diff(pts, axis=0).T))]
    if s[-1] <= 1e-12:
        return np.zeros(2)
    target = min(arc_px, 0.5 * s[-1])
    q = np.array([np.interp(target, s, pts[:, 0]), np.interp(target, s, pts[:, 1])])
    return _unit(pts[0] - q)


def join_continuations(curves: list[dict], max_turn_deg: float, tangent_px: float,
                       margin_deg: float = 0.0, same_branch_deg: float = 0.0, max_ends: int | None = None,
                       crowded: set | None = None) -> list[dict]:
    """Join curves that continue each other through a junction keypoint or a synthetic end.

    Parameters
    ----------
    curves : list of dict
        ``points`` (n, 2), ``end_types``, ``end_keypoints`` and ``parts`` per curve.
    max_turn_deg : float
        Largest turn (angle between one end's outward direction and the other's inward one).
    tangent_px : float
        Arc length over which end directions are measured.
    margin_deg : float
        Every other end at the joint must turn off both by at least this much more than they turn
        into each other (a Y's stem continues neither branch).
    same_branch_deg : float
        Other ends leaving within this angle of one of the two run along the same branch (overlapping
        curves) and do not count as other branches.
    max_ends : int, optional
        Guard: no join at a joint where more curve ends meet (the pair test costs the cube of their
        number; a crossing has four ends, a blob of ink dozens).  None = no limit.
    crowded : set, optional
        Filled with the joints skipped by ``max_ends``.

    Returns
    -------
    list of dict
        The curves after joining (same dict layout); ends meet where their keypoint is the same
        (junctions) or, for synthetic ends, where their points coincide within 1e-6 px.
    """
    import heapq

    # Curves by a running index: a joined curve gets the next one, so index order is the order of
    # the curve list (survivors in place, joined curves last). Only the groups of ends that a join
    # touches are re-examined (the joint and the joined curve's two far ends), and the next join is
    # the best pair of all groups, taken from a heap: near-linear in the number of curves, where
    # rebuilding every group after each join was quadratic (511 s for a 400-line scribble).
    alive = {n: dict(c, points=np.asarray(c["points"], np.float64)) for n, c in enumerate(curves)}
    counter = len(alive)

    def key(c: dict, e: int):
        t, k = c["end_types"][e], c["end_keypoints"][e]
        if t not in JOINABLE_TYPES:
            return None
        if k >= 0:
            return ("k", int(k))
        p = c["points"][0 if e == 0 else -1]
        return ("p", int(round(p[0] * 1e6)), int(round(p[1] * 1e6)))

    groups: dict = {}
    direction: dict[tuple[int, int], np.ndarray] = {}

    def add_end(n: int, e: int):
        kk = key(alive[n], e)
        if kk is not None:
            groups.setdefault(kk, []).append((n, e))
            direction[(n, e)] = end_direction(alive[n]["points"], e == 0, tangent_px)
        return kk

    for n in list(alive):
        for e in (0, 1):
            add_end(n, e)

    def group_best(ends: list):
        """The pair of ends at one joint that continue each other best, or None."""
        best = None
        if len(ends) < 2:
            return None
        dirs = np.array([direction[x] for x in ends])
        turn = np.degrees(np.arccos(np.clip(-(dirs @ dirs.T), -1.0, 1.0)))   # 0 = straight on
        for a in range(len(ends)):
            for b in range(a + 1, len(ends)):
                if ends[a][0] == ends[b][0]:
                    continue                                    # never close a curve on itself
                t = turn[a, b]
                # Ends overlapping a or b (a duplicate on the same branch) are not other branches.
                others = [c for c in range(len(ends)) if c not in (a, b)
                          and min(180 - turn[a, c], 180 - turn[b, c]) > same_branch_deg]
                # Unambiguous: no third end continues either of the two almost as well (a Y).
                if t <= max_turn_deg and all(min(turn[a, c], turn[b, c]) >= t + margin_deg for c in others) \
                        and (best is None or t < best[0]):
                    best = (t, ends[a], ends[b])
        return best

    heap: list = []
    version: dict = {}

    def push(kk) -> None:
        ends = groups.get(kk)
        version[kk] = version.get(kk, 0) + 1
        if not ends:
            groups.pop(kk, None)
            return
        ends.sort()
        if max_ends is not None and len(ends) > max_ends:
            if crowded is not None:
                crowded.add(kk)
            return
        best = group_best(ends)
        if best is not None:
            # Ties go to the group whose first end comes first, as in a scan of the curve list.
            heapq.heappush(heap, (best[0], ends[0], version[kk], kk, best))

    for kk in list(groups):
        push(kk)
    while heap:
        _, _, ver, kk, best = heapq.heappop(heap)
        if version.get(kk) != ver:
            continue                                            # stale: the group changed since
        (i, ei), (j, ej) = best[1], best[2]
        a, b = alive.pop(i), alive.pop(j)
        touched = set()
        for n, c in ((i, a), (j, b)):
            for e in (0, 1):
                g = key(c, e)
                if g is not None:
                    groups[g] = [x for x in groups[g] if x != (n, e)]
                    direction.pop((n, e), None)
                    touched.add(g)
        pa = a["points"] if ei == 1 else a["points"][::-1]          # a runs into the joint
        pb = b["points"] if ej == 0 else b["points"][::-1]          # b runs out of it
        ta = [a["end_types"][1 - ei], b["end_types"][1 - ej]]
        ka = [a["end_keypoints"][1 - ei], b["end_keypoints"][1 - ej]]
        alive[counter] = {**a, "points": np.concatenate([pa, pb[1:]]), "end_types": ta, "end_keypoints": ka,
                          "parts": list(a["parts"]) + list(b["parts"]), "width": _mean_width(a, b)}
        for e in (0, 1):
            touched.add(add_end(counter, e))
        counter += 1
        for g in touched - {None}:
            push(g)
    return [alive[n] for n in sorted(alive)]


def _mean_width(a: dict, b: dict):
    wa, wb = a.get("width"), b.get("width")
    if wa is None or wb is None:
        return wa if wb is None else wb
    la, lb = _length(a["points"]), _length(b["points"])
    return float((wa * la + wb * lb) / max(la + lb, 1e-12))


# ---------------------------------------------------------------------------------------------
# Curves below the drawing's resolution between two keypoints
# ---------------------------------------------------------------------------------------------

def collapse_short_links(curves: list[dict], max_px: float, max_widths: float) -> list[dict]:
    """Collapse curves shorter than about a stroke width whose two ends both meet other curves.

    When one feature of the drawing gets two keypoints a few pixels apart (a corner found twice at
    the bottom of a vee, a corner next to a junction), the selection draws a tiny curve between them
    and the other curves end at either keypoint.  Read at the drawing's resolution — the stroke width
    — those ends all meet at one point, so the tiny link only adds a third and a fourth curve end
    there: two corner arms plus the link read as a junction.  A curve no longer than
    ``max(max_px, max_widths · width)`` whose ends both meet other curve ends (same keypoint, or
    synthetic ends at the same point; never two ends of one curve, which would close it), between
    curves that are all longer than that (not inside a cluster of tiny curves, such as a filled
    eye, which contracting one by one would shrink to a point), is removed, and every curve end that
    met either of its ends is moved to the link's midpoint (so no end moves by more than half the
    link) and takes the type and keypoint of the link's end that more curves met (ties: a corner,
    then a junction).  Free-ended short curves (tips, spurs) are left to :func:`attach_spurs`.

    Links are contracted one at a time, always the first one in curve order, as a rescan of the list
    after every contraction would find them; but only the curves near a contraction (at the moved
    ends, and at the far ends of the curves whose length changed) are examined again, so the cost is
    near-linear in the number of curves (a rescan was quadratic and took minutes on dense scribbles).

    Parameters
    ----------
    curves : list of dict
        As :func:`join_continuations`.
    max_px, max_widths : float
        Longest link collapsed: ``max(max_px, max_widths · width)`` (width = the link's mean width).

    Returns
    -------
    list of dict
        The remaining curves (same dict layout).
    """
    import heapq

    alive = {n: dict(c, points=np.asarray(c["points"], np.float64)) for n, c in enumerate(curves)}
    length = {n: _length(c["points"]) for n, c in alive.items()}
    ends = _EndIndex(alive)
    # The meeting keeps the keypoint that more curves met; on a tie (one curve at each end: two ends
    # meet, a corner) a corner keypoint wins, so the ends are not joined or extended there.
    rank = {5: 3, 3: 2, 1: 1, 0: 0}

    def links_to(i: int):
        """The ends met at both ends of curve i when it is a link to collapse, else None."""
        c = alive[i]
        longest = max(max_px, max_widths * float(c.get("width") or 0.0))
        if length[i] > longest:
            return None
        met = [[x for x in ends.meeting(_end_state(c, f)) if x[0] != i] for f in (0, 1)]
        if met[0] and met[1] and not ({j for j, _ in met[0]} & {j for j, _ in met[1]}) \
                and all(length[j] > longest for j, _ in met[0] + met[1]):
            return met
        return None

    heap = list(alive)           # candidates, by curve order
    while (found := _first_in_order(heap, alive, links_to)) is not None:
        i, met = found
        link = alive.pop(i)
        ends.remove(i, link)
        mid = 0.5 * (link["points"][0] + link["points"][-1])
        f = max((0, 1), key=lambda e: (len(met[e]), rank.get(link["end_types"][e], 0), -e))
        t, k = link["end_types"][f], link["end_keypoints"][f]
        states = []              # where the meetings changed: the moved ends before and after, far ends
        for j, g in met[0] + met[1]:
            o = alive[j]
            states.append(_end_state(o, g))
            ends.remove(j, o)
            pts = o["points"].copy()
            pts[0 if g == 0 else -1] = mid
            types, kps = list(o["end_types"]), list(o["end_keypoints"])
            types[g], kps[g] = t, k
            alive[j] = dict(o, points=pts, end_types=types, end_keypoints=kps)
            length[j] = _length(pts)
            ends.add(j, alive[j])
            states += [_end_state(alive[j], g), _end_state(alive[j], 1 - g)]
        touched = {j for j, _ in met[0] + met[1]} | {j for s in states for j, _ in ends.meeting(s)}
        for j in touched:
            heapq.heappush(heap, j)
    return [alive[n] for n in sorted(alive)]


# ---------------------------------------------------------------------------------------------
# Short spurs at junctions and unlabelled overshoots
# ---------------------------------------------------------------------------------------------

def _length(points: np.ndarray) -> float:
    return float(np.hypot(*np.diff(np.asarray(points, np.float64), axis=0).T).sum()) if len(points) > 1 else 0.0


def _turn_deg(d_out_a: np.ndarray, d_out_b: np.ndarray) -> float:
    """Turn between two ends meeting at a point (outward directions; 0° = straight on)."""
    return float(np.degrees(np.arccos(np.clip(-(d_out_a @ d_out_b), -1.0, 1.0))))


_SAME_POINT_PX = 0.5     # synthetic ends this close are one point (topology puts shared ends on one vertex)


def _end_state(c: dict, f: int) -> tuple:
    """(type, keypoint, point) of end f of curve c."""
    return c["end_types"][f], c["end_keypoints"][f], c["points"][0 if f == 0 else -1]


def _first_in_order(heap: list, alive: dict, test) -> tuple | None:
    """Pop curves off a min-heap of list positions until one passes ``test``: ``(curve, answer)``.

    ``test`` answers None for a curve that is no candidate now.  The editing loops push a curve again
    whenever an edit near it could change its answer, so the first curve that passes now is the one a
    rescan of the whole list would find first; removed curves and duplicates on the heap are skipped.
    """
    import heapq

    while heap:
        i = heapq.heappop(heap)
        if i in alive and (answer := test(i)) is not None:
            return i, answer
    return None


class _PointGrid:
    """Points in square cells, added and removed by owner: which lie near a point, in time ∝ those nearby.

    The curve-editing loops below (contracting links, attaching spurs) change a few curves at a time;
    with the points of every curve in one grid, each edit looks only at its own neighbourhood instead
    of at every curve of the drawing.
    """

    def __init__(self, cell: float):
        self.cell = float(cell)
        self.cells: dict[tuple[int, int], dict] = {}   # cell -> {owner: indices of its points there}
        self.owned: dict = {}                           # owner -> its cells

    def add(self, owner, points: np.ndarray) -> None:
        """Add an owner's points ((n, 2); indices are rows)."""
        keys: dict = {}
        for n, ij in enumerate(np.floor(np.asarray(points, np.float64) / self.cell).astype(np.int64).tolist()):
            keys.setdefault(tuple(ij), []).append(n)
        for key, idx in keys.items():
            self.cells.setdefault(key, {})[owner] = idx
        self.owned[owner] = list(keys)

    def remove(self, owner) -> None:
        """Remove all points of an owner (none: nothing happens)."""
        for key in self.owned.pop(owner, ()):
            cell = self.cells[key]
            del cell[owner]
            if not cell:
                del self.cells[key]

    def near(self, points: np.ndarray, r: float) -> dict:
        """Owner -> indices of its points in the cells within ``r`` of any of ``points`` ((2,) or (n, 2)).

        A superset of the points within ``r``: callers test the distance themselves.
        """
        ij = np.floor(np.asarray(points, np.float64).reshape(-1, 2) / self.cell).astype(np.int64)
        d = int(np.ceil(r / self.cell))
        if len(ij) == 1:                 # one point (most queries): its cells without numpy's unique
            x, y = ij[0].tolist()
            keys = [(x + a, y + b) for a in range(-d, d + 1) for b in range(-d, d + 1)]
        else:
            offsets = np.stack(np.meshgrid(np.arange(-d, d + 1), np.arange(-d, d + 1)), -1).reshape(-1, 2)
            keys = map(tuple, np.unique((np.unique(ij, axis=0)[:, None, :] + offsets[None]).reshape(-1, 2),
                                        axis=0).tolist())
        out: dict = {}
        for key in keys:
            for owner, idx in self.cells.get(key, {}).items():
                out.setdefault(owner, []).extend(idx)
        return out


class _EndIndex:
    """The ends of a set of curves by keypoint and, for synthetic ends (type 0), by position."""

    def __init__(self, curves: dict):
        self.by_keypoint: dict = {}      # keypoint (−1 too) -> {(curve, end)}
        self.synthetic = _PointGrid(_SAME_POINT_PX)
        self.state: dict = {}            # (curve, end) -> (type, keypoint, point)
        for n, c in curves.items():
            self.add(n, c)

    def add(self, n, c: dict) -> None:
        for f in (0, 1):
            t, k, p = self.state[(n, f)] = _end_state(c, f)
            self.by_keypoint.setdefault(k, set()).add((n, f))
            if t == 0:
                self.synthetic.add((n, f), p[None])

    def remove(self, n, c: dict) -> None:
        for f in (0, 1):
            self.by_keypoint[c["end_keypoints"][f]].discard((n, f))
            self.synthetic.remove((n, f))
            del self.state[(n, f)]

    def synthetic_near(self, p: np.ndarray) -> list:
        """Synthetic ends within ``_SAME_POINT_PX`` of p."""
        return [o for o in self.synthetic.near(p, _SAME_POINT_PX)
                if np.hypot(*(self.state[o][2] - p)) <= _SAME_POINT_PX]

    def meeting(self, state: tuple) -> list:
        """Ends that meet an end in ``state``: the same keypoint, or synthetic ends at the same point."""
        t, k, p = state
        if k >= 0:
            return list(self.by_keypoint.get(k, ()))
        if t != 0:
            return []
        return [o for o in self.synthetic_near(p) if self.state[o][1] < 0]



def attach_spurs(curves: list[dict], spur_px: float, spur_widths: float, max_turn_deg: float,
                 tangent_px: float, near_px: float, by_valence: bool = False) -> list[dict]:
    """Attach every short junction-to-endpoint curve to the curve it continues at the junction.

    A *spur* is a curve no longer than ``max(spur_px, spur_widths · width)`` with one end at a
    junction keypoint (or at a synthetic end shared with other curves) and the other end free (an
    endpoint keypoint, or a synthetic end no other curve shares): a stroke that overshoots a
    crossing, or runs into another stroke and stops just beyond it.  It is joined to whichever piece at the
    junction continues it best — another curve ending at that keypoint, or one half of a curve
    passing within ``near_px`` of it (that curve is split there; the split vertex moves onto the
    keypoint) — when the turn is at most ``max_turn_deg``.  The drawn points and the valence at the
    junction are unchanged; only the partition into curves changes.  With ``by_valence`` the ends
    at corner and junction keypoints count by their drawn valence (curve ends at the keypoint plus
    two per curve passing within ``near_px``): a corner with three or more is a junction, a corner
    or junction keypoint with only this end is a free end.

    Spurs are attached one at a time, always the first one in curve order, as a rescan of the list
    after every edit would find them; but ends and interior vertices are kept in grids, and only the
    curves near an edit (ends near the vertices it moved, ends at the keypoints it touched) are
    examined again, so the cost is near-linear in the number of curves, not cubic.

    Parameters
    ----------
    curves : list of dict
        As :func:`join_continuations` (``points``, ``end_types``, ``end_keypoints``, ``parts``,
        ``width``, ``id``).
    spur_px, spur_widths : float
        Length limit of a spur: ``max(spur_px, spur_widths · width)``.
    max_turn_deg : float
        Largest turn between the spur and the piece it is joined to.
    tangent_px : float
        Arc length over which end directions are measured.
    near_px : float
        A curve passes through the junction when one of its interior vertices lies this close.
    by_valence : bool
        Read corner and junction keypoint ends by their drawn valence (see above).

    Returns
    -------
    list of dict
    """
    import heapq

    alive = {n: dict(c, points=np.asarray(c["points"], np.float64)) for n, c in enumerate(curves)}
    counter = len(alive)           # curves by list order: a new curve goes last, as it was appended
    done: set = set()
    ends = _EndIndex(alive)
    # Interior vertices (a curve passing by) and every end (whose spur test an edit nearby may change).
    reach = max(near_px, _SAME_POINT_PX)
    inner, all_ends = _PointGrid(reach), _PointGrid(reach)

    def index(n: int) -> None:
        c = alive[n]
        ends.add(n, c)
        inner.add(n, c["points"][1:-1])
        all_ends.add(n, c["points"][[0, -1]])

    def unindex(n: int) -> None:
        ends.remove(n, alive[n])
        inner.remove(n)
        all_ends.remove(n)

    for n in alive:
        inner.add(n, alive[n]["points"][1:-1])
        all_ends.add(n, alive[n]["points"][[0, -1]])

    def meets(t: int, k: int, p: np.ndarray) -> list:
        """Ends at the junction (keypoint k of type t, or the synthetic point p)."""
        if t in (3, 5):
            return [o for o in ends.by_keypoint.get(k, ()) if ends.state[o][0] == t]
        return ends.synthetic_near(p)

    def passing(p: np.ndarray) -> dict:
        """Curve -> its interior vertices (indices into points) within ``near_px`` of p."""
        out = {}
        for n, idx in inner.near(p, near_px).items():
            pts = alive[n]["points"][np.asarray(idx) + 1]
            close = np.hypot(*(pts - p).T) <= near_px
            if close.any():
                out[n] = (np.asarray(idx)[close] + 1, np.hypot(*(pts - p).T)[close])
        return out

    def shared(i: int, e: int) -> bool:
        return any(o != (i, e) for o in ends.synthetic_near(_end_state(alive[i], e)[2]))

    def drawn_valence(i: int, e: int) -> int:
        """Valence drawn at a keypoint end: curve ends at its keypoint, plus 2 per curve passing by."""
        _, k, p = _end_state(alive[i], e)
        v = len(ends.by_keypoint.get(k, ()))
        for n in passing(p):
            o = alive[n]
            if k not in (o["end_keypoints"][0], o["end_keypoints"][1]) and len(o["points"]) > 2:
                v += 2
        return v

    def spur_end(i: int):
        """The junction end of curve i when it is a spur to attach, else None."""
        c = alive[i]
        w = c.get("width") or 0.0
        if c["id"] in done or _length(c["points"]) > max(spur_px, spur_widths * w):
            return None
        for e in (0, 1):
            t_j, t_f = c["end_types"][e], c["end_types"][1 - e]
            at_junction = ((t_j == 3 and c["end_keypoints"][e] >= 0) or t_j == 0
                           or (by_valence and t_j == 5 and drawn_valence(i, e) >= 3))
            free = (t_f == 1 or (t_f == 0 and not shared(i, 1 - e))
                    or (by_valence and t_f in (3, 5) and c["end_keypoints"][1 - e] >= 0
                        and drawn_valence(i, 1 - e) == 1))
            if at_junction and free:
                return e
        return None

    heap = list(alive)             # candidates, by list order
    while (found := _first_in_order(heap, alive, spur_end)) is not None:
        i, e = found
        spur = alive[i]
        done.add(spur["id"])
        t_j, k, p = _end_state(spur, e)
        d_s = end_direction(spur["points"], e == 0, tangent_px)
        best = None                                     # (turn, j, kind, index)
        at_end: dict = {}
        for j, f in meets(t_j, k, p):
            at_end.setdefault(j, []).append(f)
        near = passing(p)
        for j in sorted(set(at_end) | set(near)):       # in list order: the first of equal turns wins
            if j == i:
                continue
            c = alive[j]
            for f in sorted(at_end.get(j, ())):
                t = _turn_deg(d_s, end_direction(c["points"], f == 0, tangent_px))
                if best is None or t < best[0]:
                    best = (t, j, "end", f)
            pts = c["points"]
            if j in near and len(pts) > 2:
                idx, dist = near[j]
                m = int(idx[np.lexsort((idx, dist))[0]])  # the nearest interior vertex (first of ties)
                for f, half in ((1, pts[:m + 1]), (0, pts[m:])):
                    if _length(half) <= 1e-9:
                        continue
                    t = _turn_deg(d_s, end_direction(half, f == 0, tangent_px))
                    if best is None or t < best[0]:
                        best = (t, j, "split", (m, f))
        if best is None or best[0] > max_turn_deg:
            continue
        _, j, kind, where = best
        other = alive[j]
        sp = spur["points"] if e == 1 else spur["points"][::-1]        # runs into the junction
        s_type, s_kp = spur["end_types"][1 - e], spur["end_keypoints"][1 - e]
        rest = []
        if kind == "end":
            f = where
            op = other["points"] if f == 0 else other["points"][::-1]  # runs out of the junction
            o_type, o_kp = other["end_types"][1 - f], other["end_keypoints"][1 - f]
        else:
            m, f = where
            pts = other["points"].copy()
            pts[m] = p
            first, second = pts[:m + 1], pts[m:]
            if f == 1:      # the spur continues into the first half (read backwards from the junction)
                op, o_type, o_kp = first[::-1], other["end_types"][0], other["end_keypoints"][0]
                rest = [dict(other, points=second, end_types=[t_j, other["end_types"][1]],
                             end_keypoints=[k, other["end_keypoints"][1]])]
            else:
                op, o_type, o_kp = second, other["end_types"][1], other["end_keypoints"][1]
                rest = [dict(other, points=first, end_types=[other["end_types"][0], t_j],
                             end_keypoints=[other["end_keypoints"][0], k])]
        joined = {**spur, "points": np.concatenate([sp, op[1:]]), "end_types": [s_type, o_type],
                  "end_keypoints": [s_kp, o_kp], "parts": list(spur["parts"]) + list(other["parts"]),
                  "width": _mean_width(spur, other)}
        # What the edit can change for other curves: ends near the vertices it moved between curves
        # (shared synthetic ends, curves passing by) and the counts at the keypoints it touched.
        moved = np.vstack([spur["points"], other["points"], p[None]])
        keypoints = {spur["end_keypoints"][0], spur["end_keypoints"][1], other["end_keypoints"][0],
                     other["end_keypoints"][1], k} - {-1}   # not −1: junction and corner ends have keypoints
        for n in (i, j):
            unindex(n)
            del alive[n]
        for c in rest + [joined]:
            alive[counter] = c
            index(counter)
            heapq.heappush(heap, counter)
            counter += 1
        touched = set(all_ends.near(moved, reach))
        touched |= {n for kp in keypoints for n, _ in ends.by_keypoint.get(kp, ())}
        for n in touched:
            heapq.heappush(heap, n)
    return [alive[n] for n in sorted(alive)]


def _distance_to_polyline(p: np.ndarray, pts: np.ndarray) -> float:
    """Euclidean distance from point p to a polyline (n ≥ 1 points)."""
    if len(pts) == 1:
        return float(np.hypot(*(pts[0] - p)))
    return _distance_to_segments(p, pts[:-1], pts[1:])


def _distance_to_segments(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Euclidean distance from point p to the nearest of the segments a[k]–b[k] (inf when none)."""
    if len(a) == 0:
        return np.inf
    ab = b - a
    den = np.maximum((ab * ab).sum(1), 1e-24)
    u = np.clip(((p - a) * ab).sum(1) / den, 0.0, 1.0)
    return float(np.hypot(*(a + u[:, None] * ab - p).T).min())


def extend_overshoots(curves: list[dict], mask: np.ndarray, tangent_px: float, min_px: float,
                      min_widths: float, max_px: float, max_widths: float, clearance: float,
                      step_px: float = 0.25) -> list[dict]:
    """Extend curve ends at junctions over an ink overshoot that no keypoint marks.

    A stroke that crosses another one and stops a few pixels beyond leaves a short tip of ink past
    the junction.  Without an endpoint keypoint at the tip the topology ends the curve at the
    junction and the tip is lost (it is the largest Hausdorff error of many realvec_dev drawings).
    For every curve end at a junction keypoint or a synthetic end, we walk from the end straight on
    (its direction over ``tangent_px``) through the band ``mask`` until the ink stops at distance
    ``s``; the stroke's centre line ends half a width before its ink does, so the overshoot is
    ``e = s − width/2``.  The curve is extended by ``e`` when
    ``max(min_px, min_widths·width) ≤ e ≤ max(max_px, max_widths·width)`` (a plain T has e ≈ 0: the
    ink ahead is the crossed stroke's half width; ink that goes on is another stroke's business) and
    the new tip lies at least ``clearance · e`` from every other curve (a Y's gap between branches,
    or a neighbouring stroke, fails this).

    The extended end is no longer at its keypoint: its type becomes 0 and its keypoint −1, and the
    junction is listed in the curve's ``through_keypoints``; ``extended`` gives the length (px) added
    at each end.

    Parameters
    ----------
    curves : list of dict
        As :func:`join_continuations`.
    mask : numpy.ndarray
        bool (H, W) band (prep ``mask``); pixel [i, j] covers x ∈ [j, j+1), y ∈ [i, i+1).
    tangent_px : float
        Arc length over which end directions are measured.
    min_px, min_widths, max_px, max_widths : float
        Bounds on the extension (px, and in units of the curve's width).
    clearance : float
        Minimum distance of the new tip from other curves, as a fraction of the extension.
    step_px : float
        Sampling step of the walk.

    Returns
    -------
    list of dict
    """
    from scipy.spatial import cKDTree

    curves = [dict(c, points=np.asarray(c["points"], np.float64)) for c in curves]
    h, w_img = mask.shape
    # Every curve's segments, stacked once, for the clearance test; a tree of their midpoints finds
    # the few near a tip (a segment within r of it has its midpoint within r + half the longest
    # segment), where testing every segment of the drawing for every end was quadratic.
    seg_a = [c["points"][:-1] if len(c["points"]) > 1 else c["points"] for c in curves]
    seg_b = [c["points"][1:] if len(c["points"]) > 1 else c["points"] for c in curves]
    owner = np.repeat(np.arange(len(curves)), [len(a) for a in seg_a])
    seg_a = np.concatenate(seg_a) if curves else np.zeros((0, 2))
    seg_b = np.concatenate(seg_b) if curves else np.zeros((0, 2))
    mids = cKDTree(0.5 * (seg_a + seg_b)) if len(seg_a) else None
    half = 0.5 * float(np.hypot(*(seg_b - seg_a).T).max()) if len(seg_a) else 0.0
    adds = []
    for i, c in enumerate(curves):
        w = float(c.get("width") or 0.0)
        lo, hi = max(min_px, min_widths * w), max(max_px, max_widths * w)
        ext = [None, None]
        for e in (0, 1):
            if c["end_types"][e] not in JOINABLE_TYPES or _length(c["points"]) <= 1e-9:
                continue
            p = c["points"][0 if e == 0 else -1]
            d = end_direction(c["points"], e == 0, tangent_px)
            s = np.arange(0.0, hi + 0.5 * w + 1.0, step_px)
            x, y = p[0] + s * d[0], p[1] + s * d[1]
            j, ii = np.floor(x).astype(int), np.floor(y).astype(int)
            inside = (ii >= 0) & (ii < h) & (j >= 0) & (j < w_img)
            ink = np.zeros(len(s), bool)
            ink[inside] = mask[ii[inside], j[inside]]
            if ink.all():
                continue                                   # the ink goes on: not an overshoot
            ln = float(s[np.argmin(ink)]) - 0.5 * w
            if not lo <= ln <= hi:
                continue
            tip = p + ln * d
            # Other curves, and this curve's own far part (a closed loop's other end, a hairpin).
            pts = c["points"] if e == 0 else c["points"][::-1]
            arc = np.r_[0.0, np.cumsum(np.hypot(*np.diff(pts, axis=0).T))]
            own = pts[arc > 2.0 * ln]
            cand = np.asarray(mids.query_ball_point(tip, clearance * ln + half), np.int64)
            others = cand[owner[cand] != i]
            near = min(_distance_to_segments(tip, seg_a[others], seg_b[others]),
                       _distance_to_polyline(tip, own) if len(own) else np.inf)
            if near < clearance * ln:
                continue
            ext[e] = (tip, ln)
        adds.append(ext)
    for c, ext in zip(curves, adds):
        if ext == [None, None]:
            continue
        pts, types, kps = c["points"], list(c["end_types"]), list(c["end_keypoints"])
        through = list(c.get("through_keypoints", []))
        lengths = [0.0, 0.0]
        for e in (0, 1):
            if ext[e] is None:
                continue
            tip, ln = ext[e]
            pts = np.vstack([tip[None], pts]) if e == 0 else np.vstack([pts, tip[None]])
            if kps[e] >= 0:
                through.append(int(kps[e]))
            types[e], kps[e], lengths[e] = 0, -1, round(float(ln), 3)
        c.update(points=pts, end_types=types, end_keypoints=kps, through_keypoints=through, extended=lengths)
    return curves


# ---------------------------------------------------------------------------------------------
# Cubic Bézier fitting (Schneider 1990)
# ---------------------------------------------------------------------------------------------

def _bezier(ctrl: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Points of one cubic Bézier (4, 2) at parameters u."""
    u = u[:, None]
    v = 1 - u
    return v ** 3 * ctrl[0] + 3 * v * v * u * ctrl[1] + 3 * v * u * u * ctrl[2] + u ** 3 * ctrl[3]


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.hypot(*v)
    return v / n if n > 1e-12 else np.zeros(2)


def _fit_segment(pts: np.ndarray, u: np.ndarray, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """Least-squares control points for fixed end points and end tangent directions."""
    p0, p3 = pts[0], pts[-1]
    v = 1 - u
    a0 = (3 * v * v * u)[:, None] * t0
    a1 = (3 * v * u * u)[:, None] * t1
    c00, c01, c11 = (a0 * a0).sum(), (a0 * a1).sum(), (a1 * a1).sum()
    rest = pts - _bezier(np.array([p0, p0, p3, p3]), u)
    x0, x1 = (a0 * rest).sum(), (a1 * rest).sum()
    det = c00 * c11 - c01 * c01
    seg = np.hypot(*(p3 - p0))
    if abs(det) > 1e-12:
        al0 = (x0 * c11 - x1 * c01) / det
        al1 = (c00 * x1 - c01 * x0) / det
    else:
        al0 = al1 = seg / 3
    if al0 < 1e-6 * seg or al1 < 1e-6 * seg:  # degenerate: Wu–Barsky heuristic
        al0 = al1 = seg / 3
    return np.array([p0, p0 + al0 * t0, p3 + al1 * t1, p3])


def _reparameterise(ctrl: np.ndarray, pts: np.ndarray, u: np.ndarray) -> np.ndarray:
    """One Newton step on |B(u) − p|² per point."""
    d1 = 3 * np.diff(ctrl, axis=0)
    d2 = 2 * np.diff(d1, axis=0)
    diff = _bezier(ctrl, u) - pts
    uu = u[:, None]
    b1 = (1 - uu) ** 2 * d1[0] + 2 * (1 - uu) * uu * d1[1] + uu ** 2 * d1[2]
    b2 = (1 - uu) * d2[0] + uu * d2[1]
    num = (diff * b1).sum(1)
    den = (b1 * b1).sum(1) + (diff * b2).sum(1)
    step = np.where(np.abs(den) > 1e-12, num / np.where(np.abs(den) > 1e-12, den, 1), 0)
    return np.clip(u - step, 0, 1)


def fit_cubic_beziers(points: np.ndarray, tolerance: float, max_depth: int = 32) -> list[np.ndarray]:
    """Fit a polyline with a chain of cubic Béziers within ``tolerance`` (max point distance).

    Parameters
    ----------
    points : numpy.ndarray
        (n, 2) polyline in (x, y).
    tolerance : float
        Largest allowed distance (px) between a polyline vertex and its fitted point.

    Returns
    -------
    list of numpy.ndarray
        (4, 2) control points per piece; consecutive pieces share end points.
    """
    pts = np.asarray(points, np.float64)
    keep = np.r_[True, np.hypot(*np.diff(pts, axis=0).T) > 1e-9]
    pts = pts[keep]
    if len(pts) < 2:
        return []
    if len(pts) == 2:
        a, b = pts
        return [np.array([a, a + (b - a) / 3, a + 2 * (b - a) / 3, b])]

    def tangent_at(i: int, direction: int) -> np.ndarray:
        # Direction from vertex i towards its neighbours (≥ 2 px of arc, to average out jitter).
        j, acc = i, 0.0
        while 0 <= j + direction < len(pts) and acc < 2.0:
            acc += np.hypot(*(pts[j + direction] - pts[j]))
            j += direction
        return _unit(pts[j] - pts[i])

    out: list[np.ndarray] = []

    def fit(lo: int, hi: int, t0: np.ndarray, t1: np.ndarray, depth: int) -> None:
        seg = pts[lo:hi + 1]
        if len(seg) == 2:
            a, b = seg
            d = np.hypot(*(b - a)) / 3
            out.append(np.array([a, a + d * t0, b + d * t1, b]))
            return
        s = np.r_[0, np.cumsum(np.hypot(*np.diff(seg, axis=0).T))]
        u = s / s[-1]
        ctrl = _fit_segment(seg, u, t0, t1)
        for _ in range(20):
            err = np.hypot(*(_bezier(ctrl, u) - seg).T)
            if err.max() <= tolerance:
                out.append(ctrl)
                return
            if err.max() > 4 * tolerance:
                break
            u = _reparameterise(ctrl, seg, u)
            ctrl = _fit_segment(seg, u, t0, t1)
        err = np.hypot(*(_bezier(ctrl, u) - seg).T)
        if err.max() <= tolerance or depth >= max_depth:
            out.append(ctrl)
            return
        k = int(np.argmax(err[1:-1])) + 1
        tc = _unit(seg[k - 1] - seg[k + 1])
        if not tc.any():
            tc = _unit(np.array([-(seg[k + 1] - seg[k])[1], (seg[k + 1] - seg[k])[0]]))
        fit(lo, lo + k, t0, tc, depth + 1)
        fit(lo + k, hi, -tc, t1, depth + 1)

    fit(0, len(pts) - 1, tangent_at(0, 1), tangent_at(len(pts) - 1, -1), 0)
    return out


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


def svg_document(width: int, height: int, curves: list[dict], ds: list[str], params: ExportParams) -> str:
    """An SVG document with one black, unfilled ``<path>`` per curve.

    Parameters
    ----------
    width, height : int
        Image size in pixels (also the viewBox).
    curves : list of dict
        With ``id`` and ``width`` (used when ``widths_from_graph``).
    ds : list of str
        Path data per curve.
    params : ExportParams
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
        Image size (``prep`` data ``height``/``width`` or its ``grey``), candidate paths (end types,
        widths), flowed curves (topology order) and the chosen path ids.

    Returns
    -------
    Artifact
        data ``svg``, ``curves`` and (optional) ``bezier_svg``.
    """
    params = ExportParams.from_cfg(cfg)
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
    if len(curves) > params.max_curves:
        # A guard, not a choice: the edits below are near-linear, but a drawing with more curves than
        # this is not a line drawing we can tidy in bounded time; its curves are written as selected.
        notes.append(f"{len(curves)} curves, more than export.max_curves ({params.max_curves}): written as "
                     "selected, without link contraction, joins, spurs or overshoot extension")
        params = replace(params, collapse=False, join=False, spurs=False, overshoot=False)
    if params.collapse:
        curves = collapse_short_links(curves, params.collapse_max_px, params.collapse_max_widths)
    if params.join:
        crowded: set = set()
        curves = join_continuations(curves, params.join_max_turn_deg, params.join_tangent_px,
                                    params.join_margin_deg, params.join_same_branch_deg, params.join_max_ends,
                                    crowded)
        if crowded:
            notes.append(f"{len(crowded)} joints where more than export.join.max_ends ({params.join_max_ends}) "
                         "curve ends meet: no curves joined there")
    if params.spurs:
        curves = attach_spurs(curves, params.spur_max_px, params.spur_max_widths, params.spur_max_turn_deg,
                              params.join_tangent_px, params.spur_near_px, params.spur_by_valence)
    mask = prep.arrays.get("mask")
    if params.overshoot and mask is not None:
        curves = extend_overshoots(curves, np.asarray(mask, bool), params.join_tangent_px, params.overshoot_min_px,
                                   params.overshoot_min_widths, params.overshoot_max_px,
                                   params.overshoot_max_widths, params.overshoot_clearance)
    # A curve shorter than a pixel draws nothing an artist can edit (a selected path that flowed onto
    # one point: `M x y L x y`), and has no tangent for the Bézier fit.
    curves = [c for c in curves if _length(c["points"]) >= params.min_length_px]
    for c in curves:
        pts = c["points"]
        c["points"] = pts.tolist()
        ds.append(_polyline_d(pts, params.precision))
        if params.bezier:
            bds.append(_bezier_d(fit_cubic_beziers(pts, params.bezier_tolerance), params.precision))
    data = {"svg": svg_document(width, height, curves, ds, params), "curves": curves}
    if params.bezier:
        data["bezier_svg"] = svg_document(width, height, curves, bds, params)
    return Artifact(data=data, notes=notes)
