"""PolyVector flow of the candidate paths (paper §5, Eq. 4–10; authors' ``FrameFieldFlow.cpp``).

Every allowed path from the topology stage is deformed, endpoints fixed, by the L2 gradient flow of
the anisotropic, position-varying length (Eq. 6a)

    E(x) = ∫_Γ ( |f(x, τ)|² + b(x) ) dl,   f(x, z) = z⁴ + c2(x) z² + c0(x),   τ = tangent,
    b(x) = max(1 − S(x), 0) + λ,            S(x) = Σ_k exp(−|x − p_k|² / 2σ_k²)          (Eq. 5)

where c0, c2 is the frame field extended beyond the band (field artifact ``c0_ext``, ``c2_ext``),
``p_k`` are barrier centres along the path's *initial* polyline and ``σ_k = width/6`` (3σ rule).
Points are (x, y) in pixel units, x right, y down, origin at the top-left corner of the top-left pixel;
positions are handled as complex numbers ``z = x + 1j*y``.

Discretisation (paper §5.4).  Vertices ``z_0 … z_{N−1}``, edges ``t_j = z_j − z_{j−1}``, midpoints
``m_j``, regularised length element ``q_j = √(|t_j|² + ε)`` and tangent ``τ_j = t_j / q_j`` (the
paper's).  The discrete energy — what the flow lowers and what the MIP reads — is

    E_ε = Σ_j W_j q_j,   W_j = g_j + B_j + λ,   g_j = |f(m_j, τ_j)|²,   B_j = max(1 − S(m_j), 0).

One iteration solves, for the interior vertices, the tridiagonal system

    M_j (z_j − z_j^old) + k_j t_j − k_{j+1} t_{j+1} = −(A_j − A_{j+1}) − (P_j + P_{j+1}),

    M_j = (q_j + q_{j+1}) / (2 α s_j)        lumped mass; time step α (``dt``) scaled by s_j
    k_j = W_j / q_j                          isotropic length, implicit (t at the new positions)
    A_j = q_j ∂g_j/∂t_j                      anisotropy, explicit
    P_j = (q_j / 2) ∇_x(g + B)(m_j)          position dependence of field and barrier, explicit

with all coefficients from the previous iterate.  ``k t + A + P`` is the exact gradient of ``E_ε``
(tested against finite differences), so a fixed point is a stationary point of the reported energy.
The matrix is real, symmetric and diagonally dominant (one Thomas sweep, complex right-hand side).

Choices made on purpose (vs. the paper and the authors' code)
------------------------------------------------------------
* **Stage order: flow, then select.**  As in the authors' code (not the paper's narrative) every
  allowed path is flowed and the MIP chooses among the flowed curves with their energies as costs.
  This is our DAG (flow → select), and it lets a λ sweep re-run only flow → select → export.
* **What is implicit.**  Eq. 10 puts the complex ``G = g + i g'`` and the normal force ``F`` into the
  matrix.  With frozen coefficients that is not a linearisation and buys no stability: on the
  synthetic vee (real prep → field → graph → topology) that structure *raised* a path's energy by
  2 % over 1500 iterations at α = 1e-2 (it settles in a worse state after oscillating).  We keep only
  the isotropic part implicit (unconditionally stable) and the anisotropy explicit; with the step
  control below the same path's energy falls by 3 %, and the vee/zigzag/X/T/Y candidates end at
  equal or lower energies than with Eq. 10's structure.  We also take the *full* positional gradient
  (the paper keeps its normal component), so that a fixed point is a stationary point of E_ε.
* **Monotone energy.**  An iteration whose new curve has a higher E_ε than the previous one is
  undone and that path's step is halved (then regrown ×1.25 per accepted step up to α).  The flow
  therefore never raises a path's energy, whatever α; on drawings ~10 % of the iterations are undone,
  mostly near convergence where the bilinear field's kinks make tiny increases.  The iteration after
  an undo re-assembles the restored iterate's system from stored step-independent row coefficients
  (its edges were evaluated one iteration earlier) and is not checked again: its energy is known.
  The paper has no step control; the iteration count stays fixed (1500, no convergence test).
* **Bilinear field lookup with its exact derivative** (the field's
  :func:`stages.field.bilinear_coefficients` convention: pixel centres at +0.5, zero outside the
  image).  The code's nearest-pixel lookup with central differences and its √(ν₁² + 2ν₂) factor are
  not copied.
* **τ = t/q** as in the paper (and the code): the alignment term fades on edges shorter than √ε,
  which keeps its angular stiffness bounded; with the unit tangent short noisy edges collapsed.
* **Barrier = Eq. 5.**  ``B = max(1 − S, 0)`` enters both the length weight W and the force; its
  gradient is ``−∇S`` where ``S < 1`` and zero elsewhere — the code's "barrier force only where
  0 < S < 1" (beyond the 4σ cut-off S = 0 and there is no force either).  The code leaves B out of W.
* **Barrier centres** are placed uniformly in the σ-scaled arc length ``∫ ds/σ(s)`` of the initial
  polyline, ``barrier.spacing`` σ apart (default 1σ, "spaced ≤ σ" like the code's extra centres),
  with σ interpolated from the path widths and clamped below by ``barrier.sigma_min`` (σ = 0 would
  give NaNs).  Unlike the code's "every vertex + extras" this makes S independent of how densely the
  graph sampled the path: S ≈ √(2π)/spacing ≈ 2.5 on the initial curve, and B starts ≈ 1.35σ away.
  S is summed over the centres within ``barrier.cutoff``·σ in a window of centre indices around the
  nearest one ("home" centre, tracked as the curve moves), so other parts of the same path (a
  hairpin) do not count.  Inside a precomputed safe radius round the home centre S ≥ 1 is certain
  and nothing is summed; otherwise the sum stops once S ≥ 1.  Both shortcuts are exact for B.
* **Time-step scaling** ``s = clip(d0/d, s_min, s_max)`` with d the graph distance (topology
  ``interest_dist``) to the nearest high-valence vertex or path end.  With the code's d0 = 30,
  s_min = 0.1, s_max = 2 this *is* the code's rule "2 if d < 15 else max(0.1, 30/d)", i.e. the
  paper's "scale by the inverse distance" with caps: the flow moves curves most where the initial
  graph geometry is least reliable (near junctions and ends).  d is carried by the barrier centres,
  so it follows the vertices through resampling (the code indexes it by the stale vertex id).
* **α = 1e-2 and λ = 3** (``dt``, ``lam``), the code's values (the paper quotes δ = 5e-3).
* **Resampling.**  Each path is first resampled uniformly by arc length with ``spacing`` px (the code
  keeps the vertex count of the graph chain, whose density varies, so its g and ε act differently
  on every path); whenever the longest edge exceeds ``resample_factor`` × the initial mean edge it
  is resampled again to the same count.  With 0.75 px and factor 1.34 edges stay under one pixel,
  as the paper asks.  After a resampling the next step is accepted unconditionally (other
  discretisation).  The spacing sets the cost (the iteration count is fixed): 0.5 px gave 49 900
  vertices on the scanned elephant, 0.75 px gives 33 400 (flow CPU 4.2 → 2.8 s), and on
  realvec_dev (GT keypoints, 106 cases) 0.75 px scores as 0.5 px did — Hausdorff median 3.08 px
  both, endpoint F1 0.913 vs 0.909, junction F1 0.833 vs 0.831, Chamfer 0.152 vs 0.147 px,
  dangling 0.34 vs 0.31 per drawing; 1.0 px (edges up to 2 px) was worse (Hausdorff 3.16 px,
  Chamfer 0.150).  The authors' chains are denser still (~0.3 px in their example).
* **Energies (MIP cost)** are E_ε of the flowed curves: Eq. 6a with the Eq. 5 barrier, discretised as
  the flow sees it (uniform spacing makes it comparable between paths).  The code instead *adds* the
  Gaussian sum S to g in its MIP cost; S ≈ 2.5 along any curve that stayed in its tube, so that adds
  a roughly constant, sampling-dependent length penalty, and we drop it.
* **All paths in one compiled call.**  The paths are independent blocks of one block-tridiagonal
  system (the fixed endpoints decouple them); one numba kernel runs the whole iteration loop of
  every block, blocks in parallel (``prange``, longest first, one at a time), with the edge terms,
  the energy and the Thomas forward sweep fused in one pass.  ``scipy.linalg.solve_banded`` on the
  stacked system alone takes 4.8 ms per iteration (7 s for the run) before any of the per-edge work.
  What the kernel costs (CPU time per vertex and iteration, scanned elephant, 49 900 vertices, one
  thread): 64 ns as first written; 50 ns now — the field is stored with a one-pixel zero border
  (no per-corner bounds tests in the bilinear lookup), ∂(q g)/∂t is formed from conj(A) (no
  1/|t|², no complex division), divisions by real numbers are multiplications by a reciprocal, an
  undone step swaps two buffers instead of copying and the next iteration reuses the stored rows
  (−11 %), and the kernel is compiled with the fastmath
  flags ``contract, arcp, nsz, afn``.  ``reassoc`` would give another 10 % but lets LLVM vectorise
  reductions with an alignment-dependent order, which made the rejected-step count (and the
  last bits of the curves) differ from run to run; ``nnan``/``ninf`` are never used (the
  non-finite check must stay).  A block whose solve turns non-finite stops and keeps its last finite iterate
  (``data["failed"]``).

References
----------
.. [1] I. Puhachov, W. Neveu, E. Chien, M. Bessmeltsev, "Keypoint-Driven Line Drawing Vectorization
       via PolyVector Flow", ACM Trans. Graph. 40(6), 2021, §5.
.. [2] K. Deckelnick, G. Dziuk, C. M. Elliott, "Computation of geometric partial differential
       equations and mean curvature flow", Acta Numerica 14, 2005.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numba
import numpy as np

from stages.artifact import Artifact, pack_ragged
from stages.errors import InputError

STAGE_VERSION = "2"

_FM = {"contract", "arcp", "nsz", "afn"}


@dataclass(frozen=True)
class FlowParams:
    """The ``flow`` config section (``conf/flow/default.yaml``), one field per key."""

    iterations: int
    dt: float
    lam: float
    eps: float
    spacing: float
    resample_factor: float
    sigma_scale: float
    sigma_min: float
    barrier_spacing: float
    barrier_cutoff: float
    step_d0: float
    step_min: float
    step_max: float
    max_vertices: int

    @classmethod
    def from_cfg(cls, cfg: dict) -> "FlowParams":
        """Build from the config dict; every key must be present (no hidden defaults)."""
        try:
            b = cfg["barrier"]
            s = cfg["step_scale"]
            p = cls(iterations=int(cfg["iterations"]), dt=float(cfg["dt"]), lam=float(cfg["lam"]),
                    eps=float(cfg["eps"]), spacing=float(cfg["spacing"]),
                    resample_factor=float(cfg["resample_factor"]),
                    sigma_scale=float(b["sigma_scale"]), sigma_min=float(b["sigma_min"]),
                    barrier_spacing=float(b["spacing"]), barrier_cutoff=float(b["cutoff"]),
                    step_d0=float(s["d0"]), step_min=float(s["min"]), step_max=float(s["max"]),
                    max_vertices=int(cfg["max_vertices"]))
        except KeyError as e:
            raise InputError(f"flow config is missing key {e}") from None
        if p.iterations < 0 or p.dt <= 0 or p.lam < 0 or p.eps < 0 or p.spacing <= 0:
            raise InputError("flow config: need iterations ≥ 0, dt > 0, lam ≥ 0, eps ≥ 0, spacing > 0")
        if p.resample_factor <= 1 or p.sigma_scale <= 0 or p.sigma_min <= 0 or p.barrier_spacing <= 0:
            raise InputError("flow config: need resample_factor > 1, barrier sigma_scale, sigma_min, spacing > 0")
        if not (0 < p.step_min <= p.step_max) or p.step_d0 <= 0:
            raise InputError("flow config: need 0 < step_scale.min ≤ step_scale.max and d0 > 0")
        return p


def step_scale(d: np.ndarray, params: FlowParams) -> np.ndarray:
    """Per-vertex time-step factor ``clip(d0 / d, min, max)`` (= the code's 2 if d < 15 else max(0.1, 30/d)).

    Parameters
    ----------
    d : numpy.ndarray
        Graph distance (px) to the nearest high-valence vertex or path end.
    params : FlowParams
    """
    d = np.asarray(d, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return np.clip(params.step_d0 / np.maximum(d, 0.0), params.step_min, params.step_max)


# ---------------------------------------------------------------------------------------------
# Preparation: resampling and barrier centres, vectorised over all paths
# ---------------------------------------------------------------------------------------------

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
                  params: FlowParams) -> _Batch:
    """Resample every path and place its barrier centres.

    Parameters
    ----------
    xys : list of numpy.ndarray
        Initial polylines, each (n, 2) in (x, y), corner origin.
    widths, interest : list of numpy.ndarray
        Per initial vertex: stroke width (px) and graph distance to the nearest high-valence
        vertex or path end (px).
    params : FlowParams

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
    sig = np.maximum(w / params.sigma_scale, params.sigma_min)
    du = np.zeros(len(xy))
    if len(xy) > 1:
        du[1:] = (s[1:] - s[:-1]) * 0.5 * (1.0 / sig[1:] + 1.0 / sig[:-1])
    du[off[:-1]] = 0.0
    u = np.cumsum(du)
    u = u - np.repeat(u[off[:-1]], counts)
    utot = u[off[1:] - 1]
    gu, ubase = _global_param(u, off, utot)
    nc = np.maximum(np.ceil(utot / params.barrier_spacing).astype(np.int64), 1) + 1
    coff = np.zeros(npath + 1, dtype=np.int64)
    np.cumsum(nc, out=coff[1:])
    cpath = np.repeat(np.arange(npath), nc)
    cloc = np.arange(coff[-1]) - coff[:-1][cpath]
    uc = cloc / (nc - 1)[cpath] * utot[cpath]
    sc = np.interp(uc + ubase[cpath], gu, s)           # arc length of each centre
    gcs = sc + base[cpath]
    centres = np.interp(gcs, gs, xy[:, 0]) + 1j * np.interp(gcs, gs, xy[:, 1])
    csig = np.maximum(np.interp(gcs, gs, w) / params.sigma_scale, params.sigma_min)
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
    window = np.ceil(params.barrier_cutoff / params.barrier_spacing).astype(np.int64) + 2
    window = np.full(npath, window, dtype=np.int64)
    rho = _safe_radius(centres, csig, coff, params.barrier_cutoff)
    return _Batch(z=z.astype(np.complex128), zoff=zoff, centres=centres.astype(np.complex128), sigma=csig,
                  rho2=rho * rho, dist=cdist, coff=coff, home=home, window=window)


# ---------------------------------------------------------------------------------------------
# The kernel
# ---------------------------------------------------------------------------------------------

@numba.njit(cache=True, inline="always", error_model="numpy", fastmath=_FM)
def _bilinear(c: np.ndarray, x: float, y: float):
    """Bilinear value and exact x/y derivatives of a complex pixel-centre grid at (x, y).

    Pixel ``[i, j]`` has its centre at ``(j + .5, i + .5)``; samples outside the image count as 0.
    """
    h, w = c.shape
    u = x - 0.5
    v = y - 0.5
    j0 = int(math.floor(u))
    i0 = int(math.floor(v))
    fu = u - j0
    fv = v - i0
    c00 = c[i0, j0] if (0 <= i0 < h and 0 <= j0 < w) else 0j
    c01 = c[i0, j0 + 1] if (0 <= i0 < h and 0 <= j0 + 1 < w) else 0j
    c10 = c[i0 + 1, j0] if (0 <= i0 + 1 < h and 0 <= j0 < w) else 0j
    c11 = c[i0 + 1, j0 + 1] if (0 <= i0 + 1 < h and 0 <= j0 + 1 < w) else 0j
    val = (1 - fu) * (1 - fv) * c00 + fu * (1 - fv) * c01 + (1 - fu) * fv * c10 + fu * fv * c11
    dx = (1 - fv) * (c01 - c00) + fv * (c11 - c10)
    dy = (1 - fu) * (c10 - c00) + fu * (c11 - c01)
    return val, dx, dy


@numba.njit(cache=True, inline="always", error_model="numpy", fastmath=_FM)
def _bilinear_field(fld: np.ndarray, x: float, y: float):
    """c0, ∂c0/∂x, ∂c0/∂y, c2, ∂c2/∂x, ∂c2/∂y at (x, y) from the packed field (as :func:`_bilinear`).

    ``fld`` has a one-pixel zero border (:func:`_pack_field`), so a cell that touches the image needs
    no per-corner bounds test; a cell wholly outside it is zero.
    """
    h = fld.shape[0] - 2
    w = fld.shape[1] - 2
    u = x - 0.5
    v = y - 0.5
    if not (-1.0 <= u < w and -1.0 <= v < h):
        return 0j, 0j, 0j, 0j, 0j, 0j
    j0 = int(math.floor(u))
    i0 = int(math.floor(v))
    fu = u - j0
    fv = v - i0
    a = fld[i0 + 1, j0 + 1]
    b = fld[i0 + 1, j0 + 2]
    c = fld[i0 + 2, j0 + 1]
    d = fld[i0 + 2, j0 + 2]
    p00, r00 = complex(a[0], a[1]), complex(a[2], a[3])
    p01, r01 = complex(b[0], b[1]), complex(b[2], b[3])
    p10, r10 = complex(c[0], c[1]), complex(c[2], c[3])
    p11, r11 = complex(d[0], d[1]), complex(d[2], d[3])
    w00 = (1 - fu) * (1 - fv)
    w01 = fu * (1 - fv)
    w10 = (1 - fu) * fv
    w11 = fu * fv
    a0 = w00 * p00 + w01 * p01 + w10 * p10 + w11 * p11
    a0x = (1 - fv) * (p01 - p00) + fv * (p11 - p10)
    a0y = (1 - fu) * (p10 - p00) + fu * (p11 - p01)
    a2 = w00 * r00 + w01 * r01 + w10 * r10 + w11 * r11
    a2x = (1 - fv) * (r01 - r00) + fv * (r11 - r10)
    a2y = (1 - fu) * (r10 - r00) + fu * (r11 - r01)
    return a0, a0x, a0y, a2, a2x, a2y


@numba.njit(cache=True)
def bilinear_with_gradient(c: np.ndarray, xy: np.ndarray):
    """Bilinear interpolation of a complex grid and its exact gradient at many points.

    Parameters
    ----------
    c : numpy.ndarray
        complex128 (H, W), pixel centres at +0.5, 0 outside the image.
    xy : numpy.ndarray
        float64 (n, 2) points (x, y), corner origin.

    Returns
    -------
    val, dx, dy : numpy.ndarray
        complex128 (n,) each.
    """
    n = xy.shape[0]
    val = np.empty(n, np.complex128)
    dx = np.empty(n, np.complex128)
    dy = np.empty(n, np.complex128)
    for k in range(n):
        val[k], dx[k], dy[k] = _bilinear(c, xy[k, 0], xy[k, 1])
    return val, dx, dy


@numba.njit(cache=True, inline="always", error_model="numpy", fastmath=_FM)
def _update_home(cen, c0i, nc, mx, my, h):
    """Walk the home centre index downhill in distance to (mx, my); returns it and its squared distance."""
    best = (cen[c0i + h].real - mx) ** 2 + (cen[c0i + h].imag - my) ** 2
    for _ in range(nc):
        moved = False
        if h + 1 < nc:
            d = (cen[c0i + h + 1].real - mx) ** 2 + (cen[c0i + h + 1].imag - my) ** 2
            if d < best:
                best = d
                h += 1
                moved = True
        if not moved and h - 1 >= 0:
            d = (cen[c0i + h - 1].real - mx) ** 2 + (cen[c0i + h - 1].imag - my) ** 2
            if d < best:
                best = d
                h -= 1
                moved = True
        if not moved:
            break
    return h, best


@numba.njit(cache=True, inline="always", error_model="numpy", fastmath=_FM)
def _barrier(cen, sig, rho2, c0i, nc, win, cut2, mx, my, h, d2h):
    """Eq. 5 barrier ``B = max(1 − S, 0)`` and its gradient at (mx, my) from the centres near ``h``.

    ``d2h`` is the squared distance to the home centre; within its safe radius S ≥ 1 is certain.
    """
    if d2h < rho2[c0i + h]:
        return 0.0, 0.0, 0.0
    s = 0.0
    gx = 0.0
    gy = 0.0
    for r in range(win + 1):
        for sgn in (1, -1):
            if r == 0 and sgn == -1:
                continue
            k = h + sgn * r
            if k < 0 or k >= nc:
                continue
            dx = mx - cen[c0i + k].real
            dy = my - cen[c0i + k].imag
            s2 = sig[c0i + k] * sig[c0i + k]
            d2 = dx * dx + dy * dy
            if d2 < cut2 * s2:
                e = math.exp(-0.5 * d2 / s2)
                s += e
                gx -= e * dx / s2
                gy -= e * dy / s2
        if s >= 1.0:
            return 0.0, 0.0, 0.0
    return 1.0 - s, -gx, -gy


@numba.njit(cache=True, inline="always", error_model="numpy", fastmath=_FM)
def _edge_terms(fld, t, m, eps):
    """One edge's alignment term with the regularised tangent τ = t/q (paper §5.4).

    Returns ``g = |f(m, τ)|²``, ``ft = ∂(q·g)/∂t`` (as x + iy: the exact derivative of the edge's
    alignment energy with respect to its edge vector t), ``∇_x g`` at the midpoint and ``q``.
    """
    l2 = t.real * t.real + t.imag * t.imag
    q = math.sqrt(l2 + eps)
    rq = 1.0 / q
    tau = complex(t.real * rq, t.imag * rq)
    a0, a0x, a0y, a2, a2x, a2y = _bilinear_field(fld, m.real, m.imag)
    tau2 = tau * tau
    f = tau2 * tau2 + a2 * tau2 + a0
    fc = f.conjugate()
    g = f.real * f.real + f.imag * f.imag
    # ∂(q g)/∂t = 2 conj(A) − 2 Re(A t) t / q²  with  A = conj(f) f'(τ),  f'(τ) = τ (4τ² + 2 c2).
    # (Written with conj(A) rather than through the stiffness ft/t: no 1/|t|², no special case at t = 0.)
    am = fc * (tau * (4.0 * tau2 + 2.0 * a2))
    r = 2.0 * (am.real * t.real - am.imag * t.imag) * rq * rq
    ft = complex(2.0 * am.real - r * t.real, -2.0 * am.imag - r * t.imag)
    gx = 2.0 * (fc * (a2x * tau2 + a0x)).real
    gy = 2.0 * (fc * (a2y * tau2 + a0y)).real
    return g, ft, gx, gy, q


@numba.njit(cache=True, inline="always", error_model="numpy", fastmath=_FM)
def _edge(fld, cen, sig, rho2, c0i, nc, win, cut2, lam, eps, za, zb, home_j):
    """One edge za → zb of Eq. 6a, shared by the energy, its gradient and the flow kernel.

    Returns the edge vector ``t``, its weight ``W = g + B + λ``, ``q``, ``ft = ∂(q g)/∂t``,
    ``fm = ∂(W q)/∂z`` through the midpoint (the share of each of its two vertices) and the updated
    home centre index.
    """
    t = zb - za
    m = 0.5 * (zb + za)
    g, ft, gx, gy, q = _edge_terms(fld, t, m, eps)
    h, d2h = _update_home(cen, c0i, nc, m.real, m.imag, home_j)
    b, bx, by = _barrier(cen, sig, rho2, c0i, nc, win, cut2, m.real, m.imag, h, d2h)
    return t, g + b + lam, q, ft, (0.5 * q) * complex(gx + bx, gy + by), h


@numba.njit(cache=True)
def _path_energy(z, n, fld, cen, sig, rho2, c0i, nc, win, cut2, lam, eps, home):
    """Discrete Eq. 6a of one polyline, Σ (g + B + λ) q (updates the home indices)."""
    e = 0.0
    for j in range(1, n):
        _, w, q, _, _, home[j] = _edge(fld, cen, sig, rho2, c0i, nc, win, cut2, lam, eps, z[j - 1], z[j],
                                       home[j])
        e += w * q
    return e


@numba.njit(cache=True)
def _discrete_gradient(z, n, fld, cen, sig, rho2, c0i, nc, win, cut2, lam, eps, home):
    """∂E_ε/∂z_j (as x + iy) of every vertex from the kernel's edge coefficients (tests use this)."""
    grad = np.zeros(n, np.complex128)
    for j in range(1, n):
        t, w, q, ft, fm, home[j] = _edge(fld, cen, sig, rho2, c0i, nc, win, cut2, lam, eps, z[j - 1], z[j],
                                         home[j])
        kt = w / q * t + ft
        grad[j] += kt + fm
        grad[j - 1] += -kt + fm
    return grad


@numba.njit(cache=True)
def _resample(z, n, tmp, home, home_tmp):
    """Uniform arc-length resampling of z[:n] in place (ends kept); carries the home indices."""
    cum = np.empty(n)
    cum[0] = 0.0
    for j in range(1, n):
        cum[j] = cum[j - 1] + abs(z[j] - z[j - 1])
    total = cum[n - 1]
    if total <= 0.0:
        return
    tmp[0] = z[0]
    tmp[n - 1] = z[n - 1]
    seg = 1
    for k in range(1, n - 1):
        s = total * k / (n - 1)
        while seg < n - 1 and cum[seg] < s:
            seg += 1
        span = cum[seg] - cum[seg - 1]
        f = (s - cum[seg - 1]) / span if span > 0 else 0.0
        tmp[k] = z[seg - 1] + f * (z[seg] - z[seg - 1])
    # New edge k's midpoint lies at arc length (k − ½)·total/(n−1): inherit that old edge's home.
    seg = 1
    for k in range(1, n):
        s = total * (k - 0.5) / (n - 1)
        while seg < n - 1 and cum[seg] < s:
            seg += 1
        home_tmp[k] = home[seg]
    for k in range(n):
        z[k] = tmp[k]
    for k in range(1, n):
        home[k] = home_tmp[k]


@numba.njit(cache=True, parallel=True, error_model="numpy", fastmath=_FM)
def _flow_kernel(order, z, zoff, cen, sig, rho2, dist, coff, home, window, fld, iterations, dt, lam, eps,
                 resample_factor, cut2, d0, smin, smax, e_init, e_final, n_resample, n_reject, failed):
    """Run the PolyVector flow on every path block (in place on ``z`` and ``home``)."""
    npath = zoff.shape[0] - 1
    for i in numba.prange(npath):
        p = order[i]
        z0i = zoff[p]
        n = zoff[p + 1] - z0i
        c0i = coff[p]
        nc = coff[p + 1] - c0i
        win = window[p]
        zp = z[z0i:z0i + n]
        hp = home[z0i:z0i + n]
        e_init[p] = _path_energy(zp, n, fld, cen, sig, rho2, c0i, nc, win, cut2, lam, eps, hp)
        if n <= 2:
            e_final[p] = e_init[p]
            continue
        ell = 0.0
        for j in range(1, n):
            ell += abs(zp[j] - zp[j - 1])
        ell /= (n - 1)
        cp = np.empty(n)
        dp = np.empty(n, np.complex128)
        tmp = np.empty(n, np.complex128)
        # Two iterate buffers swapped on every step: an undo is a swap back, never a copy.
        cur = zp.copy()
        nxt = zp.copy()
        htmp = np.empty(n, np.int64)
        # Row coefficients that do not depend on the step (two slots: the current iterate's and the
        # previous one's), so that the iteration after an undone step re-assembles the restored
        # iterate's system with the halved step without evaluating its edges again.
        row_kp = np.empty((2, n))
        row_kc = np.empty((2, n))
        row_mb = np.empty((2, n))
        row_f = np.empty((2, n), np.complex128)
        slot = 0
        reuse = False
        lim2 = (resample_factor * ell) ** 2
        dtp = dt
        e_last = np.inf
        for it in range(iterations + 1):
            inv2dt = 1.0 / (2.0 * dtp)
            if reuse:
                # The iterate was just restored: its rows are stored in `slot`, its energy is e_last.
                for r in range(n - 2):
                    mass = row_mb[slot, r] * inv2dt
                    dia = mass + row_kp[slot, r] + row_kc[slot, r]
                    rhs = mass * cur[r + 1] + row_f[slot, r]
                    if r > 0:
                        dia += row_kp[slot, r] * cp[r - 1]
                        rhs += row_kp[slot, r] * dp[r - 1]
                    inv = 1.0 / dia
                    cp[r] = -row_kc[slot, r] * inv
                    dp[r] = complex(rhs.real * inv, rhs.imag * inv)
                reuse = False
                e_cur = e_last
            else:
                # One pass over the edges: edge j's terms complete row j − 1 (vertex j − 1), which is
                # assembled and forward-eliminated at once (Thomas); the energy comes for free.
                ws = 1 - slot
                e_cur = 0.0
                k_prev = 0.0
                f_prev = 0j
                q_prev = 0.0
                d_prev = 0.0
                for j in range(1, n):
                    # ft (anisotropy, ∂(q g)/∂t) and fm (∂(W q)/∂z via the midpoint) are explicit.
                    _, w, q, ft, fm, h = _edge(fld, cen, sig, rho2, c0i, nc, win, cut2, lam, eps, cur[j - 1], cur[j],
                                               hp[j])
                    hp[j] = h
                    e_cur += w * q
                    k_cur = w / q                                    # implicit: isotropic length
                    d_cur = dist[c0i + h]
                    if j >= 2:
                        r = j - 2
                        d = 0.5 * (d_prev + d_cur)
                        s = smax if d <= 0.0 else min(max(d0 / d, smin), smax)
                        mb = (q_prev + q) / s
                        mass = mb * inv2dt
                        dia = mass + k_prev + k_cur
                        # Vertex j − 1 ends edge j − 1 and starts edge j.
                        f0 = -(f_prev + fm - ft)
                        if r == 0:
                            f0 += k_prev * cur[0]
                        if j == n - 1:
                            f0 += k_cur * cur[n - 1]
                        row_kp[ws, r] = k_prev
                        row_kc[ws, r] = k_cur
                        row_mb[ws, r] = mb
                        row_f[ws, r] = f0
                        rhs = mass * cur[j - 1] + f0
                        if r > 0:
                            dia += k_prev * cp[r - 1]
                            rhs += k_prev * dp[r - 1]
                        inv = 1.0 / dia
                        cp[r] = -k_cur * inv
                        dp[r] = complex(rhs.real * inv, rhs.imag * inv)
                    k_prev = k_cur
                    f_prev = ft + fm
                    q_prev = q
                    d_prev = d_cur
                if e_cur > e_last + 1e-12 * abs(e_last):
                    # The last step raised the energy: undo it and halve this path's step.
                    cur, nxt = nxt, cur
                    dtp *= 0.5
                    n_reject[p] += 1
                    reuse = True
                    continue
                slot = ws
            if it == iterations:
                break
            e_last = e_cur
            dtp = min(dt, dtp * 1.25)
            # Back substitution into the spare buffer (row r is vertex r + 1), with the edge lengths.
            nxt[0] = cur[0]
            nxt[n - 1] = cur[n - 1]
            acc = 0.0
            longest = 0.0
            for r in range(n - 3, -1, -1):
                after = nxt[r + 2]                           # nxt[n - 1] is the fixed end
                if r == n - 3:
                    zr = dp[r]
                else:
                    zr = dp[r] - complex(cp[r] * after.real, cp[r] * after.imag)
                nxt[r + 1] = zr
                t = after - zr
                l2 = t.real * t.real + t.imag * t.imag
                acc += l2
                longest = max(longest, l2)
            t = nxt[1] - nxt[0]
            l2 = t.real * t.real + t.imag * t.imag
            acc += l2
            longest = max(longest, l2)
            if not math.isfinite(acc):
                failed[p] = it + 1
                break
            cur, nxt = nxt, cur
            if longest > lim2:
                _resample(cur, n, tmp, hp, htmp)
                n_resample[p] += 1
                e_last = np.inf   # another discretisation: energies are not comparable
        for j in range(n):
            zp[j] = cur[j]
        e_final[p] = _path_energy(zp, n, fld, cen, sig, rho2, c0i, nc, win, cut2, lam, eps, hp)


# ---------------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------------

def _pack_field(c0: np.ndarray, c2: np.ndarray) -> np.ndarray:
    """float64 (H + 2, W + 2, 4): real and imaginary parts of c0 and c2 with a one-pixel zero border.

    One pixel's coefficients share a cache line, and the border spares the kernel's bilinear lookup
    its per-corner bounds tests (the field is zero outside the image).
    """
    h, w = c0.shape
    fld = np.zeros((h + 2, w + 2, 4), np.float64)
    fld[1:-1, 1:-1] = np.stack([c0.real, c0.imag, c2.real, c2.imag], axis=-1)
    return fld


@dataclass
class FlowResult:
    """Flowed curves of a drawing.

    Attributes
    ----------
    curves : list of numpy.ndarray
        (n, 2) float64 polylines in (x, y), corner origin, endpoints = the initial ones.
    energies, energies_initial : numpy.ndarray
        Eq. 6a of the flowed and of the (resampled) initial curves.
    resamples : numpy.ndarray
        Resampling count per path.
    failed : numpy.ndarray
        0, or the iteration at which the path's solve turned non-finite (the path keeps its last
        finite iterate).
    """

    curves: list[np.ndarray]
    energies: np.ndarray
    energies_initial: np.ndarray
    resamples: np.ndarray
    failed: np.ndarray
    rejected: np.ndarray


def polyvector_flow(c0: np.ndarray, c2: np.ndarray, xys: list[np.ndarray], widths: list[np.ndarray],
                    interest: list[np.ndarray], params: FlowParams) -> FlowResult:
    """Flow every path to the frame field (all paths in one batched, compiled call).

    Parameters
    ----------
    c0, c2 : numpy.ndarray
        complex (H, W) extended PolyVector field (``c0_ext``, ``c2_ext``); pixel centres at +0.5.
    xys : list of numpy.ndarray
        Initial polylines (n, 2) in (x, y) pixel units, corner origin; the ends stay fixed.
    widths : list of numpy.ndarray
        Stroke width per initial vertex (px), for the barrier's σ = width / sigma_scale.
    interest : list of numpy.ndarray
        Graph distance per initial vertex to the nearest high-valence vertex or path end (px).
    params : FlowParams

    Returns
    -------
    FlowResult
    """
    npath = len(xys)
    if npath == 0:
        z = np.zeros(0)
        return FlowResult([], z, z.copy(), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
    batch = prepare_paths(xys, widths, interest, params)
    e0 = np.zeros(npath)
    e1 = np.zeros(npath)
    nres = np.zeros(npath, np.int64)
    failed = np.zeros(npath, np.int64)
    nrej = np.zeros(npath, np.int64)
    # Longest paths first, handed out one at a time: the blocks differ in size by 100×.
    order = np.argsort(-np.diff(batch.zoff), kind="stable")
    old_chunk = numba.get_parallel_chunksize()
    numba.set_parallel_chunksize(1)
    try:
        _flow_kernel(order, batch.z, batch.zoff, batch.centres, batch.sigma, batch.rho2, batch.dist, batch.coff,
                     batch.home, batch.window, _pack_field(c0, c2), params.iterations, params.dt, params.lam,
                     params.eps, params.resample_factor, params.barrier_cutoff ** 2, params.step_d0,
                     params.step_min, params.step_max, e0, e1, nres, nrej, failed)
    finally:
        numba.set_parallel_chunksize(old_chunk)
    curves = [np.stack([batch.z[a:b].real, batch.z[a:b].imag], axis=1)
              for a, b in zip(batch.zoff[:-1], batch.zoff[1:])]
    return FlowResult(curves, e1, e0, nres, failed, nrej)


def path_energy(c0: np.ndarray, c2: np.ndarray, xy: np.ndarray, centres: np.ndarray, sigmas: np.ndarray,
                lam: float, eps: float, cutoff: float) -> float:
    """Discrete Eq. 6a of one polyline, by brute force over all barrier centres (a reference for tests).

    Parameters
    ----------
    c0, c2 : numpy.ndarray
        complex (H, W) field, pixel centres at +0.5, 0 outside the image.
    xy : numpy.ndarray
        (n, 2) polyline in (x, y), corner origin.
    centres : numpy.ndarray
        (k, 2) barrier centres (x, y); ``sigmas`` (k,) their standard deviations.
    lam, eps : float
        λ and the length regulariser ε.
    cutoff : float
        Centres farther than ``cutoff``·σ are ignored (the kernel's rule).

    Returns
    -------
    float
        ``Σ_j (|f(m_j, t_j/q_j)|² + max(1 − S(m_j), 0) + λ) q_j``, ``q_j = √(|t_j|² + ε)``.
    """
    xy = np.asarray(xy, dtype=np.float64)
    t = np.diff(xy, axis=0)
    q = np.sqrt((t ** 2).sum(1) + eps)
    m = np.ascontiguousarray(0.5 * (xy[1:] + xy[:-1]))
    tau = (t[:, 0] + 1j * t[:, 1]) / q
    a0, _, _ = bilinear_with_gradient(np.ascontiguousarray(c0, dtype=np.complex128), m)
    a2, _, _ = bilinear_with_gradient(np.ascontiguousarray(c2, dtype=np.complex128), m)
    g = np.abs(tau ** 4 + a2 * tau ** 2 + a0) ** 2
    d2 = ((m[:, None, :] - np.asarray(centres)[None, :, :]) ** 2).sum(-1)
    s2 = np.asarray(sigmas)[None, :] ** 2
    s = np.where(d2 < cutoff ** 2 * s2, np.exp(-0.5 * d2 / s2), 0.0).sum(1)
    return float(((g + np.maximum(1.0 - s, 0.0) + lam) * q).sum())


def run(cfg: dict, **inputs: Artifact) -> Artifact:
    """Stage entry: flow every candidate path of the topology artifact.

    Parameters
    ----------
    cfg : dict
        The ``flow`` config section (keys of :class:`FlowParams`).
    prep, field, graph, topology : Artifact
        ``field`` supplies ``c0_ext``/``c2_ext``; ``topology`` the paths (``xy``, ``widths``,
        ``interest_dist``); ``prep`` the image size.  ``graph`` is not read (widths and distances
        come with the paths).

    Returns
    -------
    Artifact
        Arrays ``curve_xy`` float64 (n, 2) + ``curve_xy_offsets``; data ``energies``,
        ``energies_initial`` (Eq. 6a, per path, topology order), ``resamples``, ``failed`` (ids),
        ``n_vertices``.
    """
    params = FlowParams.from_cfg(cfg)
    for name in ("prep", "field", "topology"):
        if name not in inputs:
            raise InputError(f"flow stage needs the '{name}' artifact")
    field, topology = inputs["field"], inputs["topology"]
    c0 = np.asarray(field.arrays.get("c0_ext"))
    c2 = np.asarray(field.arrays.get("c2_ext"))
    if c0.ndim != 2 or c0.shape != c2.shape or min(c0.shape) < 1:
        raise InputError(f"flow: field c0_ext/c2_ext must be equal 2-D arrays, got {c0.shape}, {c2.shape}")
    paths = topology.data.get("paths", [])
    xys, widths, interest = [], [], []
    for p in paths:
        xy = np.asarray(p["xy"], dtype=np.float64).reshape(-1, 2)
        n = len(xy)
        wd = np.asarray(p.get("widths", []), dtype=np.float64).ravel()
        dd = np.asarray(p.get("interest_dist", []), dtype=np.float64).ravel()
        dd = np.where(np.isposinf(dd), 1e9, dd)   # "no interesting vertex reachable": far away
        if n < 1 or len(wd) != n or len(dd) != n:
            raise InputError(f"flow: path {p.get('id')} needs xy, widths and interest_dist of equal length ≥ 1")
        if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(wd)) and np.all(np.isfinite(dd))):
            raise InputError(f"flow: path {p.get('id')} has non-finite coordinates, widths or distances")
        xys.append(xy)
        widths.append(wd)
        interest.append(dd)
    notes = []
    # Guard: the flow costs iterations × vertices; past max_vertices (the paths resampled at
    # spacing) the iterations shrink so that their product stays within iterations × max_vertices.
    n_vert = sum(float(np.hypot(*np.diff(xy, axis=0).T).sum()) / params.spacing + 1.0 for xy in xys)
    if n_vert > params.max_vertices and params.iterations > 1:
        its = max(1, int(params.iterations * params.max_vertices / n_vert))
        notes.append(f"about {n_vert:.0f} path vertices, more than flow.max_vertices ({params.max_vertices}): "
                     f"{its} iterations instead of {params.iterations}")
        params = replace(params, iterations=its)
    res = polyvector_flow(c0, c2, xys, widths, interest, params)
    flat, off = pack_ragged(res.curves, dtype=np.float64)
    return Artifact(
        arrays={"curve_xy": flat.reshape(-1, 2), "curve_xy_offsets": off},
        data={"energies": [float(e) for e in res.energies],
              "energies_initial": [float(e) for e in res.energies_initial],
              "resamples": int(res.resamples.sum()),
              "rejected_steps": int(res.rejected.sum()),
              "failed": [int(p["id"]) for p, f in zip(paths, res.failed) if f],
              "n_vertices": int(len(flat))}, notes=notes)
