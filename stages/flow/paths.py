"""Preparation of the flow: every path resampled uniformly and its barrier centres, vectorised over all
paths (the blocks the kernel of :mod:`stages.flow.kernel` runs on).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from stages.artifact import pack_ragged

if TYPE_CHECKING:
    from stages.flow import FlowConfig


def _local_arclength(xy: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Cumulative arc length of every point within its own path (0 at each path's start)."""
    n = len(xy)
    seg = np.zeros(n)
    if n > 1:
        seg[1:] = np.hypot(xy[1:, 0] - xy[:-1, 0], xy[1:, 1] - xy[:-1, 1])
    seg[offsets[:-1][offsets[:-1] < n]] = 0.0
    cum = np.cumsum(seg)
    lengths = np.diff(offsets)
    return cum - np.repeat(cum[offsets[:-1]] if n else np.zeros(0), lengths)


def _global_param(local: np.ndarray, offsets: np.ndarray, totals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map per-path parameters onto one strictly increasing axis (for a single ``np.interp``).

    Returns the mapped knots and each path's base; a query ``u`` on path ``p`` maps to ``u + base[p]``.
    """
    lengths = np.diff(offsets)
    base = np.zeros(len(lengths))
    if len(lengths) > 1:
        base[1:] = np.cumsum(totals[:-1] + 1.0)
    idx_local = np.arange(len(local)) - np.repeat(offsets[:-1], lengths)
    # Repeated points would give repeated knots; a sub-nanometre ramp keeps them increasing.
    return local + 1e-9 * idx_local + np.repeat(base, lengths), base


@dataclass
class _Batch:
    """All paths of a drawing, packed for the kernel (flat arrays + offsets)."""

    z: np.ndarray          # complex128 (Nv,) resampled vertices
    zoff: np.ndarray       # int64 (P+1,)
    centres: np.ndarray    # complex128 (Nc,) barrier centres
    sigma: np.ndarray      # float64 (Nc,)
    rho2: np.ndarray       # float64 (Nc,) squared safe radius: S ≥ 1 within it (no need to sum)
    dist: np.ndarray       # float64 (Nc,) interest distance carried by each centre
    coff: np.ndarray       # int64 (P+1,)
    home: np.ndarray       # int64 (Nv,) local centre index of edge j's midpoint (slot 0 unused)
    window: np.ndarray     # int64 (P,) half-width of the centre window


def _safe_radius(centres: np.ndarray, sigma: np.ndarray, coff: np.ndarray, cutoff: float) -> np.ndarray:
    """Radius around each barrier centre inside which S ≥ 1 is guaranteed (so B = 0 and ∇B = 0).

    A point at distance δ from centre k is at most δ + |c_k − c_j| from its neighbours j = k ± 1, so
    S ≥ exp(−δ²/2σ_k²) + Σ_j exp(−(δ + |c_k − c_j|)²/2σ_j²) (terms beyond the cut-off dropped).  The
    radius is the largest δ keeping this lower bound ≥ 1 (bisection); 0 where even δ = 0 fails.
    """
    nc = len(centres)
    first = np.zeros(nc, bool)
    first[coff[:-1][coff[:-1] < nc]] = True
    last = np.zeros(nc, bool)
    last[(coff[1:] - 1)[coff[1:] > coff[:-1]]] = True
    nb = []
    for shift, invalid in ((-1, first), (1, last)):
        j = np.clip(np.arange(nc) + shift, 0, max(nc - 1, 0))
        dkj = np.abs(centres - centres[j])
        nb.append((dkj, sigma[j], ~invalid))

    def bound(delta):
        val = np.exp(-0.5 * delta ** 2 / sigma ** 2)
        for dkj, sj, ok in nb:
            r = delta + dkj
            val = val + np.where(ok & (r * r < cutoff ** 2 * sj ** 2), np.exp(-0.5 * r ** 2 / sj ** 2), 0.0)
        return val

    lo = np.zeros(nc)
    hi = cutoff * sigma
    good = bound(lo) >= 1.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        ok = bound(mid) >= 1.0
        lo = np.where(ok, mid, lo)
        hi = np.where(ok, hi, mid)
    return np.where(good, lo, 0.0)


def prepare_paths(xys: list[np.ndarray], widths: list[np.ndarray], interest: list[np.ndarray],
                  params: FlowConfig) -> _Batch:
    """Resample every path and place its barrier centres.

    Parameters
    ----------
    xys : list of numpy.ndarray
        Initial polylines, each (n, 2) in (x, y), corner origin.
    widths, interest : list of numpy.ndarray
        Per initial vertex: stroke width (px) and graph distance to the nearest high-valence
        vertex or path end (px).
    params : FlowConfig

    Returns
    -------
    _Batch
    """
    npath = len(xys)
    xy, off = pack_ragged([np.asarray(a, dtype=np.float64).reshape(-1, 2) for a in xys], dtype=np.float64)
    xy = xy.reshape(-1, 2)
    w, _ = pack_ragged([np.asarray(a, dtype=np.float64).ravel() for a in widths], dtype=np.float64)
    dd, _ = pack_ragged([np.asarray(a, dtype=np.float64).ravel() for a in interest], dtype=np.float64)
    counts = np.diff(off)
    s = _local_arclength(xy, off)
    total = s[off[1:] - 1] if npath else np.zeros(0)
    gs, base = _global_param(s, off, total)

    # Vertices: uniform in arc length, `spacing` apart (at least the two ends).
    nv = np.maximum(np.ceil(total / params.spacing).astype(np.int64), 1) + 1
    nv[counts == 1] = 2
    zoff = np.zeros(npath + 1, dtype=np.int64)
    np.cumsum(nv, out=zoff[1:])
    vpath = np.repeat(np.arange(npath), nv)
    vloc = np.arange(zoff[-1]) - zoff[:-1][vpath]
    sv = vloc / np.maximum(nv - 1, 1)[vpath] * total[vpath]
    gq = sv + base[vpath]
    z = np.interp(gq, gs, xy[:, 0]) + 1j * np.interp(gq, gs, xy[:, 1])
    # Exact endpoints (they are the keypoints and stay fixed).
    z[zoff[:-1]] = xy[off[:-1], 0] + 1j * xy[off[:-1], 1]
    z[zoff[1:] - 1] = xy[off[1:] - 1, 0] + 1j * xy[off[1:] - 1, 1]

    # Barrier centres: uniform in u = ∫ ds/σ, `barrier_spacing` apart.
    sig = np.maximum(w / params.barrier.sigma_scale, params.barrier.sigma_min)
    du = np.zeros(len(xy))
    if len(xy) > 1:
        du[1:] = (s[1:] - s[:-1]) * 0.5 * (1.0 / sig[1:] + 1.0 / sig[:-1])
    du[off[:-1]] = 0.0
    u = np.cumsum(du)
    u = u - np.repeat(u[off[:-1]], counts)
    utot = u[off[1:] - 1]
    gu, ubase = _global_param(u, off, utot)
    nc = np.maximum(np.ceil(utot / params.barrier.spacing).astype(np.int64), 1) + 1
    coff = np.zeros(npath + 1, dtype=np.int64)
    np.cumsum(nc, out=coff[1:])
    cpath = np.repeat(np.arange(npath), nc)
    cloc = np.arange(coff[-1]) - coff[:-1][cpath]
    uc = cloc / (nc - 1)[cpath] * utot[cpath]
    sc = np.interp(uc + ubase[cpath], gu, s)           # arc length of each centre
    gcs = sc + base[cpath]
    centres = np.interp(gcs, gs, xy[:, 0]) + 1j * np.interp(gcs, gs, xy[:, 1])
    csig = np.maximum(np.interp(gcs, gs, w) / params.barrier.sigma_scale, params.barrier.sigma_min)
    cdist = np.interp(gcs, gs, dd)

    # Home centre of each edge midpoint: nearest in arc length (the kernel refines it spatially).
    smid = sv - 0.5 * (total / np.maximum(nv - 1, 1))[vpath]
    key_c = gcs
    key_m = smid + base[vpath]
    pos = np.searchsorted(key_c, key_m)
    lo = np.clip(pos - 1, coff[:-1][vpath], coff[1:][vpath] - 1)
    hi = np.clip(pos, coff[:-1][vpath], coff[1:][vpath] - 1)
    pick = np.where(np.abs(key_c[hi] - key_m) < np.abs(key_c[lo] - key_m), hi, lo)
    home = (pick - coff[:-1][vpath]).astype(np.int64)
    window = np.ceil(params.barrier.cutoff / params.barrier.spacing).astype(np.int64) + 2
    window = np.full(npath, window, dtype=np.int64)
    rho = _safe_radius(centres, csig, coff, params.barrier.cutoff)
    return _Batch(z=z.astype(np.complex128), zoff=zoff, centres=centres.astype(np.complex128), sigma=csig,
                  rho2=rho * rho, dist=cdist, coff=coff, home=home, window=window)


