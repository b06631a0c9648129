"""PolyVector flow of the candidate paths (paper §5, Eq. 4–10; authors' ``FrameFieldFlow.cpp``).

Every allowed path from the topology stage is deformed, endpoints fixed, by the L2 gradient flow of
the anisotropic, position-varying length (Eq. 6a)

    E(x) = ∫_Γ ( |f(x, τ)|² + b(x) ) dl,   f(x, z) = z⁴ + c2(x) z² + c0(x),   τ = tangent,
    b(x) = max(1 − S(x), 0) + λ,            S(x) = Σ_k exp(−|x − p_k|² / 2σ_k²)          (Eq. 5)

where c0, c2 is the frame field extended beyond the band (extension artifact ``c0_ext``, ``c2_ext``),
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

Choices made on purpose (vs. the paper and the authors' code; measurements in stages/DECISIONS.md)
------------------------------------------------------------
* **Stage order: flow, then select**, as in the authors' code: every allowed path is flowed and the
  MIP chooses among the flowed curves with their energies as costs, so a λ sweep re-runs only
  flow → select → export.
* **Only the isotropic length is implicit**; the anisotropy and the positional forces are explicit,
  and the full positional gradient is taken (the paper keeps its normal component).  Eq. 10's
  complex implicit structure with frozen coefficients is no linearisation and raised energies; this
  way a fixed point is a stationary point of E_ε.
* **Monotone energy.**  An iteration that raises a path's E_ε is undone and that path's step halved
  (regrown ×1.25 per accepted step up to α), so the flow never raises an energy whatever α.  The
  iteration after an undo re-assembles the restored iterate's system from stored step-independent
  row coefficients and is not checked again (its energy is known).  The iteration count stays
  fixed (no convergence test), as in the paper, but at 400, not the paper's 1500: past a few hundred
  iterations the length term keeps pulling the curves off the stroke centres (both validation splits:
  chamfer to the drawn strokes lower at 400 than at 600 and 1500, topology a tie; stages/DECISIONS.md).
* **Bilinear field lookup with its exact derivative** (the :func:`stages.geometry.bilinear`
  convention: pixel centres at +0.5, zero outside the image) instead of the code's nearest-pixel
  lookup with central differences: the energy the flow lowers is then the one it differentiates.
* **τ = t/q** as in the paper and the code: the alignment term fades on edges shorter than √ε, which
  keeps its angular stiffness bounded (with the unit tangent short noisy edges collapsed).
* **Barrier = Eq. 5.**  ``B = max(1 − S, 0)`` enters both the length weight W and the force; its
  gradient is ``−∇S`` where ``S < 1`` and zero elsewhere (the code's "barrier force only where
  0 < S < 1"; beyond the 4σ cut-off S = 0).  The code leaves B out of W.
* **Barrier centres** are placed uniformly in the σ-scaled arc length ``∫ ds/σ(s)`` of the initial
  polyline, ``barrier.spacing`` σ apart, σ interpolated from the path widths and clamped below by
  ``barrier.sigma_min`` (σ = 0 gives NaNs): S then does not depend on how densely the graph sampled
  the path (S ≈ √(2π)/spacing ≈ 2.5 on the initial curve).  S sums the centres within
  ``barrier.cutoff``·σ in a window of centre indices around the nearest ("home") centre, tracked as
  the curve moves, so other parts of the same path (a hairpin) do not count.  Inside a precomputed
  safe radius round the home centre S ≥ 1 is certain and nothing is summed; otherwise the sum stops
  once S ≥ 1 (both shortcuts are exact for B).
* **Time-step scaling** ``s = clip(d0/d, s_min, s_max)``, d = topology ``interest_dist``: with the
  code's d0 = 30, s_min = 0.1, s_max = 2 this is its rule "2 if d < 15 else max(0.1, 30/d)", the
  paper's inverse-distance scaling, moving curves most where the graph is least reliable (near
  junctions and ends).  d is carried by the barrier centres, so it follows the vertices through
  resampling (the code indexes it by the stale vertex id).
* **α = 1e-2 and λ = 3** (``dt``, ``lam``), the code's values (the paper quotes δ = 5e-3).
* **Resampling** uniformly by arc length every ``spacing`` px first (the code keeps the graph chain's
  varying density, so its g and ε act differently on every path), and again to the same count when
  the longest edge exceeds ``resample_factor`` × the initial mean edge; 0.75 px and 1.34 keep edges
  under one pixel, as the paper asks, at 2/3 of the cost of 0.5 px.  After a resampling the next
  step is accepted unconditionally (another discretisation).
* **Energies (MIP cost)** are E_ε of the flowed curves (Eq. 6a with the Eq. 5 barrier, as the flow
  sees it; uniform spacing makes them comparable).  The code adds S to g in its MIP cost, a roughly
  constant, sampling-dependent length penalty (S ≈ 2.5 along a curve in its tube): dropped.
* **All paths in one compiled call.**  The paths are independent blocks of one block-tridiagonal
  system (fixed endpoints decouple them); one numba kernel runs the whole iteration loop of every
  block, edge terms, energy and the Thomas forward sweep fused in one pass — a banded solver on the
  stacked system alone costs more than the run.  The blocks are shared out between
  ``numba.get_num_threads()`` Python threads (:func:`split_paths`, longest first; the kernel releases
  the GIL), not a ``prange``: the kernel compiled in numba's parallel pipeline with no parallel region
  runs as fast and compiles in 3.5 s instead of 8.3 s (a fresh install's first run).
  The field is stored with a one-pixel zero border (no bounds tests in the lookup), ∂(q g)/∂t is
  formed from conj(A), an undone step swaps two buffers.  Fastmath flags ``contract, arcp, nsz,
  afn`` only: ``reassoc`` makes results differ from run to run, and ``nnan``/``ninf`` would remove
  the non-finite check.  A block whose solve turns non-finite stops and keeps its last finite
  iterate (``data["failed"]``).
* **A path's result depends on that path alone, to the last bit** (each path is resampled in its own
  arc length): the engine reuses the stored results of unchanged paths after a keypoint correction
  (:func:`plan_items`, :func:`run_items`, :func:`assemble`; keyed with the effective iterations).

References
----------
.. [1] I. Puhachov, W. Neveu, E. Chien, M. Bessmeltsev, "Keypoint-Driven Line Drawing Vectorization
       via PolyVector Flow", ACM Trans. Graph. 40(6), 2021, §5.
.. [2] K. Deckelnick, G. Dziuk, C. M. Elliott, "Computation of geometric partial differential
       equations and mean curvature flow", Acta Numerica 14, 2005.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numba
import numpy as np

from stages.artifact import Artifact, ItemPlan, pack_ragged
from stages.config import from_section
from stages.errors import InputError
from stages.flow import FlowConfig
from stages.flow.kernel import _flow_kernel, _pack_field, bilinear_with_gradient
from stages.flow.paths import prepare_paths
from stages.geometry import polyline_length


def step_scale(d: np.ndarray, params: FlowConfig) -> np.ndarray:
    """Per-vertex time-step factor ``clip(d0 / d, min, max)`` (= the code's 2 if d < 15 else max(0.1, 30/d)).

    Parameters
    ----------
    d : numpy.ndarray
        Graph distance (px) to the nearest high-valence vertex or path end.
    params : FlowConfig
    """
    d = np.asarray(d, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return np.clip(params.step_scale.d0 / np.maximum(d, 0.0), params.step_scale.min, params.step_scale.max)


# ---------------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------------

def split_paths(sizes: np.ndarray, threads: int) -> list[np.ndarray]:
    """Path indices for each of up to ``threads`` threads, about equal in vertices (longest first, greedy).

    Parameters
    ----------
    sizes : numpy.ndarray
        Vertex count per path (the work of a path is about proportional to it).
    threads : int
        Threads available; at most one share per path.

    Returns
    -------
    list of numpy.ndarray
        int64 path indices per share, each longest first; every path in exactly one share.
    """
    sizes = np.asarray(sizes, dtype=np.int64)
    order = np.argsort(-sizes, kind="stable")
    k = max(1, min(int(threads), len(sizes)))
    if k == 1:
        return [order]
    load = np.zeros(k, np.int64)
    owner = np.empty(len(order), np.int64)
    for r, p in enumerate(order):  # a Python loop over paths (hundreds), not vertices
        t = int(np.argmin(load))
        owner[r] = t
        load[t] += sizes[p]
    return [order[owner == t] for t in range(k)]


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
                    interest: list[np.ndarray], params: FlowConfig) -> FlowResult:
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
    params : FlowConfig

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
    field = _pack_field(c0, c2)
    args = (batch.z, batch.zoff, batch.centres, batch.sigma, batch.rho2, batch.dist, batch.coff, batch.home,
            batch.window, field, params.iterations, params.dt, params.lam, params.eps, params.resample_factor,
            params.barrier.cutoff ** 2, params.step_scale.d0, params.step_scale.min, params.step_scale.max,
            e0, e1, nres, nrej, failed)
    shares = split_paths(np.diff(batch.zoff), numba.get_num_threads())
    if len(shares) == 1:
        _flow_kernel(shares[0], *args)
    else:
        # The kernel releases the GIL; each thread flows its own paths (disjoint slices of every array).
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max_workers=len(shares), thread_name_prefix="polyvec-flow") as pool:
            for done in [pool.submit(_flow_kernel, share, *args) for share in shares]:
                done.result()
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


#: The paths are independent items (:class:`stages.artifact.ItemPlan`): the engine may reuse a path's
#: stored result whenever the path, these inputs' artifacts and the effective config are unchanged.
ITEM_INPUTS = ("extension",)
ITEM_NAME = "paths"


@dataclass
class _FlowWork:
    """The stage-private part of the flow's :class:`ItemPlan`: what flowing any subset of the paths needs."""

    c0: np.ndarray
    c2: np.ndarray
    xys: list[np.ndarray]
    widths: list[np.ndarray]
    interest: list[np.ndarray]
    ids: list[int]
    params: FlowConfig  # effective: the max_vertices guard may have lowered the iterations


def plan_items(cfg: dict, **inputs: Artifact) -> ItemPlan:
    """The flow's work as independent items, one per candidate path (checks the inputs as :func:`run`).

    Parameters
    ----------
    cfg : dict
        The ``flow`` config section.
    prep, extension, graph, topology : Artifact
        As for :func:`run`.

    Returns
    -------
    ItemPlan
        ``items``: per path, its ``xy``, ``widths`` and ``interest_dist`` (float64, topology order);
        ``context``: the effective config (iterations after the ``max_vertices`` guard, which itself
        is left out), so that a path's result never mixes with one flowed under another iteration count.
    """
    params = from_section(FlowConfig, cfg, "flow")
    for name in ("prep", "extension", "topology"):
        if name not in inputs:
            raise InputError(f"flow stage needs the '{name}' artifact")
    extension, topology = inputs["extension"], inputs["topology"]
    c0 = np.asarray(extension.arrays.get("c0_ext"))
    c2 = np.asarray(extension.arrays.get("c2_ext"))
    if c0.ndim != 2 or c0.shape != c2.shape or min(c0.shape) < 1:
        raise InputError(f"flow: extension c0_ext/c2_ext must be equal 2-D arrays, got {c0.shape}, {c2.shape}")
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
    n_vert = sum(polyline_length(xy) / params.spacing + 1.0 for xy in xys)
    if n_vert > params.max_vertices and params.iterations > 1:
        its = max(1, int(params.iterations * params.max_vertices / n_vert))
        notes.append(f"about {n_vert:.0f} path vertices, more than flow.max_vertices ({params.max_vertices}): "
                     f"{its} iterations instead of {params.iterations}")
        params = replace(params, iterations=its)
    work = _FlowWork(c0, c2, xys, widths, interest, [int(p["id"]) for p in paths], params)
    # A path's result depends on the config through the effective iterations, not on max_vertices:
    # the guard couples the paths, and keying on its outcome keeps results of different iteration
    # counts apart while a max_vertices that does not bind leaves the stored paths usable.
    context = {k: v for k, v in asdict(params).items() if k != "max_vertices"}
    return ItemPlan(items=[(xy, wd, dd) for xy, wd, dd in zip(xys, widths, interest)],
                    context={"flow": context}, work=work, notes=notes)


def run_items(plan: ItemPlan, which: list[int]) -> list[dict[str, np.ndarray]]:
    """Flow the paths ``which`` of a plan (each path's result depends on that path alone).

    Parameters
    ----------
    plan : ItemPlan
        From :func:`plan_items`.
    which : list of int
        Path indices (topology order).

    Returns
    -------
    list of dict
        Per path: ``curve`` float64 (n, 2), and 0-d ``energy``, ``energy_initial`` (float64),
        ``resamples``, ``rejected``, ``failed`` (int64).
    """
    w: _FlowWork = plan.work
    res = polyvector_flow(w.c0, w.c2, [w.xys[i] for i in which], [w.widths[i] for i in which],
                          [w.interest[i] for i in which], w.params)
    return [{"curve": res.curves[k], "energy": np.float64(res.energies[k]),
             "energy_initial": np.float64(res.energies_initial[k]), "resamples": np.int64(res.resamples[k]),
             "rejected": np.int64(res.rejected[k]), "failed": np.int64(res.failed[k])}
            for k in range(len(which))]


def assemble(plan: ItemPlan, results: list[dict[str, np.ndarray]]) -> Artifact:
    """The flow artifact from every path's result (as :func:`run_items` returns them), in topology order."""
    w: _FlowWork = plan.work
    flat, off = pack_ragged([np.asarray(r["curve"], dtype=np.float64).reshape(-1, 2) for r in results],
                            dtype=np.float64)
    return Artifact(
        arrays={"curve_xy": flat.reshape(-1, 2), "curve_xy_offsets": off},
        data={"energies": [float(r["energy"]) for r in results],
              "energies_initial": [float(r["energy_initial"]) for r in results],
              "resamples": int(sum(int(r["resamples"]) for r in results)),
              "rejected_steps": int(sum(int(r["rejected"]) for r in results)),
              "failed": [pid for pid, r in zip(w.ids, results) if int(r["failed"])],
              "n_vertices": int(len(flat))}, notes=list(plan.notes))


def run(cfg: dict, **inputs: Artifact) -> Artifact:
    """Stage entry: flow every candidate path of the topology artifact.

    The engine may instead reuse stored paths: :func:`plan_items`, :func:`run_items` on the paths it
    lacks, :func:`assemble` — the same artifact, byte for byte.

    Parameters
    ----------
    cfg : dict
        The ``flow`` config section (keys of :class:`FlowConfig`).
    prep, extension, graph, topology : Artifact
        ``extension`` supplies ``c0_ext``/``c2_ext``; ``topology`` the paths (``xy``, ``widths``,
        ``interest_dist``); ``prep`` the image size.  ``graph`` is not read (widths and distances
        come with the paths).

    Returns
    -------
    Artifact
        Arrays ``curve_xy`` float64 (n, 2) + ``curve_xy_offsets``; data ``energies``,
        ``energies_initial`` (Eq. 6a, per path, topology order), ``resamples``, ``failed`` (ids),
        ``n_vertices``.
    """
    plan = plan_items(cfg, **inputs)
    return assemble(plan, run_items(plan, list(range(len(plan.items)))))
