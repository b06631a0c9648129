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
* **One system for all components** instead of B19's per-component solves: the matrix is block
  diagonal, so the solution is the same up to the CG stopping rule, and one solve avoids a Python loop
  over hundreds of tiny components in a scan.  The singularity loop is therefore global: it stops
  when the *total* count stops falling.
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
import scipy.ndimage as ndi
import scipy.sparse as sp

from stages.artifact import Artifact
from stages.config import from_section
from stages.errors import InputError
from stages.field import FieldConfig
from stages.prep import piece_windows


# ---------------------------------------------------------------------------------------------
# Data terms
# ---------------------------------------------------------------------------------------------

def image_tangents(grey: np.ndarray, gradient_cutoff: float) -> tuple[np.ndarray, np.ndarray]:
    """Image tangent τ and gradient magnitude from a 3×3 Sobel of the inverted image.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) in [0, 1], 1 = white paper.
    gradient_cutoff : float
        Pixels with ``|g| < gradient_cutoff * max|g|`` get τ = 0 and |g| = 0.

    Returns
    -------
    tau : numpy.ndarray
        complex128 (H, W), unit modulus where the gradient is strong, 0 elsewhere.
    gmag : numpy.ndarray
        float64 (H, W), |g| (0 below the cutoff).
    """
    ink = 1.0 - np.asarray(grey, dtype=np.float64)
    # scipy's "mirror" is OpenCV's BORDER_REFLECT_101 (the reference's BORDER_DEFAULT).
    gx = ndi.sobel(ink, axis=1, mode="mirror")
    gy = ndi.sobel(ink, axis=0, mode="mirror")
    g = gx + 1j * gy
    gmag = np.abs(g)
    peak = gmag.max() if gmag.size else 0.0
    strong = (gmag >= gradient_cutoff * peak) & (gmag > 0)
    tau = np.zeros_like(g)
    tau[strong] = 1j * g[strong] / gmag[strong]
    gmag = np.where(strong, gmag, 0.0)
    return tau, gmag


_RING = np.array([[1.0, 1.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.0]])


def coherence_weights(tau: np.ndarray, gmag: np.ndarray) -> np.ndarray:
    """Alignment weight w: agreement of a pixel's tangent with its 8-neighbourhood.

    Parameters
    ----------
    tau, gmag : numpy.ndarray
        Output of :func:`image_tangents`.

    Returns
    -------
    numpy.ndarray
        float64 (H, W) in [0, 1]; 0 where ``gmag == 0``.
    """
    t2g = (tau * gmag) ** 2  # doubled-angle tangent weighted by |g|²
    ring = (ndi.correlate(t2g.real, _RING, mode="mirror")
            + 1j * ndi.correlate(t2g.imag, _RING, mode="mirror"))
    mod = np.abs(ring)
    unit = np.divide(ring, mod, out=np.zeros_like(ring), where=mod > 0)
    dev = np.abs(unit - tau ** 2)
    top = dev.max() if dev.size else 0.0
    w = 1.0 - dev / top if top > 0 else np.ones_like(dev)
    w[gmag == 0] = 0.0
    return w


def smart_weights(w: np.ndarray) -> np.ndarray:
    """Smoothness weight s: mean of ``1 − w`` over the 4-neighbours, 1 on the image border."""
    one_minus = 1.0 - w
    s = np.ones_like(w)
    if w.shape[0] > 2 and w.shape[1] > 2:
        s[1:-1, 1:-1] = 0.25 * (one_minus[:-2, 1:-1] + one_minus[2:, 1:-1]
                                + one_minus[1:-1, :-2] + one_minus[1:-1, 2:])
    return s


# ---------------------------------------------------------------------------------------------
# Sparse operators
# ---------------------------------------------------------------------------------------------

