"""The field's linear system and its solve: sparse operators, assembly and conjugate gradients (step 3).

The energy of :mod:`stages.field.stage` (see its docstring) leads to normal equations over
``X = [c0; c2]`` of the band pixels: the finite differences restricted to the band
(:func:`_difference_operator`) and the smart-weighted Laplacian ``L = Σ Dᵀ diag(s) D``
(:func:`_smart_laplacian`), the system split into a real part and a diagonal coupling
(:func:`_assemble`) and applied to four real columns without forming the complex matrix
(:func:`_field_operator`), solved by a hand-written Jacobi-preconditioned CG
(:func:`_conjugate_gradient`, which says why not scipy's) on each block of independent band
components (:func:`_solve_blocks`, :func:`_blockwise_cg`).  The extension stage solves its own
system with the same pieces; the field stage (:func:`stages.field.stage.compute_field`) runs the
singularity loop around them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp


if TYPE_CHECKING:
    from stages.field import FieldConfig


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


def _band_differences(region: np.ndarray, index: np.ndarray) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """The difference operators along rows and columns (:func:`_difference_operator`, axes 0 and 1).

    They depend on the region alone: the singularity loop builds them once and re-weights them on
    every pass (:func:`_weighted_laplacian`).
    """
    return _difference_operator(region, index, 0), _difference_operator(region, index, 1)


def _weighted_laplacian(differences, s_band: np.ndarray) -> sp.csr_matrix:
    """``L = Σ_dir Dᵀ diag(s) D`` of prebuilt difference operators and per-pixel weights ``s``."""
    sd = sp.diags(s_band)
    lap = None
    for d in differences:
        term = (d.T @ sd @ d)
        lap = term if lap is None else lap + term
    return lap.tocsr()


def _smart_laplacian(region: np.ndarray, s: np.ndarray) -> sp.csr_matrix:
    """``L = Σ_dir Dᵀ diag(s) D`` over the pixels of ``region`` (real symmetric PSD); ``s`` (H, W).

    The pixel index and the difference operators are gone before the product is returned, and the
    weights are taken (as float64) on the region only: the extension builds it over a page's dilated band.
    """
    return _weighted_laplacian(_band_differences(region, _region_index(region)),
                               np.asarray(s[region], np.float64))


def _region_index(region: np.ndarray) -> np.ndarray:
    index = np.full(region.shape, -1, dtype=np.int64)
    index[region] = np.arange(int(region.sum()))
    return index


# Unknowns (pixels) per solve block.  A block's CG vectors and matrix (≈ 20 MB at 2¹⁶ pixels) stay in
# the 32 MB L3 cache; one system for a whole 4×4 page (0.57 M pixels) streams them from memory and each
# CG iteration costs 1.4× more per pixel (stages/DECISIONS.md, field, 2026-11-29).  Every one of the 14
# drawings (bands ≤ 36 k pixels) is a single block, solved exactly as before.
BLOCK_UNKNOWNS = 1 << 16


def _solve_blocks(region: np.ndarray, unknowns: np.ndarray, limit: int | None = None) -> list[np.ndarray]:
    """Independent blocks of a system on ``region``: its 4-connected components, grouped in label order.

    The difference operator couples a pixel only to its 4-neighbours in the region (through the
    pixel between them, for the central differences), so the components of the region are independent
    blocks of the matrix.  A component starts a new block when the unknowns before it reach a multiple
    of ``limit`` (a block then holds at most ``limit`` plus one component's unknowns).

    Parameters
    ----------
    region : numpy.ndarray
        bool (H, W), the pixels the operator spans.
    unknowns : numpy.ndarray
        bool (H, W), the pixels solved for (a subset of ``region``; numbered in raster order).
    limit : int, optional
        Unknowns per block; :data:`BLOCK_UNKNOWNS` by default.

    Returns
    -------
    list of numpy.ndarray
        Per block, the increasing positions of its pixels among the unknowns; one block (all of
        them) when they number at most ``limit``.
    """
    limit = BLOCK_UNKNOWNS if limit is None else limit
    n = int(unknowns.sum())
    if n <= limit:
        return [np.arange(n)]
    labels, count = ndi.label(region)
    label_of = labels[unknowns]
    sizes = np.bincount(label_of, minlength=count + 1)
    first = np.cumsum(sizes) - sizes  # unknowns before each component, in label order
    block_of = np.unique(first // limit, return_inverse=True)[1].reshape(-1)[label_of]
    order = np.argsort(block_of, kind="stable")
    return [b for b in np.split(order, np.cumsum(np.bincount(block_of))[:-1]) if len(b)]


def _submatrix(k: sp.csr_matrix, sel: np.ndarray, local: np.ndarray) -> sp.csr_matrix:
    """Rows and columns ``sel`` of ``k`` for a block whose rows reach no column outside it.

    ``local`` (length ``k.shape[0]``, scratch) gets the block's numbering.  Each row keeps the order of
    its stored entries, so the block's products sum as the whole matrix's do.
    """
    local[sel] = np.arange(len(sel))
    rows = k[sel]
    return sp.csr_matrix((rows.data, local[rows.indices], rows.indptr), shape=(len(sel), len(sel)))


def _blockwise_cg(k: sp.csr_matrix, off: np.ndarray | None, rhs: np.ndarray, x0: np.ndarray | None,
                  blocks: list[np.ndarray], rtol: float, maxiter: int,
                  compiled: bool = False) -> tuple[np.ndarray, list[int], bool]:
    """:func:`_conjugate_gradient` on each block of a block-diagonal system (:func:`_solve_blocks`).

    The operator is the field's (:func:`_field_operator` of ``k`` and the coupling ``off``), or ``k``
    alone when ``off`` is None (the extension's).  Each block stops on its own residual (``rtol`` of
    its right-hand side), so the work is the sum of the blocks' and each block's vectors stay in cache.

    Returns
    -------
    x, iterations (per block), converged (all blocks)
    """
    local = np.empty(k.shape[0], np.int64) if len(blocks) > 1 else None
    x = np.zeros_like(rhs)
    iterations, converged = [], True
    for sel in blocks:
        # One block is the whole system: no copy of it (the same solve, bit for bit, as without blocks).
        kb = k if local is None else _submatrix(k, sel, local)
        apply = kb.__matmul__ if off is None else _field_operator(kb, off[sel], compiled=compiled)
        xb, iters, ok = _conjugate_gradient(apply, kb.diagonal(), rhs[sel], None if x0 is None else x0[sel],
                                            rtol, maxiter, compiled=compiled)
        x[sel] = xb
        iterations.append(iters)
        converged &= ok
    return x, iterations, converged


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
# The system
# ---------------------------------------------------------------------------------------------

def _assemble(differences, tau_b: np.ndarray, w_b: np.ndarray, s_b: np.ndarray, cfg: FieldConfig):
    """The system over ``X = [c0; c2]`` of the band pixels, split into its real and coupling parts.

    The Hermitian matrix is ``[[K, diag(o)], [diag(conj o), K]]`` with the *real* ``K = diag(w + α m)
    + β L`` shared by both coefficients and the diagonal coupling ``o = (w − α m) τ²``.  It is never
    formed: :func:`_field_operator` applies ``K`` to the four real columns ``Re/Im c0, Re/Im c2`` in
    one sparse product (a third of the memory traffic of the complex ``2n × 2n`` matrix).

    Parameters
    ----------
    differences : tuple of scipy.sparse.csr_matrix
        The band's difference operators (:func:`_band_differences`), the same on every pass.
    tau_b, w_b, s_b : numpy.ndarray
        Per band pixel: image tangent τ, coherence weight w and its smart weight s
        (:func:`stages.field.data_terms.band_smart_weights`).
    cfg : FieldConfig

    Returns
    -------
    k : scipy.sparse.csr_matrix
        real (n, n).
    off : numpy.ndarray
        complex (n,), the coupling ``o``.
    rhs : numpy.ndarray
        float (n, 4), the right-hand side as ``Re/Im`` of ``[-(w + α m) τ⁴, -(w − α m) τ²]``.
    """
    m = (np.abs(tau_b) > 0).astype(np.float64)  # the orthogonal term applies where τ ≠ 0
    t2 = tau_b ** 2
    t4 = t2 ** 2
    lap = _weighted_laplacian(differences, s_b)
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
