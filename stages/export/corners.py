"""Strokes through their sharp corners: the last clean-up of the selected curves (``export.corners``).

Described in :mod:`stages.export.stage`; measurements in stages/DECISIONS.md.
"""

from __future__ import annotations

import numpy as np

from stages.export.curve_ends import mean_width

CORNER = 5


def join_at_corners(curves: list[dict]) -> list[dict]:
    """Join the two curves that meet at a sharp-corner keypoint into one curve with a corner vertex.

    The selection ends curves at every keypoint, so a stroke with corners (a zigzag, a star, a
    letter) comes out as one curve per straight-ish piece.  Where exactly two curve ends share a
    corner keypoint (and they belong to two different curves), the drawing has one stroke turning
    sharply: the two become one curve whose ``corners`` lists the index of the corner vertex, so the
    Bézier fit keeps it sharp.  A stroke that crosses itself is then one curve crossing itself, not
    two curves crossing (a junction the drawing does not have).  Chains are followed through
    several corners; a closed chain (a polygon) is opened at its first joint, so no curve is
    closed on itself.  Ends of other types, and corners where three or more ends meet, are left.

    Parameters
    ----------
    curves : list of dict
        As :func:`join_continuations`; an optional ``corners`` (vertex indices) is carried over.

    Returns
    -------
    list of dict
        The curves after joining, each with ``corners``; a joined curve keeps its first piece's
        ``id`` and lists every piece's ``parts``.
    """
    at: dict[int, list[tuple[int, int]]] = {}
    for n, c in enumerate(curves):
        for e in (0, 1):
            if c["end_types"][e] == CORNER and c["end_keypoints"][e] >= 0:
                at.setdefault(int(c["end_keypoints"][e]), []).append((n, e))
    link: dict[tuple[int, int], tuple[int, int]] = {}
    for ends in at.values():
        if len(ends) == 2 and ends[0][0] != ends[1][0]:
            link[ends[0]], link[ends[1]] = ends[1], ends[0]

    return join_linked(curves, link, corner_joints=True)


def join_linked(curves: list[dict], link: dict, corner_joints: bool) -> list[dict]:
    """Join curves along ``link`` (curve end -> the end of another curve it continues into) into chains.

    Chains are followed through several joints; a closed chain is opened at its first joint, so no
    curve is closed on itself. Shared by the corner joins and the gap closing.

    Parameters
    ----------
    curves : list of dict
        As :func:`join_at_corners`.
    link : dict
        ``(curve, end) -> (curve, end)``, symmetric; each end at most once.
    corner_joints : bool
        Mark every joint as a corner vertex (``corners``); the joint's point is kept once when the two
        ends coincide.

    Returns
    -------
    list of dict
        The curves after joining, each with ``corners``; a joined curve keeps its first piece's ``id``
        and lists every piece's ``parts``.
    """
    def walk(n: int, leave: int) -> list[tuple[int, int]]:
        """Curves linked from curve n leaving by end ``leave``: (curve, end it is left by),
        stopping at a free end or where the chain comes round to a curve already walked."""
        out, seen = [(n, leave)], {n}
        while (nxt := link.get(out[-1])) is not None and nxt[0] not in seen:
            seen.add(nxt[0])
            out.append((nxt[0], 1 - nxt[1]))
        return out

    done: set = set()
    result: list[dict] = []
    for n in range(len(curves)):
        if n in done:
            continue
        # Walk back to a free end of the chain (or once round a closed chain, which opens it there),
        # then forward from there: the pieces in order, each reversed when it is left by its start.
        start, left_by = walk(n, 0)[-1]
        pieces = [(k, leave == 0) for k, leave in walk(start, 1 - left_by)]
        done.update(k for k, _ in pieces)
        if len(pieces) == 1:
            result.append(dict(curves[n], corners=list(curves[n].get("corners", []))))
            continue
        pts, corners = [], []
        for k, rev in pieces:
            p = np.asarray(curves[k]["points"], np.float64)
            own = [int(i) for i in curves[k].get("corners", [])]
            if rev:
                p, own = p[::-1], [len(p) - 1 - i for i in own][::-1]
            base = 0
            if pts:
                joint = sum(len(q) for q in pts) - 1    # the joint: the chain's last point so far
                if corner_joints:
                    corners.append(joint)
                base = joint + 1                         # this piece's first point comes next
                if np.hypot(*(p[0] - pts[-1][-1])) <= 1e-9:
                    p, own = p[1:], [i - 1 for i in own]     # the shared joint point once
            corners += [base + i for i in own]
            pts.append(p)
        first, last = curves[pieces[0][0]], curves[pieces[-1][0]]
        e0 = 1 if pieces[0][1] else 0                  # the chain starts at this end of the first piece
        e1 = 0 if pieces[-1][1] else 1
        joined = dict(first, points=np.concatenate(pts), corners=sorted(set(corners)),
                      end_types=[first["end_types"][e0], last["end_types"][e1]],
                      end_keypoints=[first["end_keypoints"][e0], last["end_keypoints"][e1]],
                      parts=[q for k, _ in pieces for q in curves[k]["parts"]],
                      width=mean_width([curves[k] for k, _ in pieces]))
        result.append(joined)
    return result