def _difference_operator(region: np.ndarray, index: np.ndarray, axis: int) -> sp.csr_matrix:
    """The reference's finite difference along ``axis`` restricted to ``region``.

    Central ±½ to both neighbours when both are in the region (the centre is not used), one-sided
    ±1 when only one is, an empty row when neither is.  Rows and columns follow ``index``.
    """
    n = int(region.sum())
    pad = np.pad(region, 1, constant_values=False)
    ipad = np.pad(index, 1, constant_values=-1)
    if axis == 1:
        prev_in, next_in = pad[1:-1, :-2], pad[1:-1, 2:]
        prev_ix, next_ix = ipad[1:-1, :-2], ipad[1:-1, 2:]
    else:
        prev_in, next_in = pad[:-2, 1:-1], pad[2:, 1:-1]
        prev_ix, next_ix = ipad[:-2, 1:-1], ipad[2:, 1:-1]
    r = region
    me = index[r]
    pi_, ni_ = prev_in[r], next_in[r]
    pix, nix = prev_ix[r], next_ix[r]
    both = pi_ & ni_
    only_next = ni_ & ~pi_
    only_prev = pi_ & ~ni_
    rows = np.concatenate([me[both], me[both], me[only_next], me[only_next], me[only_prev], me[only_prev]])
    cols = np.concatenate([nix[both], pix[both], nix[only_next], me[only_next], me[only_prev], pix[only_prev]])
    nb, nn, npv = both.sum(), only_next.sum(), only_prev.sum()
    vals = np.concatenate([np.full(nb, 0.5), np.full(nb, -0.5), np.ones(nn), -np.ones(nn),
                           np.ones(npv), -np.ones(npv)])
    return sp.csr_matrix((vals, (rows, cols)), shape=(n, n))


def _smart_laplacian(region: np.ndarray, index: np.ndarray, s: np.ndarray) -> sp.csr_matrix:
    """``L = Σ_dir Dᵀ diag(s) D`` over the pixels of ``region`` (real symmetric PSD)."""
    sd = sp.diags(s[region])
    lap = None
    for axis in (0, 1):
        d = _difference_operator(region, index, axis)
        term = (d.T @ sd @ d)
        lap = term if lap is None else lap + term
    return lap.tocsr()


def _region_index(region: np.ndarray) -> np.ndarray:
    index = np.full(region.shape, -1, dtype=np.int64)
    index[region] = np.arange(int(region.sum()))
    return index


def _rdot(a: np.ndarray, b: np.ndarray) -> float:
    """``Σ a·b`` of real arrays of any shape without BLAS (see :func:`_conjugate_gradient`)."""
    return float(np.einsum("i,i->", a.reshape(-1), b.reshape(-1)))


def _conjugate_gradient(apply, diag: np.ndarray, b: np.ndarray, x0: np.ndarray | None, rtol: float,
                        maxiter: int, compiled: bool = False) -> tuple[np.ndarray, int, bool]:
    """Jacobi-preconditioned conjugate gradients for a Hermitian PSD system in real form.

    The complex unknowns travel as real (n, m) arrays (``Re``/``Im`` columns): ``apply(X)`` is the
    operator, ``diag`` its real diagonal, shared by the m columns.  Hand-written rather than
    ``scipy.sparse.linalg.cg``: scipy's complex inner products call BLAS (``zdotc``), which
    multi-threads even 40k-vectors; on a busy 2-core machine that made the solve 5–20× slower
    (elephant: 17.7 s vs 3.5 s wall).  Here the inner products are numpy loops (:func:`_rdot`), and
    only the sparse product does real work.  ``compiled``: the updates of ``x, r, z`` and ``p`` run as
    two numba loops (:mod:`stages.field.kernel`) instead of six numpy passes, with the same result to
    the last bit; the field's solve uses them, the extension's (in the keypoints process, which loads
    no numba) does not.  Stops when ``‖b − A x‖ ≤ rtol · ‖b‖``.  Zero diagonal entries (rows without
    any term) get a preconditioner of 1; their unknowns keep the start value.

    Returns
    -------
    x, iterations, converged
    """
    inv = np.where(diag > 0, 1.0 / np.where(diag > 0, diag, 1.0), 1.0)
    x = np.zeros_like(b) if x0 is None else np.array(x0, dtype=b.dtype, copy=True)
    bnorm = np.sqrt(_rdot(b, b))
    if bnorm == 0.0:
        return np.zeros_like(b), 0, True
    r = b - apply(x) if x0 is not None else b.copy()
    z = inv[:, None] * r
    p = z.copy()
    rz = _rdot(r, z)
    stop = rtol * bnorm
    if compiled:
        from stages.field.kernel import next_direction, step_solution
    else:
        tmp = np.empty_like(b)

        def step_solution(x, r, z, p, ap, inv, step):
            x += np.multiply(p, step, out=tmp)
            r -= np.multiply(ap, step, out=tmp)
            np.multiply(inv[:, None], r, out=z)

        def next_direction(p, z, beta):
            p *= beta
            p += z
    for k in range(maxiter):
        if np.sqrt(_rdot(r, r)) <= stop:
            return x, k, True
        ap = apply(p)
        step = rz / _rdot(p, ap)
        step_solution(x, r, z, p, ap, inv, step)
        rz_new = _rdot(r, z)
        next_direction(p, z, rz_new / rz)
        rz = rz_new
    return x, maxiter, bool(np.sqrt(_rdot(r, r)) <= stop)


