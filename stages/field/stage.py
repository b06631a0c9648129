"""PolyVector frame field on the narrow band (paper §4.1; Bessmeltsev & Solomon 2019).

Every band pixel carries the two complex coefficients of the even quartic

    p(z) = z⁴ + c2·z² + c0,

whose roots ±u, ±v are the two (unoriented, neither unit nor orthogonal) stroke directions at that
pixel.  Directions are complex numbers ``x + 1j*y`` (x right, y down).

Steps (in the order of :func:`compute_field`):

1. **Tangents.**  3×3 Sobel on the inverted grey image (ink = 1 − grey, reflect-101 border, no
   pre-smoothing): ``g = gx + i·gy``; the image tangent is ``τ = i·g/|g|``.  Pixels with
   ``|g| < gradient_cutoff · max|g|`` get ``τ = 0`` and drop out of both data terms.
2. **Coherence weight w.**  Ring sum (3×3 ones, centre 0) of ``(τ|g|)²``, normalised to unit modulus,
   minus the pixel's own ``τ²``; ``w = 1 − dev / max(dev)`` (max over the whole image, like the
   reference), ``w = 0`` where ``τ = 0``.
3. **Energy** over the unknowns ``X = [c0; c2]`` of all band pixels (one sparse complex Hermitian
   system; the 8-connected components of the band are independent blocks of it anyway):

       E = Σ w |p(τ)|²  +  α Σ_{τ≠0} |p(iτ)|²  +  β Σ_{x,y} Σ s |D c0|² + β Σ_{x,y} Σ s |D c2|²

   D is the reference's difference operator restricted to the band (central ±½ when both neighbours
   are in the band, one-sided ±1 when only one is, nothing otherwise) and ``s`` the *smart weight*,
   the mean of ``1 − w`` over the 4-neighbours (1 on the image border).  Normal equations
   ``[M_align + α M_orth + β (L ⊕ L)] X = r``, ``L = Σ Dᵀ diag(s) D``, solved by conjugate gradients
   (hand-written, :func:`_conjugate_gradient`; not scipy's ``cg``) with a Jacobi preconditioner, in
   real form: the real ``K = diag(w + α m) + β L`` acts on the four columns ``Re/Im c0, Re/Im c2`` in
   one sparse product and the diagonal coupling is added (:func:`_field_operator`; 1.8× fewer bytes
   per product than the complex ``2n × 2n`` matrix).  The sparse product and the CG's updates run as
   numba loops (:mod:`stages.field.kernel`) that round as numpy and scipy do: the same bits, fewer passes.
4. **Singularity loop.**  A 2×2 pixel cell is singular when walking round it the root pairing between
   neighbours (:func:`root_matching`) swaps an odd number of times; a pixel is singular when one of
   its (fully in-band) cells is.  Singular pixels get ``w = 0`` (which also raises the smart weights
   around them) and the system is solved again, until no pixel gets a newly zeroed weight or the
   singularity count stops falling.
5. **Roots** in closed form (:func:`polyvector_roots`), ``roots[..., 0]`` = larger modulus.  Where
   the moduli tie (relative difference < ``tie_tolerance``) the root closer to the image tangent
   (structure tensor smoothed with σ = ``tie_sigma``) goes first: for an axis-aligned stroke the exact
   frame {x, y} is *one* polynomial (c0 = −1, c2 = 0) for a horizontal and a vertical stroke, so
   "larger modulus" alone would put the normal first on one of them (a frequent case: see
   stages/DECISIONS.md).
6. **Smart weights** ``s`` of step 2's coherence weights (before the singularity loop zeroes any) are
   kept in the artifact: the ``extension`` stage extends the field beyond the band with them.

The steps' code is in the modules next to this one: the tangents and weights of steps 1, 2 and 6 in
:mod:`stages.field.data_terms`, the system and its solve (step 3) in :mod:`stages.field.solver`, the
roots, the singularity test and the tie-break (steps 4 and 5) in :mod:`stages.field.roots`; the loop
that runs them (:func:`compute_field`, with the choices below) and the stage entry (:func:`run`) are here.

Choices made on purpose (vs. the references; measurements in stages/DECISIONS.md)
-------------------------------------------
* **β = 50** (B19's value), not the authors' 10, although this project reproduces the authors'
  paper: β = 10 lets the Sobel aliasing of thin anti-aliased strokes through and leaves far more
  singularities on scans; β = 50 rounds the field at sharp corners slightly more.  It is ``beta`` in
  ``conf/field/default.yaml``.
* **α = 0.1** (both references).  It is what keeps X junctions from being represented exactly: it
  pulls each arm's second root to the arm's normal, so where two strokes overlap the field is a
  compromise between the arms' {stroke, normal} frames.  A smaller α fits X junctions better but
  leaves many more singular pixels on scans.
* **Tie-break of equal moduli** by the smoothed image tangent (step 5).
* **Solves by blocks of components** (:func:`stages.field.solver._solve_blocks`): the matrix is block
  diagonal over the band's components, grouped into blocks of up to 2¹⁶ unknowns (a drawing is
  usually one), each solved by its own CG — not B19's per-component solves (a Python loop over
  hundreds of tiny components in a scan) nor one system for a whole page.  Jacobi-CG by blocks, not
  algebraic multigrid: the iteration count is bounded by the data term (the same 134/77/60/47 on one
  drawing and on its 4×4 page); what grew was each iteration's cost once a page's vectors left the
  cache.  The singularity loop stays global: it stops when the *total* count stops falling.
* **A mosaic's pieces** (far-apart parts that prep laid side by side) get steps 1–2 on their own
  windows: the cutoff's and the coherence's maxima are then each part's, as on it cropped alone
  (the parts' band pixels are one system all the same).
* **CG tolerance.**  The references run Eigen's CG to machine epsilon; we stop at a relative residual
  of ``cg_rtol`` = 1e-6, where the roots already match a much tighter solve, and ``cg_max_iterations``
  caps every solve (bounds the run time).
* **Warm start.**  Each re-solve of the singularity loop starts from the previous solution
  (``warm_start``); the references start from zero.  Same fixed point, fewer iterations.
* **Kept solution.**  If a re-solve does not lower the singularity count the loop stops and keeps
  the solution with the fewest singular pixels (the reference keeps the last one).
* Pixels with no data and no smoothness neighbour (isolated single-pixel band components without
  gradient) have an all-zero row; the Jacobi preconditioner uses 1 there and their coefficients stay 0.
* An empty band yields an all-zero field (no error): an empty drawing is prep's to reject.

References
----------
.. [1] I. Puhachov, W. Neveu, E. Chien, M. Bessmeltsev, "Keypoint-Driven Line Drawing Vectorization
   via PolyVector Flow", ACM TOG 40(6), 2021, §4.1.
.. [2] M. Bessmeltsev, J. Solomon, "Vectorization of Line Drawings via PolyVector Fields", ACM TOG
   38(1), 2019.
"""

