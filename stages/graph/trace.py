"""Streamline tracing of the PolyVector field (paper §4.1; B19 §A.2).

Every band pixel seeds one streamline of its larger-modulus root, traced from the pixel centre in both
directions by explicit Euler steps of ``step`` px.  At each step the coefficients are bilinearly
interpolated (off-band pixels count as 0), the quartic is solved again and the trace continues along
the one of ``±u/|u|, ±v/|v|`` best aligned with its previous direction (ties within ``tie`` with the
other family are averaged).  That continuation is what carries a trace straight through an X junction.

A half-trace stops when it

* leaves the image or steps onto a pixel off the band, or the field there is zero (``LEFT``),
* steps onto a singular pixel (``SINGULAR``),
* *merges*: its pixel already holds a sample closer than ``merge_distance`` with ``|cos| >
  merge_cos`` (``MERGED``).  Samples of the curve being traced count too, except those fewer than
  ``self_merge_lag`` steps away along it, so a closed loop closes on itself but a trace never stops on
  its own last points (the reference's lagged queue, expressed as an index distance),
* reaches ``max_half_samples`` samples (``CAP``).

A seed whose own centre already merges is skipped (most seeds: lanes fill the band at ~``merge_distance``
spacing).  Traces of ≤ 2 samples are dropped, and so is a trace all of whose samples lie within
``merge_distance`` of a single earlier curve (the reference's duplicate test).

The kernel is one sequential numba loop: each trace depends on every earlier one through the merge
test, so it cannot be vectorised over seeds without changing the result (and the merge test is what
keeps the lanes ~``merge_distance`` apart instead of one full-length trace per band pixel).  Measured
on the scanned drawings (20–35 k band pixels, 1–2 M samples): 0.3–0.9 s.  During the trace the samples
live in per-pixel linked lists (``head``/``next``), which the merge test walks; the cross-sections
index them afresh (:func:`stages.graph.cross_section._cell_index`).  A sample's curve and its step along
it are not stored: the curves lie one after another, the one being traced last, so both follow from the
sample's id (20 bytes a sample in the kernel, was 28; 34 M samples on a 4x4 page).
"""

from __future__ import annotations

import cmath
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

# Why a half-trace stopped (per curve end).
LEFT, SINGULAR, MERGED, CAP, DEGENERATE = 0, 1, 2, 3, 4


@njit(cache=True)
def coeffs_at(c0, c2, x, y):
    """Bilinear c0, c2 at point (x, y) (pixel centres at +0.5); outside the image counts as 0.

    Compiled copy of :func:`stages.geometry.bilinear` (the reference): nopython code cannot call it.
    """
    h, w = c0.shape
    u = x - 0.5
    v = y - 0.5
    j0 = math.floor(u)
    i0 = math.floor(v)
    fu = u - j0
    fv = v - i0
    a0 = 0j
    a2 = 0j
    for di in range(2):
        ii = i0 + di
        if ii < 0 or ii >= h:
            continue
        wy = fv if di == 1 else 1.0 - fv
        for dj in range(2):
            jj = j0 + dj
            if jj < 0 or jj >= w:
                continue
            wt = wy * (fu if dj == 1 else 1.0 - fu)
            a0 += wt * c0[ii, jj]
            a2 += wt * c2[ii, jj]
    return a0, a2


@njit(cache=True)
def quartic_roots(a0, a2):
    """Roots u, v of z⁴ + a2 z² + a0 (the other two are −u, −v); same branches as field.polyvector_roots."""
    disc = cmath.sqrt(a2 * a2 - 4.0 * a0)
    return cmath.sqrt(0.5 * (-a2 + disc)), cmath.sqrt(0.5 * (-a2 - disc))