# ---------------------------------------------------------------------------------------------
# Roots and singularities (public helpers, used by graph and flow)
# ---------------------------------------------------------------------------------------------

def polyvector_roots(c0, c2) -> np.ndarray:
    """Closed-form roots of ``p(z) = z⁴ + c2 z² + c0``.

    ``z² = (−c2 ± √(c2² − 4 c0)) / 2`` then principal square roots; the four roots are ±u, ±v.

    Parameters
    ----------
    c0, c2 : array_like of complex
        Coefficients, any broadcastable shapes.

    Returns
    -------
    numpy.ndarray
        complex128 ``(..., 2)``: ``[..., 0]`` = u, the root of larger modulus (≈ the stroke tangent on
        a stroke), ``[..., 1]`` = v.  Both 0 where c0 = c2 = 0.
    """
    c0 = np.asarray(c0, dtype=np.complex128)
    c2 = np.asarray(c2, dtype=np.complex128)
    disc = np.sqrt(c2 * c2 - 4.0 * c0)
    u = np.sqrt(0.5 * (-c2 + disc))
    v = np.sqrt(0.5 * (-c2 - disc))
    swap = np.abs(v) > np.abs(u)
    first = np.where(swap, v, u)
    second = np.where(swap, u, v)
    return np.stack([first, second], axis=-1)