from __future__ import annotations

import time

import numpy as np

from stages.artifact import Artifact
from stages.config import from_section
from stages.errors import InputError
from stages.field import FieldConfig
from stages.field.data_terms import band_ring, band_smart_weights, coherence_weights, image_tangents, smart_weights
from stages.field.roots import _order_ties, band_cells, band_singular_pixels, polyvector_roots
from stages.field.solver import _assemble, _band_differences, _blockwise_cg, _region_index, _solve_blocks
from stages.prep import piece_windows


# ---------------------------------------------------------------------------------------------
# The solve
# ---------------------------------------------------------------------------------------------

def compute_field(grey: np.ndarray, mask: np.ndarray, cfg: FieldConfig,
                  windows: list[tuple[slice, slice]] | None = None) -> dict:
    """PolyVector field on the band and the singularity loop.

    Parameters
    ----------
    grey : numpy.ndarray
        float (H, W) in [0, 1], 1 = white.
    mask : numpy.ndarray
        bool (H, W), the narrow band.
    cfg : FieldConfig
    windows : list of (slice, slice), optional
        A mosaic's pieces (:func:`stages.prep.piece_windows`): the tangents' cutoff and the coherence
        weights' normalisation (maxima over the image) are each piece's own, as on that part cropped
        alone; the rest of the pixels are paper.

    Returns
    -------
    dict
        ``c0, c2, roots`` (complex128), ``singular`` (bool), ``smart_weights`` (float64) arrays and
        ``stats`` (dict).
    """
    band = _band_field(grey, mask, cfg, windows)
    out = _on_image(band, mask, np.complex128)
    out["smart_weights"], out["stats"] = band["smart_weights"], band["stats"]
    return out


def _on_image(band: dict, mask: np.ndarray, dtype) -> dict:
    """The band values of :func:`_band_field` as (H, W) images of ``dtype``, 0 off the band."""
    h, w = mask.shape
    out = {"c0": np.zeros((h, w), dtype), "c2": np.zeros((h, w), dtype), "roots": np.zeros((h, w, 2), dtype),
           "singular": np.zeros((h, w), bool)}
    for key in out:
        out[key][mask] = band[key]
    return out