@njit(cache=True)
def choose_direction(u, v, d, tie):
    """Of ±u/|u|, ±v/|v| the unit direction best aligned with ``d`` (B19 ``chooseRoot``).

    Returns ``(direction, family, ok)``: family 0 if it came from ``u``, 1 from ``v``; ``ok`` is False
    when both roots vanish.  When the two families score within ``tie`` their (signed) average is used.
    """
    nu = abs(u)
    nv = abs(v)
    su = -2.0
    sv = -2.0
    du = 0j
    dv = 0j
    if nu > 1e-12:
        du = u / nu
        su = du.real * d.real + du.imag * d.imag
        if su < 0:
            du = -du
            su = -su
    if nv > 1e-12:
        dv = v / nv
        sv = dv.real * d.real + dv.imag * d.imag
        if sv < 0:
            dv = -dv
            sv = -sv
    if su < -1.0 and sv < -1.0:
        return 0j, -1, False
    if su >= sv:
        best, fam, margin = du, 0, su - sv
    else:
        best, fam, margin = dv, 1, sv - su
    if margin < tie:
        m = du + dv
        nm = abs(m)
        if nm > 1e-12:
            best = m / nm
    return best, fam, True


@njit(cache=True)
def _grow_f(a, n):
    # an element loop, not ``b[:len(a)] = a``: a slice assignment also compiles numba's shape-mismatch
    # error message (string formatting, ~3 s on the first run; stages/DECISIONS.md)
    b = np.empty(n, a.dtype)
    for q in range(len(a)):
        b[q] = a[q]
    return b


@njit(cache=True)
def _merges(head, nxt, sx, sy, tx, ty, w, qx, qy, dx, dy, base, nf, t, lag, d2, mcos):
    """Whether a sample at (qx, qy) heading (dx, dy), step ``t`` of the curve being traced, merges.

    The curve being traced holds the samples from ``base`` on, its forward half first (``nf`` samples,
    the seed at ``base``: step ``s − base``), then its backward half (step ``−(s − base − nf + 1)``): so
    a sample's curve and in-curve step follow from its id, with no curve id or step stored a sample
    (8 bytes, 0.27 GB on a 4x4 page).  ``base`` past every sample (the seed test) lags no sample.
    """
    s = head[int(qy) * w + int(qx)]
    while s >= 0:
        own = False
        if s >= base:
            si = s - base if s - base < nf else base + nf - 1 - s
            own = abs(si - t) <= lag
        if not own:
            ex = sx[s] - qx
            ey = sy[s] - qy
            if ex * ex + ey * ey < d2 and abs(tx[s] * dx + ty[s] * dy) > mcos:
                return True
        s = nxt[s]
    return False


@njit(cache=True)
def _curve_of(c_start, nc, s):
    """The curve holding sample ``s`` of the kept curves (they lie one after another from ``c_start``)."""
    lo = np.int64(0)
    hi = nc - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if c_start[mid] <= s:
            lo = mid
        else:
            hi = mid - 1
    return lo


@njit(cache=True)
def _is_duplicate(head, nxt, sx, sy, c_start, c_len, nc, w, base, n, d2):
    """Every sample in [base, n) lies within sqrt(d2) of one same earlier curve.

    The earlier curves are ``c_start[:nc]``, ``c_len[:nc]`` (samples before ``base``); the samples of the
    curve being tested are those from ``base`` on.
    """
    s = head[int(sy[base]) * w + int(sx[base])]
    cands = np.empty(64, np.int64)
    nc_ = 0
    while s >= 0 and nc_ < 64:
        if s < base:
            c = _curve_of(c_start, nc, s)
            seen = False
            for q in range(nc_):
                if cands[q] == c:
                    seen = True
                    break
            if not seen:
                cands[nc_] = c
                nc_ += 1
        s = nxt[s]
    for q in range(nc_):
        c = cands[q]
        lo = c_start[c]
        hi = lo + c_len[c]
        all_close = True
        for k in range(base, n):
            r = head[int(sy[k]) * w + int(sx[k])]
            close = False
            while r >= 0:
                if lo <= r < hi:
                    ex = sx[r] - sx[k]
                    ey = sy[r] - sy[k]
                    if ex * ex + ey * ey < d2:
                        close = True
                        break
                r = nxt[r]
            if not close:
                all_close = False
                break
        if all_close:
            return True
    return False


@njit(cache=True)
def _grow_rows(a, n):
    """A (2, n) copy of the (2, m) ``a``'s first ``m`` columns (an element loop, as :func:`_grow_f`)."""
    b = np.empty((2, n), a.dtype)
    for r in range(2):
        for q in range(a.shape[1]):
            b[r, q] = a[r, q]
    return b


