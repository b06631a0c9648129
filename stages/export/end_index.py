"""Indexes of curve ends and vertices for the curve-editing loops of :mod:`stages.export.joins`.

Contracting links and attaching spurs change a few curves at a time; these keep the curves' ends (by
keypoint, and synthetic ends by position) and vertices in grids, so that each edit re-examines only the
curves near it (near-linear in the number of curves, where a rescan of the whole list was quadratic),
and :func:`_first_in_order` keeps the choice of a rescan: the first candidate in curve order.
"""

from __future__ import annotations

import numpy as np

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
        self.cells: dict[int, dict] = {}               # cell -> {owner: indices of its points there}
        self.owned: dict = {}                           # owner -> its cells

    def _keys(self, points: np.ndarray) -> np.ndarray:
        """Cell keys of points: column · 2³² + row (one int: ordered as the (column, row) pairs)."""
        ij = np.floor(np.asarray(points, np.float64).reshape(-1, 2) / self.cell).astype(np.int64)
        return (ij[:, 0] << 32) + ij[:, 1]

    def add(self, owner, points: np.ndarray) -> None:
        """Add an owner's points ((n, 2); indices are rows)."""
        # Grouped by numpy, not point by point: a page's grids hold hundreds of thousands of vertices.
        key = self._keys(points)
        order = np.argsort(key, kind="stable")
        cut = (np.flatnonzero(key[order][1:] != key[order][:-1]) + 1).tolist()
        keys, rows = key[order][[0] + cut].tolist() if len(key) else [], order.tolist()
        for key_, lo, hi in zip(keys, [0] + cut, cut + [len(rows)]):
            self.cells.setdefault(key_, {})[owner] = rows[lo:hi]
        self.owned[owner] = keys

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
        d = int(np.ceil(r / self.cell))
        step = np.arange(-d, d + 1)
        around = ((step[:, None] << 32) + step).ravel()          # (column, row) offsets, in order
        key = self._keys(points)
        if len(key) == 1:                # one point (most queries): its cells without numpy's unique
            keys = (int(key[0]) + around).tolist()
        else:
            keys = np.unique((np.unique(key)[:, None] + around).ravel()).tolist()
        out: dict = {}
        for key in keys:
            for owner, idx in self.cells.get(key, {}).items():
                out.setdefault(owner, []).extend(idx)
        return out


def _within(points: np.ndarray, q: np.ndarray, r: float) -> np.ndarray:
    """bool (n,): which of ``points`` ((n, 2)) lie within ``r`` of ``q`` (squared distances, as k-d trees test).

    :meth:`_PointGrid.near` gives a superset by cells; this is the exact test its callers apply.
    """
    d = np.asarray(points, np.float64).reshape(-1, 2) - q
    return d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] <= r * r


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


def _in_cells(order: np.ndarray, skey: np.ndarray, look: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points in each of the cells ``look``: (how many in each, their indices cell after cell), from
    the points' cell keys sorted (``skey``) and the sorting order (``order``)."""
    lo, hi = np.searchsorted(skey, look, "left"), np.searchsorted(skey, look, "right")
    n = hi - lo
    return n, order[np.repeat(lo, n) + np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)]


