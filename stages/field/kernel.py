"""Compiled steps of the field's conjugate gradients (:func:`stages.field.stage._conjugate_gradient`).

One CG iteration in numpy made about fifteen passes over arrays of the band's size — the sparse
product through scipy's dispatch, the coupling's complex temporaries, the updates of ``x``, ``r``,
``z`` and ``p`` — while the sparse product itself was a quarter of the time. These kernels make the
same arithmetic in fewer passes, operation for operation as numpy and scipy make it (each product and
sum rounded on its own, the sparse rows summed in CSR order from zero), so the solve is the same to
the last bit (tested). The inner products stay numpy's (``einsum``: its summation order), and so does
the coupling's complex product (numpy's SIMD loops may fuse its multiply-adds on one CPU and not on
another).
"""

from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True)
def sparse_product(indptr, indices, data, x, y):
    """``y = K x`` for a CSR matrix ``K`` and a float64 (n, 4) ``x`` (``y`` overwritten), summed as
    scipy's ``csr_matvecs`` sums: each row from zero, in the order of its stored entries."""
    n = len(indptr) - 1
    for i in range(n):
        y0 = 0.0
        y1 = 0.0
        y2 = 0.0
        y3 = 0.0
        for jj in range(indptr[i], indptr[i + 1]):
            j = indices[jj]
            a = data[jj]
            y0 += a * x[j, 0]
            y1 += a * x[j, 1]
            y2 += a * x[j, 2]
            y3 += a * x[j, 3]
        y[i, 0] = y0
        y[i, 1] = y1
        y[i, 2] = y2
        y[i, 3] = y3


@njit(cache=True, nogil=True)
def step_solution(x, r, z, p, ap, inv, step):
    """``x += step·p``, ``r −= step·Ap``, ``z = inv·r`` in one pass (float64 (n, m); ``inv`` (n,))."""
    n, m = x.shape
    for i in range(n):
        s = inv[i]
        for k in range(m):
            x[i, k] = x[i, k] + p[i, k] * step
            rik = r[i, k] - ap[i, k] * step
            r[i, k] = rik
            z[i, k] = s * rik


@njit(cache=True, nogil=True)
def next_direction(p, z, beta):
    """``p = beta·p + z`` in place (float64 (n, m))."""
    n, m = p.shape
    for i in range(n):
        for k in range(m):
            p[i, k] = p[i, k] * beta + z[i, k]

