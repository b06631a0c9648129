"""Pixel and vertex coverage of paths over the drawing graph (paper §4.2 "Covering the drawing").

The *thickened* version of a path is the union, over its edges, of the tapered capsules around each
segment whose radius is interpolated linearly between the end vertices' radii
``width / 2 + margin``.  A band pixel is covered when its centre lies inside; a graph vertex is
covered when its position does (same region, one definition for both).

Since every path the stage handles is made of graph edges, coverage is precomputed once per edge
(:func:`edge_coverage`) and a path's coverage is the union of its edges'.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import cKDTree


def capsule_members(points: np.ndarray, tree: cKDTree, a: np.ndarray, b: np.ndarray,
                    ra: np.ndarray, rb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which points lie in each tapered capsule.

    Parameters
    ----------
    points : numpy.ndarray
        (P, 2) in (x, y); ``tree`` is their KD-tree.
    a, b : numpy.ndarray
        (S, 2) segment ends (x, y).
    ra, rb : numpy.ndarray
        (S,) radii at ``a`` and ``b``.

    Returns
    -------
    flat, offsets : numpy.ndarray
        int64 CSR: segment ``s`` holds ``flat[offsets[s]:offsets[s + 1]]`` (point indices, sorted).
    """
    s = len(a)
    offsets = np.zeros(s + 1, np.int64)
    if s == 0 or len(points) == 0:
        return np.zeros(0, np.int64), offsets
    mid = 0.5 * (a + b)
    reach = 0.5 * np.hypot(*(b - a).T) + np.maximum(ra, rb) + 1e-9
    lists = tree.query_ball_point(mid, reach, return_sorted=True)
    counts = np.fromiter((len(x) for x in lists), np.int64, count=s)
    cand = np.fromiter(itertools.chain.from_iterable(lists), np.int64, count=int(counts.sum()))
    seg = np.repeat(np.arange(s), counts)
    keep = _in_capsule(points[cand, 0], points[cand, 1], seg, a, b, ra, rb)
    np.cumsum(np.bincount(seg[keep], minlength=s), out=offsets[1:])
    return cand[keep], offsets


def _in_capsule(px: np.ndarray, py: np.ndarray, seg: np.ndarray, a: np.ndarray, b: np.ndarray, ra: np.ndarray,
                rb: np.ndarray) -> np.ndarray:
    """Whether point ``(px, py)`` lies in the tapered capsule of segment ``seg`` (one test, both callers)."""
    d = b[seg] - a[seg]
    ll = np.maximum((d * d).sum(1), 1e-18)
    rx, ry = px - a[seg, 0], py - a[seg, 1]
    t = np.clip((rx * d[:, 0] + ry * d[:, 1]) / ll, 0.0, 1.0)
    dist = np.hypot(rx - t * d[:, 0], ry - t * d[:, 1])
    return dist <= ra[seg] + t * (rb[seg] - ra[seg])


def band_capsule_members(mask: np.ndarray, a: np.ndarray, b: np.ndarray, ra: np.ndarray, rb: np.ndarray,
                         chunk: int = 250_000) -> tuple[np.ndarray, np.ndarray]:
    """:func:`capsule_members` for the band pixel centres of ``mask``, by scanning each capsule's box.

    The points are the pixel grid, so each capsule's candidates are the pixels of its bounding box:
    no KD-tree query and no per-segment Python lists (a 4×-upscaled scan's coverage spent most of
    its time there). Segments are taken in chunks of about ``chunk`` candidate pixels, which bounds
    the memory (a chunk's temporaries take about 120 bytes per candidate: 250 k keep them near
    30 MB, at no cost in time — 2 M took 250 MB). The pixel → band index table is int32 (the
    only page-sized array here). Point indices follow ``np.nonzero(mask)`` (:func:`band_pixels`).
    """
    mask = np.asarray(mask, bool)
    s = len(a)
    offsets = np.zeros(s + 1, np.int64)
    if s == 0 or not mask.any():
        return np.zeros(0, np.int64), offsets
    h, w = mask.shape
    index = np.full(mask.shape, -1, np.int32)
    index[mask] = np.arange(int(mask.sum()), dtype=np.int32)
    # Pixel (i, j) has its centre at (j + 0.5, i + 0.5); a one-pixel margin keeps the box a superset.
    lo = np.minimum(a - ra[:, None], b - rb[:, None])
    hi = np.maximum(a + ra[:, None], b + rb[:, None])
    j0 = np.clip(np.floor(lo[:, 0] - 0.5).astype(np.int64) - 1, 0, w)
    j1 = np.clip(np.ceil(hi[:, 0] - 0.5).astype(np.int64) + 1, -1, w - 1)
    i0 = np.clip(np.floor(lo[:, 1] - 0.5).astype(np.int64) - 1, 0, h)
    i1 = np.clip(np.ceil(hi[:, 1] - 0.5).astype(np.int64) + 1, -1, h - 1)
    nx, ny = np.maximum(j1 - j0 + 1, 0), np.maximum(i1 - i0 + 1, 0)
    area = nx * ny
    ends = np.cumsum(area)
    members, counts = [], np.zeros(s, np.int64)
    start = 0
    while start < s:
        before = int(ends[start - 1]) if start else 0
        stop = max(int(np.searchsorted(ends, before + chunk, side="right")), start + 1)
        seg = np.repeat(np.arange(start, stop), area[start:stop])
        k = np.arange(len(seg)) - np.repeat(ends[start:stop] - area[start:stop] - before, area[start:stop])
        ii = i0[seg] + k // nx[seg]
        jj = j0[seg] + k % nx[seg]
        idx = index[ii, jj]
        inband = idx >= 0
        seg, ii, jj, idx = seg[inband], ii[inband], jj[inband], idx[inband]
        keep = _in_capsule(jj + 0.5, ii + 0.5, seg, a, b, ra, rb)
        members.append(idx[keep].astype(np.int64))
        counts[start:stop] = np.bincount(seg[keep] - start, minlength=stop - start)
        start = stop
    np.cumsum(counts, out=offsets[1:])
    return np.concatenate(members), offsets


