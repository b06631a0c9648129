"""Short spurs at junctions: a junction-to-free-end curve attached to the piece it continues.

An export clean-up beyond the paper (:mod:`stages.export.stage` describes it, stages/DECISIONS.md
has the measurements), run after the joins of :mod:`stages.export.joins`; see
:func:`attach_spurs`.  Curves are dicts ``{"id", "points", "end_types", "end_keypoints", "parts",
"width", ...}`` (stages/INTERFACES.md, export); points are (x, y) pixel coordinates, corner origin.
"""

from __future__ import annotations

import numpy as np

from stages.export.curve_ends import end_direction, mean_width
from stages.export.end_index import _SAME_POINT_PX, _EndIndex, _end_state, _first_in_order, _PointGrid
from stages.geometry import polyline_length, turn_deg


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
        As :func:`~stages.export.joins.join_continuations` (``points``, ``end_types``, ``end_keypoints``, ``parts``,
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
        if c["id"] in done or polyline_length(c["points"]) > max(spur_px, spur_widths * w):
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
                t = turn_deg(d_s, end_direction(c["points"], f == 0, tangent_px))
                if best is None or t < best[0]:
                    best = (t, j, "end", f)
            pts = c["points"]
            if j in near and len(pts) > 2:
                idx, dist = near[j]
                m = int(idx[np.lexsort((idx, dist))[0]])  # the nearest interior vertex (first of ties)
                for f, half in ((1, pts[:m + 1]), (0, pts[m:])):
                    if polyline_length(half) <= 1e-9:
                        continue
                    t = turn_deg(d_s, end_direction(half, f == 0, tangent_px))
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
                  "width": mean_width([spur, other])}
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
