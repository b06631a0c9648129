"""Clean-ups of the selected curves before export: joins, link contraction, spurs and overshoots.

Each is a choice beyond the paper, described in :mod:`stages.export.stage` (measurements in
stages/DECISIONS.md). Curves are dicts ``{"id", "points", "end_types", "end_keypoints", "parts",
"width", ...}`` (stages/INTERFACES.md, export); points are (x, y) pixel coordinates, corner origin.
"""

from __future__ import annotations

import numpy as np

from stages.export.end_index import _SAME_POINT_PX, _EndIndex, _end_state, _first_in_order, _PointGrid, _within
from stages.geometry import arc_length, point_at_arc, polyline_length, turn_deg, unit

JOINABLE_TYPES = (0, 3)      # synthetic ends and junctions; never endpoints (1) or sharp corners (5)
_MIDPOINT_CELL_PX = 4.0     # cell of the segment-midpoint grid of the overshoot extension (a few segments per cell)


def end_direction(points: np.ndarray, at_start: bool, arc_px: float) -> np.ndarray:
    """Unit direction pointing *out of* a curve end: from the point ``arc_px`` along it to the end."""
    pts = np.asarray(points, np.float64)
    if not at_start:
        pts = pts[::-1]
    s = arc_length(pts)
    if s[-1] <= 1e-12:
        return np.zeros(2)
    q = point_at_arc(pts, s, min(arc_px, 0.5 * s[-1]))
    return unit(pts[0] - q)


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


def mean_width(pieces: list[dict]):
    """Stroke width of curves joined into one: their widths weighted by length (unknown ones left out)."""
    known = [c for c in pieces if c.get("width") is not None]
    if len(known) < 2:
        return known[0]["width"] if known else None
    lengths = [polyline_length(c["points"]) for c in known]
    return float(sum(c["width"] * ln for c, ln in zip(known, lengths)) / max(sum(lengths), 1e-12))


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


# ---------------------------------------------------------------------------------------------
# Short spurs at junctions and unlabelled overshoots
# ---------------------------------------------------------------------------------------------

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
    curves = [dict(c, points=np.asarray(c["points"], np.float64)) for c in curves]
    h, w_img = mask.shape
    # Every curve's segments, stacked once, for the clearance test; a grid of their midpoints finds
    # the few near a tip (a segment within r of it has its midpoint within r + half the longest
    # segment), where testing every segment of the drawing for every end was quadratic. (The
    # export's own grid, not a scipy k-d tree: a λ re-run then loads no scipy.spatial.)
    seg_a = [c["points"][:-1] if len(c["points"]) > 1 else c["points"] for c in curves]
    seg_b = [c["points"][1:] if len(c["points"]) > 1 else c["points"] for c in curves]
    first = np.cumsum([0] + [len(a) for a in seg_a])
    mids = _PointGrid(_MIDPOINT_CELL_PX)
    for i, (a, b) in enumerate(zip(seg_a, seg_b)):
        mids.add(i, 0.5 * (a + b))
    seg_a = np.concatenate(seg_a) if curves else np.zeros((0, 2))
    seg_b = np.concatenate(seg_b) if curves else np.zeros((0, 2))
    half = 0.5 * float(np.hypot(*(seg_b - seg_a).T).max()) if len(seg_a) else 0.0
    adds = []
    for i, c in enumerate(curves):
        w = float(c.get("width") or 0.0)
        lo, hi = max(min_px, min_widths * w), max(max_px, max_widths * w)
        ext = [None, None]
        for e in (0, 1):
            if c["end_types"][e] not in JOINABLE_TYPES or polyline_length(c["points"]) <= 1e-9:
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
            arc = arc_length(pts)
            own = pts[arc > 2.0 * ln]
            reach = clearance * ln + half
            others = np.array([first[o] + k for o, idx in mids.near(tip, reach).items() if o != i for k in idx],
                              np.int64)
            others = others[_within(0.5 * (seg_a[others] + seg_b[others]), tip, reach)]
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