@njit(cache=True)
def _trace_all(c0, c2, band, singular, seed_dir, h, max_half, merge_d2, merge_cos, lag, tie, cap):
    H, W = band.shape
    head = np.full(H * W, -1, np.int32)
    # the samples' (x, y) and tangents as the rows of (2, cap) buffers: the streamlines' (2, N) columns
    # come out as views, not stacked after the kernel (a copy as large as the kernel's own samples)
    sxy = np.empty((2, cap), np.float32)
    stg = np.empty((2, cap), np.float32)
    sx = sxy[0]; sy = sxy[1]; tx = stg[0]; ty = stg[1]
    # no curve id and no in-curve step a sample: both follow from the sample's id (_merges,
    # _is_duplicate); 20 bytes a sample with the pixels' lists, was 28 (stages/DECISIONS.md, graph)
    nxt = np.empty(cap, np.int32)
    # counters start as int64, not as the literal 0: a literal reaches the helpers' signatures and
    # compiles each of them once more (stages/DECISIONS.md)
    n = np.int64(0)
    ccap = np.int64(1024)
    c_start = np.empty(ccap, np.int64)
    c_len = np.empty(ccap, np.int64)
    c_end = np.empty((ccap, 2), np.int8)
    nc = np.int64(0)
    tmp = np.empty((0, 4), np.float32)
    r = np.int64(0)
    for i in range(H):
        for j in range(W):
            if not band[i, j]:
                continue
            # seed_dir holds the band pixels only, in this loop's (row-major) order
            d0 = seed_dir[r]
            r += 1
            if singular[i, j] or d0 == 0:
                continue
            x0 = j + 0.5
            y0 = i + 0.5
            if _merges(head, nxt, sx, sy, tx, ty, W, x0, y0, d0.real, d0.imag, n, n, np.int64(0), lag,
                       merge_d2, merge_cos):
                continue
            # room for the longest curve one seed can add, made here and not per step: an array
            # reassigned inside the step loop costs numba's reference counting on every step
            # (NRT_incref/decref were 40 % of the kernel's time; stages/DECISIONS.md, graph)
            if n + 2 * max_half + 2 >= cap:
                while n + 2 * max_half + 2 >= cap:
                    cap *= 2
                sxy = _grow_rows(sxy, cap); stg = _grow_rows(stg, cap)
                sx = sxy[0]; sy = sxy[1]; tx = stg[0]; ty = stg[1]
                nxt = _grow_f(nxt, cap)
            base = n
            reasons = np.empty(2, np.int8)
            # while the forward half is traced all the curve's samples are forward ones
            nf = np.int64(2 * max_half + 2)
            for half in range(2):
                sgn = 1 if half == 0 else -1
                px = x0
                py = y0
                d = d0 * sgn
                k = 0
                if half == 0:
                    # the seed itself is sample 0 of the forward half
                    sx[n] = x0; sy[n] = y0; tx[n] = d0.real; ty[n] = d0.imag
                    p = i * W + j
                    nxt[n] = head[p]
                    head[p] = n
                    n += 1
                reason = CAP
                while k < max_half:
                    a0, a2 = coeffs_at(c0, c2, px, py)
                    u, v = quartic_roots(a0, a2)
                    nd, fam, ok = choose_direction(u, v, d, tie)
                    if not ok:
                        reason = DEGENERATE
                        break
                    # samples are stored as float32: test the pixel of the rounded position, or a
                    # point a hair inside the last row/column could be stored outside the image
                    qx = np.float64(np.float32(px + h * nd.real))
                    qy = np.float64(np.float32(py + h * nd.imag))
                    if qx < 0 or qy < 0 or qx >= W or qy >= H:
                        reason = LEFT
                        break
                    qi = int(qy)
                    qj = int(qx)
                    if not band[qi, qj]:
                        reason = LEFT
                        break
                    if singular[qi, qj]:
                        reason = SINGULAR
                        break
                    k += 1
                    if _merges(head, nxt, sx, sy, tx, ty, W, qx, qy, nd.real, nd.imag, base, nf, sgn * k,
                               lag, merge_d2, merge_cos):
                        reason = MERGED
                        break
                    sx[n] = qx; sy[n] = qy
                    # tangents are oriented along the final curve order (backward half reversed)
                    tx[n] = sgn * nd.real; ty[n] = sgn * nd.imag
                    p = qi * W + qj
                    nxt[n] = head[p]
                    head[p] = n
                    n += 1
                    px = qx
                    py = qy
                    d = nd
                reasons[half] = reason
                if half == 0:
                    nf = n - base
            total = n - base
            keep = total > 2
            if keep and _is_duplicate(head, nxt, sx, sy, c_start, c_len, nc, W, base, n, merge_d2):
                keep = False
            # this curve's samples sit at the front of their pixels' lists: unlink them
            for s in range(n - 1, base - 1, -1):
                p = int(sy[s]) * W + int(sx[s])
                while head[p] >= base:
                    head[p] = nxt[head[p]]
            if not keep:
                n = base
                continue
            # lay the curve out as reversed backward half + forward half, then relink in that order
            if tmp.shape[0] < total:
                tmp = np.empty((2 * total, 4), np.float32)
            nb = total - nf
            for q in range(nb):
                s = base + nf + nb - 1 - q
                tmp[q, 0] = sx[s]; tmp[q, 1] = sy[s]; tmp[q, 2] = tx[s]; tmp[q, 3] = ty[s]
            for q in range(nf):
                s = base + q
                tmp[nb + q, 0] = sx[s]; tmp[nb + q, 1] = sy[s]; tmp[nb + q, 2] = tx[s]; tmp[nb + q, 3] = ty[s]
            for q in range(total):
                s = base + q
                sx[s] = tmp[q, 0]; sy[s] = tmp[q, 1]; tx[s] = tmp[q, 2]; ty[s] = tmp[q, 3]
                p = int(sy[s]) * W + int(sx[s])
                nxt[s] = head[p]
                head[p] = s
            if nc >= ccap:
                ccap *= 2
                c_start = _grow_f(c_start, ccap)
                c_len = _grow_f(c_len, ccap)
                ce = np.empty((ccap, 2), np.int8)
                for q in range(nc):
                    ce[q, 0] = c_end[q, 0]
                    ce[q, 1] = c_end[q, 1]
                c_end = ce
            c_start[nc] = base
            c_len[nc] = total
            c_end[nc, 0] = reasons[1]
            c_end[nc, 1] = reasons[0]
            nc += 1
    # views, not copies: a copy of the ~28 bytes a sample would double the samples' memory at the
    # return (a 4x4 page: 34 M samples, 1 GB); the buffers' untouched tails take no memory
    return sxy[:, :n], stg[:, :n], c_start[:nc], c_len[:nc], c_end[:nc]