def _abs_cos(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    na, nb = np.abs(a), np.abs(b)
    den = na * nb
    return np.divide(np.abs((a * np.conj(b)).real), den, out=np.zeros(den.shape), where=den > 0)


def root_matching(ra: np.ndarray, rb: np.ndarray) -> np.ndarray:
    """Whether the root pairing between two pixels is swapped.

    The pairing (0↔0, 1↔1) or (0↔1, 1↔0) whose best |cos| is larger wins (ties: not swapped).  Signs
    are ignored (directions are unoriented).

    Parameters
    ----------
    ra, rb : numpy.ndarray
        complex ``(..., 2)`` roots, e.g. from :func:`polyvector_roots`.

    Returns
    -------
    numpy.ndarray
        bool ``(...)``: True where root 0 of ``ra`` pairs with root 1 of ``rb``.
    """
    same = np.maximum(_abs_cos(ra[..., 0], rb[..., 0]), _abs_cos(ra[..., 1], rb[..., 1]))
    swapped = np.maximum(_abs_cos(ra[..., 0], rb[..., 1]), _abs_cos(ra[..., 1], rb[..., 0]))
    return swapped > same


def singular_cells(roots: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The 2×2 root-matching parity test on every pixel cell.

    Cell ``[i, j]`` is made of pixels ``[i, j], [i, j+1], [i+1, j+1], [i+1, j]`` (its centre is the
    point ``(j + 1, i + 1)`` in (x, y) pixel-corner coordinates).  Walking round it, count the
    neighbour pairs whose root matching is swapped; an odd count means a singularity of the field
    inside the cell.  Only cells with all four pixels in ``mask`` are tested.  To test a point
    ``(x, y)`` use cell ``[floor(y − 0.5), floor(x − 0.5)]``.

    Parameters
    ----------
    roots : numpy.ndarray
        complex (H, W, 2).
    mask : numpy.ndarray
        bool (H, W), the narrow band.

    Returns
    -------
    numpy.ndarray
        bool (H − 1, W − 1).
    """
    h, w = mask.shape
    out = np.zeros((max(h - 1, 0), max(w - 1, 0)), dtype=bool)
    if h < 2 or w < 2:
        return out
    full = mask[:-1, :-1] & mask[:-1, 1:] & mask[1:, 1:] & mask[1:, :-1]
    ci, cj = np.nonzero(full)  # only cells inside the band are tested
    r00, r01 = roots[ci, cj], roots[ci, cj + 1]
    r11, r10 = roots[ci + 1, cj + 1], roots[ci + 1, cj]
    parity = (root_matching(r00, r01).astype(np.int8) + root_matching(r01, r11)
              + root_matching(r11, r10) + root_matching(r10, r00)) % 2
    out[ci[parity == 1], cj[parity == 1]] = True
    return out


def singular_pixels(cells: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Pixels touching at least one singular cell (the reference's per-pixel singular flag)."""
    out = np.zeros(shape, dtype=bool)
    if cells.size:
        out[:-1, :-1] |= cells
        out[:-1, 1:] |= cells
        out[1:, :-1] |= cells
        out[1:, 1:] |= cells
    return out


def _order_ties(roots: np.ndarray, mask: np.ndarray, tau: np.ndarray, gmag: np.ndarray,
                tolerance: float, sigma: float) -> int:
    """Order the roots of near-equal modulus by the smoothed image tangent (in place).

    For an axis-aligned stroke the frame {x, y} fits the alignment and orthogonality terms exactly,
    and it is the *same* polynomial (c0 = −1, c2 = 0) for a horizontal and a vertical stroke: the
    moduli tie and "larger modulus" alone would put the normal first on one of them.  Where
    ``|v| ≥ (1 − tolerance)·|u|`` the root closer to the Gaussian-smoothed (σ = ``sigma``) structure
    tensor orientation of the image goes first.  Returns the number of swapped pixels.
    """
    t2g = (tau * gmag) ** 2
    orient = ndi.gaussian_filter(t2g.real, sigma) + 1j * ndi.gaussian_filter(t2g.imag, sigma)
    m = np.abs(roots)
    tie = mask & (m[..., 1] >= (1.0 - tolerance) * m[..., 0]) & (m[..., 0] > 0) & (np.abs(orient) > 0)
    r = roots[tie]
    t = np.sqrt(orient[tie])  # a direction whose doubled angle is the orientation's
    swap = _abs_cos(r[:, 1], t) > _abs_cos(r[:, 0], t)
    idx = np.nonzero(tie)
    ii, jj = idx[0][swap], idx[1][swap]
    roots[ii, jj] = roots[ii, jj][:, ::-1]
    return int(swap.sum())


# ---------------------------------------------------------------------------------------------
# The solve
# ---------------------------------------------------------------------------------------------

def _assemble(mask, index, tau_b, w_full, cfg: FieldConfig):
    """The system over ``X = [c0; c2]`` of the band pixels, split into its real and coupling parts.

    The Hermitian matrix is ``[[K, diag(o)], [diag(conj o), K]]`` with the *real* ``K = diag(w + α m)
    + β L`` shared by both coefficients and the diagonal coupling ``o = (w − α m) τ²``.  It is never
    formed: :func:`_field_operator` applies ``K`` to the four real columns ``Re/Im c0, Re/Im c2`` in
    one sparse product (a third of the memory traffic of the complex ``2n × 2n`` matrix).

    Returns
    -------
    k : scipy.sparse.csr_matrix
        real (n, n).
    off : numpy.ndarray
        complex (n,), the coupling ``o``.
    rhs : numpy.ndarray
        float (n, 4), the right-hand side as ``Re/Im`` of ``[-(w + α m) τ⁴, -(w − α m) τ²]``.
    """
    w_b = w_full[mask]
    m = (np.abs(tau_b) > 0).astype(np.float64)  # the orthogonal term applies where τ ≠ 0
    t2 = tau_b ** 2
    t4 = t2 ** 2
    lap = _smart_laplacian(mask, index, smart_weights(w_full))
    plus = w_b + cfg.alpha * m
    minus = w_b - cfg.alpha * m
    k = (sp.diags(plus) + cfg.beta * lap).tocsr()
    rhs = np.stack([-plus * t4, -minus * t2], axis=1).astype(np.complex128)
    return k, (minus * t2).astype(np.complex128), _as_real(rhs)


def _as_real(x: np.ndarray) -> np.ndarray:
    """complex (n, 2) → float (n, 4) columns ``Re c0, Im c0, Re c2, Im c2`` (a copy, C order)."""
    return np.ascontiguousarray(x).view(np.float64).copy()


def _field_operator(k: sp.csr_matrix, off: np.ndarray, compiled: bool = False):
    """``X ↦ A X`` for the four real columns of ``[c0, c2]`` (see :func:`_assemble`).

    ``compiled``: the sparse product by a numba loop (:func:`stages.field.kernel.sparse_product`,
    the same result to the last bit, without scipy's dispatch) and the coupling's complex products
    (numpy's, as below) into buffers that each call overwrites (the CG reads a product before it
    asks for the next).
    """
    if compiled:
        from stages.field.kernel import sparse_product

        off_conj = off.conj()
        y, product = np.empty((k.shape[0], 4)), np.empty(k.shape[0], np.complex128)

        def apply_compiled(x: np.ndarray) -> np.ndarray:
            sparse_product(k.indptr, k.indices, k.data, x, y)
            yc, xc = y.view(np.complex128), x.view(np.complex128)
            yc[:, 0] += np.multiply(off, xc[:, 1], out=product)
            yc[:, 1] += np.multiply(off_conj, xc[:, 0], out=product)
            return y
        return apply_compiled

    def apply(x: np.ndarray) -> np.ndarray:
        y = k @ x
        yc, xc = y.view(np.complex128), x.view(np.complex128)
        yc[:, 0] += off * xc[:, 1]
        yc[:, 1] += off.conj() * xc[:, 0]
        return y
    return apply


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
    index = _region_index(mask)
    n = int(mask.sum())
    tau_b = tau[mask]
    stats: dict = {"unknowns": 2 * n, "band_pixels": n, "cg_iterations": [], "cg_converged": [],
                   "singular_pixels": [], "nonzeros": [], "tie_swapped": 0}
    c0 = np.zeros((h, w), np.complex128)
    c2 = np.zeros((h, w), np.complex128)
    roots = np.zeros((h, w, 2), np.complex128)
    singular = np.zeros((h, w), bool)
    if n > 0:
        w_cur = w0.copy()
        x = None
        best = None
        maxiter = max(1, cfg.cg_max_iterations)
        # The loop keeps band values only (the best solve's x and singular pixels): full-image copies
        # per re-solve cost 0.4 GB and 7 s on a 6 Mpx scan.  `roots` off the band stays 0 throughout.
        for _ in range(max(1, cfg.max_singularity_iterations)):
            k, off, rhs = _assemble(mask, index, tau_b, w_cur, cfg)
            x0 = x if (cfg.warm_start and x is not None) else None
            x, iters, info = _conjugate_gradient(_field_operator(k, off, compiled=True), k.diagonal(), rhs, x0,
                                                 cfg.cg_rtol, maxiter, compiled=True)
            stats["cg_iterations"].append(iters)
            stats["cg_converged"].append(info)
            stats["nonzeros"].append(2 * int(k.nnz) + 2 * n)  # of the complex 2n × 2n matrix
            xc = x.view(np.complex128)
            roots[mask] = polyvector_roots(xc[:, 0], xc[:, 1])
            singular = singular_pixels(singular_cells(roots, mask), (h, w))
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
        c0[mask], c2[mask] = xc[:, 0], xc[:, 1]
        roots[mask] = polyvector_roots(xc[:, 0], xc[:, 1])
        stats["tie_swapped"] = _order_ties(roots, mask, tau, gmag, cfg.tie_tolerance, cfg.tie_sigma)
    stats["solve_seconds"] = time.perf_counter() - t_start
    return {"c0": c0, "c2": c2, "roots": roots, "singular": singular, "smart_weights": smart_weights(w0),
            "stats": stats}


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
    out = compute_field(grey.astype(np.float64), mask.astype(bool), conf, piece_windows(prep.data, grey.shape))
    arrays = {
        "c0": out["c0"].astype(np.complex64), "c2": out["c2"].astype(np.complex64),
        "roots": out["roots"].astype(np.complex64), "singular": out["singular"],
        "smart_weights": out["smart_weights"].astype(np.float32),
    }
    notes = []
    capped = sum(not c for c in out["stats"]["cg_converged"])
    if capped:
        notes.append(f"{capped} of {len(out['stats']['cg_converged'])} solves stopped at field.cg_max_iterations "
                     f"({conf.cg_max_iterations}) before field.cg_rtol: the field may be less smooth")
    return Artifact(arrays=arrays, data=out["stats"], notes=notes)