def band_pixels(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Band pixel centres (x, y) and their flat indices ``row * W + col``."""
    ii, jj = np.nonzero(mask)
    return np.stack([jj + 0.5, ii + 0.5], axis=1).astype(np.float64), (ii * mask.shape[1] + jj).astype(np.int64)


def edge_coverage(xy: np.ndarray, width: np.ndarray, edges: np.ndarray, comp_of: np.ndarray,
                  mask: np.ndarray, margin: float):
    """Per graph edge: the band pixels and the same-component vertices its thickened segment covers.

    Returns
    -------
    (pix_flat, pix_off), (ver_flat, ver_off)
        CSR per edge; pixel entries index the band pixels of ``mask`` (:func:`band_pixels` order),
        vertex entries index ``xy``.
    """
    a, b = xy[edges[:, 0]], xy[edges[:, 1]]
    ra = width[edges[:, 0]] / 2 + margin
    rb = width[edges[:, 1]] / 2 + margin
    pix = band_capsule_members(mask, a, b, ra, rb)
    vflat, voff = capsule_members(xy, cKDTree(xy), a, b, ra, rb) if len(xy) else \
        (np.zeros(0, np.int64), np.zeros(len(edges) + 1, np.int64))
    # Only a component's own subgraph covers its vertices (components are processed independently).
    seg = np.repeat(np.arange(len(edges)), np.diff(voff))
    keep = comp_of[vflat] == comp_of[edges[seg, 0]]
    voff2 = np.zeros_like(voff)
    np.cumsum(np.bincount(seg[keep], minlength=len(edges)), out=voff2[1:])
    return pix, (vflat[keep], voff2)


def gather(flat: np.ndarray, offsets: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Concatenation of the CSR rows ``rows`` (may repeat entries)."""
    rows = np.asarray(rows, np.int64)
    if len(rows) == 0:
        return np.zeros(0, flat.dtype)
    starts, ends = offsets[rows], offsets[rows + 1]
    lengths = ends - starts
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, flat.dtype)
    base = np.repeat(starts - np.concatenate([[0], np.cumsum(lengths)[:-1]]), lengths)
    return flat[base + np.arange(total)]


class CoverageState:
    """Coverage of a growing subgraph: covered band pixels and covered vertices.

    Arrays are global (whole drawing); :meth:`reset` clears only what was set, so processing many
    components stays linear in their sizes.
    """

    def __init__(self, n_pixels: int, n_vertices: int, pix_csr, ver_csr):
        self.pixel = np.zeros(n_pixels, bool)
        self.vertex = np.zeros(n_vertices, bool)
        self.pix_flat, self.pix_off = pix_csr
        self.ver_flat, self.ver_off = ver_csr
        self._touched_px: list[np.ndarray] = []
        self._touched_v: list[np.ndarray] = []

    def new_pixels(self, edge_ids) -> int:
        """How many band pixels the edges would newly cover."""
        px = np.unique(gather(self.pix_flat, self.pix_off, edge_ids))
        return int((~self.pixel[px]).sum())

    def add(self, edge_ids, vertices) -> None:
        """Cover the thickened edges and the given vertices."""
        px = gather(self.pix_flat, self.pix_off, edge_ids)
        vv = np.concatenate([gather(self.ver_flat, self.ver_off, edge_ids), np.asarray(vertices, np.int64)])
        self.pixel[px] = True
        self.vertex[vv] = True
        self._touched_px.append(px)
        self._touched_v.append(vv)

    def reset(self) -> None:
        """Clear everything covered so far."""
        for px in self._touched_px:
            self.pixel[px] = False
        for vv in self._touched_v:
            self.vertex[vv] = False
        self._touched_px.clear()
        self._touched_v.clear()