@dataclass
class Streamlines:
    """Traced curves.

    Attributes
    ----------
    xy : numpy.ndarray
        float32 (N, 2) samples (x, y), curve after curve; the two rows of a (2, ·) array seen as
        columns (``xy[:, 0]`` is contiguous).
    tangent : numpy.ndarray
        float32 (N, 2) unit tangents, oriented along each curve; laid out like ``xy``.
    start, length : numpy.ndarray
        int64 (C,) first sample and number of samples of each curve.
    end_reason : numpy.ndarray
        int8 (C, 2) why the curve stopped at its first / last sample (``LEFT``, ``SINGULAR``,
        ``MERGED``, ``CAP``, ``DEGENERATE``).
    """

    xy: np.ndarray
    tangent: np.ndarray
    start: np.ndarray
    length: np.ndarray
    end_reason: np.ndarray

    @property
    def curve(self) -> np.ndarray:
        """int32 (N,) curve id of each sample, made on demand: the samples lie curve after curve, so no
        stage step keeps one a sample (4 bytes, 0.14 GB on a 4x4 page)."""
        return np.repeat(np.arange(len(self.start), dtype=np.int32), self.length)

    @property
    def offsets(self) -> np.ndarray:
        """int64 (C + 1,) ragged offsets of the curves into ``xy``."""
        return np.concatenate([self.start, [len(self.xy)]]).astype(np.int64)

