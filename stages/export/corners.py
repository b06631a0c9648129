"""Strokes through their sharp corners: the last clean-up of the selected curves (``export.corners``).

Described in :mod:`stages.export`; measurements in stages/DECISIONS.md.
"""

from __future__ import annotations

import numpy as np

from stages.geometry import polyline_length

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

    def chain_from(n: int, e: int, seen: set) -> list[tuple[int, bool]]:
        """Curves from curve n leaving by end e: (curve, reversed) in order, stopping at a repeat."""
        out, cur, leave = [], n, e
        while True:
            seen.add(cur)
            out.append((cur, leave == 0))          # leaving by its start: walked backwards
            nxt = link.get((cur, leave))
            if nxt is None or nxt[0] in seen:
                return out
            cur, leave = nxt[0], 1 - nxt[1]

    done: set = set()
    result: list[dict] = []
    for n in range(len(curves)):
        if n in done:
            continue
        # Walk back to a free end of the chain (or once round a closed chain), then forward.
        start, e, seen = n, 0, {n}
        while (prev := link.get((start, e))) is not None and prev[0] not in seen:
            start, e = prev[0], 1 - prev[1]
            seen.add(start)
        pieces = chain_from(start, 1 - e, set())
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
                joint = sum(len(q) for q in pts) - 1    # the corner vertex: the chain's last point so far
                corners.append(joint)
                base = joint + 1                         # this piece's first point comes next
                if np.hypot(*(p[0] - pts[-1][-1])) <= 1e-9:
                    p, own = p[1:], [i - 1 for i in own]     # the shared corner point once
            corners += [base + i for i in own]
            pts.append(p)
        first, last = curves[pieces[0][0]], curves[pieces[-1][0]]
        e0 = 1 if pieces[0][1] else 0                  # the chain starts at this end of the first piece
        e1 = 0 if pieces[-1][1] else 1
        joined = dict(first, points=np.concatenate(pts), corners=sorted(set(corners)),
                      end_types=[first["end_types"][e0], last["end_types"][e1]],
                      end_keypoints=[first["end_keypoints"][e0], last["end_keypoints"][e1]],
                      parts=[q for k, _ in pieces for q in curves[k]["parts"]])
        w = [(curves[k].get("width"), polyline_length(curves[k]["points"])) for k, _ in pieces]
        if all(x is not None for x, _ in w):
            joined["width"] = float(sum(x * ln for x, ln in w) / max(sum(ln for _, ln in w), 1e-12))
        result.append(joined)
    return result