def _band_field(grey: np.ndarray, mask: np.ndarray, cfg: FieldConfig,
                windows: list[tuple[slice, slice]] | None) -> dict:
    """:func:`compute_field` with its per-pixel results as band vectors (raster order of ``mask``).

    Only the data terms (steps 1, 2, 6) and the tie-break's smoothing see the whole image; the
    singularity loop keeps band vectors and builds what does not change across its passes (the
    difference operators, the tested cells, the neighbours off the band) once: image-sized arrays
    per pass fall out of the cache on a page and cost memory.

    Returns
    -------
    dict
        ``c0, c2`` complex (n,), ``roots`` complex (n, 2), ``singular`` bool (n,), ``smart_weights``
        float64 (H, W) and ``stats``.
    """
    t_start = time.perf_counter()
    h, w = mask.shape
    if windows is None:
        tau, gmag = image_tangents(grey, cfg.gradient_cutoff)
        w0 = coherence_weights(tau, gmag)
    else:
        tau, gmag, w0 = np.zeros((h, w), np.complex128), np.zeros((h, w)), np.zeros((h, w))
        for win in windows:
            tau[win], gmag[win] = image_tangents(grey[win], cfg.gradient_cutoff)
            w0[win] = coherence_weights(tau[win], gmag[win])
    n = int(mask.sum())
    tau_b = tau[mask]
    blocks = _solve_blocks(mask, mask)
    stats: dict = {"unknowns": 2 * n, "band_pixels": n, "solve_blocks": len(blocks), "cg_iterations": [],
                   "cg_converged": [], "singular_pixels": [], "nonzeros": [], "tie_swapped": 0}
    x = np.zeros((n, 4))
    singular = np.zeros(n, bool)
    if n > 0:
        index = _region_index(mask)
        differences = _band_differences(mask, index)
        cells = band_cells(mask, index)
        del index
        ring = band_ring(w0, mask)
        w_cur = w0[mask]
        x = None
        best = None
        maxiter = max(1, cfg.cg_max_iterations)
        for _ in range(max(1, cfg.max_singularity_iterations)):
            k, off, rhs = _assemble(differences, tau_b, w_cur, band_smart_weights(w_cur, ring), cfg)
            x0 = x if (cfg.warm_start and x is not None) else None
            x, iters, info = _blockwise_cg(k, off, rhs, x0, blocks, cfg.cg_rtol, maxiter, compiled=True)
            stats["cg_iterations"].append(max(iters))
            stats["cg_converged"].append(info)
            stats["nonzeros"].append(2 * int(k.nnz) + 2 * n)  # of the complex 2n × 2n matrix
            xc = x.view(np.complex128)
            singular = band_singular_pixels(polyvector_roots(xc[:, 0], xc[:, 1]), cells)
            count = int(singular.sum())
            stats["singular_pixels"].append(count)
            if best is None or count < best[0]:
                best = (count, x, singular)
            elif count >= best[0]:
                break  # the count stopped falling
            newly = singular & (w_cur > 1e-5)
            if not newly.any():
                break
            w_cur[newly] = 0.0
        _, x, singular = best
    xc = x.view(np.complex128)
    roots = polyvector_roots(xc[:, 0], xc[:, 1])
    if n > 0:
        stats["tie_swapped"] = _order_ties(roots, mask, tau, gmag, cfg.tie_tolerance, cfg.tie_sigma)
    stats["solve_seconds"] = time.perf_counter() - t_start
    return {"c0": xc[:, 0], "c2": xc[:, 1], "roots": roots, "singular": singular,
            "smart_weights": smart_weights(w0), "stats": stats}


# ---------------------------------------------------------------------------------------------
# Stage entry point
# ---------------------------------------------------------------------------------------------

def run(cfg: dict, **inputs: Artifact) -> Artifact:
    """Stage entry: the PolyVector field of the ``prep`` artifact.

    Parameters
    ----------
    cfg : dict
        The ``field`` config section (keys of :class:`FieldConfig`).
    prep : Artifact
        With ``grey`` float32 (H, W) and ``mask`` bool (H, W).

    Returns
    -------
    Artifact
        Arrays ``c0, c2`` complex64 (H, W), ``roots`` complex64 (H, W, 2), ``singular`` bool (H, W),
        ``smart_weights`` float32 (H, W); data = solver statistics.
    """
    conf = from_section(FieldConfig, cfg, "field")
    if "prep" not in inputs:
        raise InputError("field stage needs the 'prep' artifact")
    prep = inputs["prep"]
    grey = np.asarray(prep.arrays.get("grey"))
    mask = np.asarray(prep.arrays.get("mask"))
    if grey.ndim != 2 or mask.shape != grey.shape:
        raise InputError(f"field: grey and mask must be equal-shaped 2-D arrays, got {grey.shape} and {mask.shape}")
    if not np.all(np.isfinite(grey)):
        raise InputError("field: grey image contains NaN or infinite values")
    mask = mask.astype(bool)
    out = _band_field(grey.astype(np.float64), mask, conf, piece_windows(prep.data, grey.shape))
    # Straight into the stored dtypes: no complex128 image of the roots (0.2 GB on a 4×4 page).
    arrays = {**_on_image(out, mask, np.complex64), "smart_weights": out["smart_weights"].astype(np.float32)}
    notes = []
    capped = sum(not c for c in out["stats"]["cg_converged"])
    if capped:
        notes.append(f"{capped} of {len(out['stats']['cg_converged'])} solves stopped at field.cg_max_iterations "
                     f"({conf.cg_max_iterations}) before field.cg_rtol: the field may be less smooth")
    return Artifact(arrays=arrays, data=out["stats"], notes=notes)