def field_on_band(c: np.ndarray, band: np.ndarray) -> np.ndarray:
    """The coefficient image as the kernels read it: 0 off the band, complex64 or complex128, C order.

    The kernels' bilinear reads reach a pixel beyond the band, where the field counts as 0.  The field
    stage's arrays already are what the kernels need (complex64, 0 off the band), so they are read as
    they are: a complex128 copy zeroed off the band cost 32 bytes a pixel for c0 and c2, in the trace
    and again in the cross-sections.  The kernels widen each complex64 value to complex128 (exactly)
    before any arithmetic, so the results are those of a complex128 copy.  Any other input is copied.

    Parameters
    ----------
    c : numpy.ndarray
        complex (H, W) c0 or c2.
    band : numpy.ndarray
        bool (H, W), C order, the narrow band.

    Returns
    -------
    numpy.ndarray
        A read-only view of ``c``, or of a copy that is 0 off the band (complex64 stays complex64).
        Read-only always: numba compiles a read-only array (the engine's memo hands the stage read-only
        arrays) as another type than a writable one, so the shipped kernels cover one type, not two.
    """
    c = np.asarray(c)
    if c.dtype != np.complex64:
        c = np.asarray(c, dtype=np.complex128)
    # checked in blocks of rows: a whole-image mask of the off-band values would be page-sized again
    rows = 256
    if not (c.flags.c_contiguous and not any(np.any(c[r:r + rows][~band[r:r + rows]])
                                             for r in range(0, len(c), rows))):
        c = np.ascontiguousarray(np.where(band, c, np.zeros((), c.dtype)))
    view = c.view()
    view.flags.writeable = False
    return view



def trace_streamlines(c0: np.ndarray, c2: np.ndarray, band: np.ndarray, singular: np.ndarray,
                      seed_root: np.ndarray, *, step: float, max_half_samples: int, merge_distance: float,
                      merge_cos: float, self_merge_lag: int, tie: float) -> Streamlines:
    """Trace the field from every band pixel in both directions.

    Parameters
    ----------
    c0, c2 : numpy.ndarray
        complex (H, W) PolyVector coefficients; read as 0 off the band (:func:`field_on_band`).
    band : numpy.ndarray
        bool (H, W), the narrow band.
    singular : numpy.ndarray
        bool (H, W) singular pixels; traces stop on them and no seed starts there.
    seed_root : numpy.ndarray
        complex (H, W) the root each pixel seeds (the larger-modulus root); 0 = no seed (read on the
        band only).
    step : float
        Euler step h in px (reference 0.1).
    max_half_samples : int
        Length cap of each half-trace in samples (reference 10 000).
    merge_distance, merge_cos : float
        Merge test: a sample closer than this with ``|cos|`` above ``merge_cos`` stops the trace.
    self_merge_lag : int
        Own samples fewer than this many steps away along the curve do not stop it.
    tie : float
        Root-choice tie margin (averaged directions).

    Returns
    -------
    Streamlines
    """
    band = np.ascontiguousarray(band, dtype=np.bool_)
    sing = np.ascontiguousarray(singular, dtype=np.bool_)
    c0 = field_on_band(c0, band)
    c2 = field_on_band(c2, band)
    # the seed directions of the band pixels alone (16 bytes a band pixel, not five page-sized
    # temporaries); the same elementwise operations as on the whole image, so the same values
    root = np.asarray(seed_root)[band]
    mod = np.abs(root)
    seed = np.where(mod > 1e-12, root / np.where(mod > 0, mod, 1), 0).astype(np.complex128)
    del root, mod
    cap = max(1024, int(band.sum()) * 64)
    xy, tangent, cs, cl, ce = _trace_all(
        c0, c2, band, sing, seed, float(step), int(max_half_samples),
        float(merge_distance) ** 2, float(merge_cos), int(self_merge_lag), float(tie), cap)
    # (2, N) views of the kernel's buffers seen as (N, 2): the columns are contiguous, so the
    # cross-sections' kernel reads them without copying (four copies were 16 bytes a sample, 0.55 GB
    # on a 4x4 page), and nothing is stacked after the kernel
    return Streamlines(xy=xy.T, tangent=tangent.T, start=cs, length=cl, end_reason=ce)