def points_near(P: np.ndarray, Q: np.ndarray, r: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (q, p) of a query point ``Q[q]`` and a point ``P[p]`` within its own radius ``r[q]``.

    The squared-distance test of :func:`_within`, each query looking in the cells (side ``cell``)
    its radius reaches; all queries at once (where :meth:`_PointGrid.near` answers one at a time).

    Parameters
    ----------
    P, Q : numpy.ndarray
        (n, 2) points and (m, 2) queries.
    r : numpy.ndarray
        (m,) radius of each query.
    cell : float
        Cell side.

    Returns
    -------
    q, p : numpy.ndarray
        Index pairs, by query, then cell, then point.
    """
    none = np.zeros(0, np.int64)
    r = np.asarray(r, np.float64)
    if not len(P) or not len(Q):
        return none, none
    reach = np.ceil(r / cell).astype(np.int64)             # cells each way
    cp, cq = np.floor(P / cell).astype(np.int64), np.floor(Q / cell).astype(np.int64)
    base = np.minimum(cp.min(axis=0), cq.min(axis=0)) - int(reach.max())
    cp, cq = cp - base, cq - base
    span = int(max(cp[:, 1].max(), cq[:, 1].max()) + reach.max() + 1)
    key = cp[:, 0] * span + cp[:, 1]
    order = np.argsort(key, kind="stable")
    skey = key[order]
    out_q, out_p = [], []
    for k in np.unique(reach).tolist():
        sel = np.flatnonzero(reach == k)
        step = np.arange(-k, k + 1)
        look = ((cq[sel, 0] * span + cq[sel, 1])[:, None] + (step[:, None] * span + step).ravel()).ravel()
        n, p = _in_cells(order, skey, look)
        if not len(p):
            continue
        q = np.repeat(np.repeat(sel, (2 * k + 1) ** 2), n)
        d = P[p] - Q[q]
        ok = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] <= r[q] * r[q]
        out_q.append(q[ok]), out_p.append(p[ok])
    if not out_q:
        return none, none
    q, p = np.concatenate(out_q), np.concatenate(out_p)
    by_query = np.argsort(q, kind="stable")
    return q[by_query], p[by_query]


#: Points whose cell neighbours :func:`near_pairs` looks up at once: its candidate pairs (tens per
#: point) then stay a few megabytes, the size of one drawing's, however large the page.
NEAR_PAIRS_CHUNK = 16384


def near_pairs(P: np.ndarray, r: float, keep=None, chunk: int = NEAR_PAIRS_CHUNK) -> tuple[np.ndarray, np.ndarray]:
    """All pairs i < j of points within ``r`` of each other, by square cells of side ``r``.

    Each point meets the points of its own cell and of four of its neighbours (the other four see it
    from theirs): time ∝ the pairs within ~2r, linear in the ink for a bounded width. A grid of our
    own, not a k-d tree: a λ re-run of the export imports no ``scipy.spatial`` (tests/stages/test_export.py).

    Parameters
    ----------
    P : numpy.ndarray
        (n, 2) points.
    r : float
        Largest distance (also the cell side).
    keep : callable, optional
        ``keep(i, j, d)`` → bool mask of the pairs (index arrays, distances) to return: applied to
        ``chunk`` points' pairs at a time, so that only the kept pairs of a large page are ever held.
    chunk : int
        Points whose pairs are found at once (the result does not depend on it).

    Returns
    -------
    i, j : numpy.ndarray
        The pairs, ordered by the neighbour cell they were found in, then ``i``, then ``j``'s place in
        its cell (the order of one pass over all points).
    """
    none = np.zeros(0, np.int64)
    if len(P) < 2 or r <= 0:
        return none, none
    cell = np.floor(P / r).astype(np.int64)
    cell -= cell.min(axis=0)
    span = int(cell[:, 1].max()) + 3
    key = (cell[:, 0] + 1) * span + cell[:, 1] + 1
    order = np.argsort(key, kind="stable")
    skey = key[order]
    out_i, out_j, out_o = [], [], []
    for s0 in range(0, len(P), max(int(chunk), 1)):
        ckey = key[s0:s0 + chunk]
        for o, (dx, dy) in enumerate(((0, 0), (1, -1), (1, 0), (1, 1), (0, 1))):
            n, dst = _in_cells(order, skey, ckey + dx * span + dy)
            if not len(dst):
                continue
            src = s0 + np.repeat(np.arange(len(ckey)), n)
            if (dx, dy) == (0, 0):
                src, dst = src[src < dst], dst[src < dst]
            d = np.hypot(*(P[src] - P[dst]).T)
            near = d <= r
            if keep is not None:
                near &= keep(src, dst, d)
            out_i.append(src[near]), out_j.append(dst[near]), out_o.append(np.full(int(near.sum()), o, np.int8))
    if not out_i:
        return none, none
    # Chunk by chunk, the pairs come neighbour cell by neighbour cell: put them back into one pass's order.
    by_cell = np.argsort(np.concatenate(out_o), kind="stable")
    return np.concatenate(out_i)[by_cell], np.concatenate(out_j)[by_cell]
