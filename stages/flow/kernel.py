"""The compiled PolyVector flow kernel (paper §5.4, Eq. 5, 6a, 10) and its building blocks.

One numba kernel runs the whole iteration loop of every path block (see :mod:`stages.flow.stage` for the
scheme and its choices); the functions marked ``inline="always"`` are its parts, shared by the energy
and the gradient that tests check it against.
"""

from __future__ import annotations

import math
import warnings

import numba
import numpy as np
from numba.core.errors import NumbaPerformanceWarning

# _flow_kernel asks for numba's parallel pipeline for its speed, not for a parallel region (see its
# docstring): numba's warning that it found nothing to parallelise is expected.
warnings.filterwarnings("ignore", message="The keyword argument 'parallel=True' was specified but no transformation",
                        category=NumbaPerformanceWarning)

#: fastmath flags of the kernel: no ``reassoc`` (run-to-run differences), no ``nnan``/``ninf`` (the
#: non-finite check must stay); see stages/DECISIONS.md.
_FM = {"contract", "arcp", "nsz", "afn"}


@numba.njit(cache=True, inline="always", error_model="numpy", fastmath=_FM)
def _bilinear(c: np.ndarray, x: float, y: float):
    """Bilinear value and exact x/y derivatives of a complex pixel-centre grid at (x, y).

    Pixel ``[i, j]`` has its centre at ``(j + .5, i + .5)``; samples outside the image count as 0.
    Compiled copy of :func:`stages.geometry.bilinear` (the reference), with the derivatives.
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
                e = math.exp(-0.5 * d2 / s2)             # S = Σ_k exp(−|x − p_k|² / 2σ_k²) (Eq. 5)
                s += e
                gx -= e * dx / s2
                gy -= e * dy / s2
        if s >= 1.0:
            return 0.0, 0.0, 0.0
    return 1.0 - s, -gx, -gy                                 # B = max(1 − S, 0) (Eq. 5), ∇B = −∇S


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
    f = tau2 * tau2 + a2 * tau2 + a0                # f(m, τ) = τ⁴ + c2 τ² + c0, g = |f|² (Eq. 5's |f(x, τ)|²)
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
    # W = g + B + λ (Eq. 5's weight b(x) plus the alignment); P = (q/2) ∇_x(g + B)(m) (§5.4).
    return t, g + b + lam, q, ft, (0.5 * q) * complex(gx + bx, gy + by), h


@numba.njit(cache=True)
def _path_energy(z, n, fld, cen, sig, rho2, c0i, nc, win, cut2, lam, eps, home):
    """Discrete Eq. 6a of one polyline, Σ (g + B + λ) q (updates the home indices)."""
    e = 0.0
    for j in range(1, n):
        _, w, q, _, _, home[j] = _edge(fld, cen, sig, rho2, c0i, nc, win, cut2, lam, eps, z[j - 1], z[j],
                                       home[j])
        e += w * q                                          # E_ε = Σ_j W_j q_j (discrete Eq. 6a)
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
    """Uniform arc-length resampling of z[:n] in place (ends kept); carries the home indices.

    Compiled counterpart of :func:`stages.geometry.resample_uniform` (the reference) for a fixed count
    of complex points inside the flow kernel, which cannot call the numpy version.
    """
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


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy", fastmath=_FM)
def _flow_kernel(order, z, zoff, cen, sig, rho2, dist, coff, home, window, fld, iterations, dt, lam, eps,
                 resample_factor, cut2, d0, smin, smax, e_init, e_final, n_resample, n_reject, failed):
    """Run the PolyVector flow on the path blocks ``order`` lists, one after another (in place on ``z`` and
    ``home``; each block touches only its own slices, so threads may run disjoint lists at once).

    ``parallel=True`` with no ``prange``: numba's parallel pipeline compiles this loop 1.6× faster than
    its plain one (elephant, one thread: 0.95 vs 1.6 s CPU) and creates no parallel region, so it
    compiles in 3.5 s instead of the ``prange`` kernel's 8.3 s; the threads are the caller's
    (stages/DECISIONS.md, flow, 2026-11-26).
    """
    for i in range(order.shape[0]):
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
                    e_cur += w * q                                   # E_ε = Σ_j W_j q_j (discrete Eq. 6a)
                    k_cur = w / q                                    # k_j = W_j / q_j, implicit (Eq. 10's G_j / q_j, isotropic part)
                    d_cur = dist[c0i + h]
                    if j >= 2:
                        r = j - 2
                        d = 0.5 * (d_prev + d_cur)
                        s = smax if d <= 0.0 else min(max(d0 / d, smin), smax)
                        mb = (q_prev + q) / s
                        mass = mb * inv2dt                           # M_j = (q_j + q_{j+1}) / (2 α s_j) (Eq. 10's 1/2δ term)
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



def _pack_field(c0: np.ndarray, c2: np.ndarray) -> np.ndarray:
    """float64 (H + 2, W + 2, 4): real and imaginary parts of c0 and c2 with a one-pixel zero border.

    One pixel's coefficients share a cache line, and the border spares the kernel's bilinear lookup
    its per-corner bounds tests (the field is zero outside the image).
    """
    h, w = c0.shape
    fld = np.zeros((h + 2, w + 2, 4), np.float64)
    # Channel by channel from views: a stacked temporary was a second page-sized copy (+190 MB at 2000×3000).
    for k, part in enumerate((c0.real, c0.imag, c2.real, c2.imag)):
        fld[1:-1, 1:-1, k] = part
    return fld


