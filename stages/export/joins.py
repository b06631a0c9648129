"""Clean-ups of the selected curves before export: joins, link contraction, spurs and overshoots.

Each is a choice beyond the paper, described in :mod:`stages.export.stage` (measurements in
stages/DECISIONS.md). Curves are dicts ``{"id", "points", "end_types", "end_keypoints", "parts",
"width", ...}`` (stages/INTERFACES.md, export); points are (x, y) pixel coordinates, corner origin.

The joins of curves that continue each other (:func:`join_continuations`) and the contraction of
links below the drawing's resolution (:func:`collapse_short_links`) are here; the spurs
(:func:`~stages.export.spurs.attach_spurs`) and the overshoots
(:func:`~stages.export.overshoots.extend_overshoots`) have their own modules, and what they all read
of a curve end (:func:`~stages.export.curve_ends.end_direction`,
:func:`~stages.export.curve_ends.mean_width`) is in :mod:`stages.export.curve_ends`.
"""

from __future__ import annotations

import numpy as np

from stages.export.curve_ends import JOINABLE_TYPES, end_direction, mean_width
from stages.export.end_index import _EndIndex, _end_state, _first_in_order
from stages.geometry import polyline_length

__all__ = ["collapse_short_links", "join_continuations"]


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
                          "parts": list(a["parts"]) + list(b["parts"]), "width": mean_width([a, b])}
        for e in (0, 1):
            touched.add(add_end(counter, e))
        counter += 1
        for g in touched - {None}:
            push(g)
    return [alive[n] for n in sorted(alive)]


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
    length = {n: polyline_length(c["points"]) for n, c in alive.items()}
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
            length[j] = polyline_length(pts)
            ends.add(j, alive[j])
            states += [_end_state(alive[j], g), _end_state(alive[j], 1 - g)]
        touched = {j for j, _ in met[0] + met[1]} | {j for s in states for j, _ in ends.meeting(s)}
        for j in touched:
            heapq.heappush(heap, j)
    return [alive[n] for n in sorted(alive)]
