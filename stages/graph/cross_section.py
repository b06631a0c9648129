"""Cross-sections of the traced curves: the graph's vertices (paper §4.1, Fig. 7; B19 §A.3), numba kernels.

A *cross-section* through a point ``p`` of streamline ``k`` is the orthogonal trajectory of the field
through ``p``: traced (Euler, same step) along ``i·f`` where ``f`` is the root family ``k`` follows,
continuing at each step with the perpendicular best aligned with the previous heading.  Every streamline
segment it crosses is tested for the *same root family*: its tangent must be closer (|cos|) to the
followed root than to the other root at that point, which excludes the curves of a crossing stroke.
Crossings in singular pixels are skipped.  Sorted by arc length along the cross-section, the crossings
are cut at the first gap larger than ``max_gap`` on each side of ``p``; the contiguous run around ``p``
is the vertex.  A cross-section stops on leaving the band, on a singular pixel (the vertex is then
flagged *next to singularity* if that happened within ``max_gap`` of the run), after ``max_gap`` px
without a crossing, or at ``max_section_length`` px.

``max_gap`` is 1.5 px, not the reference's 1 px: on an axis-aligned stroke the lanes sit on pixel
centres exactly 1 px apart, and a cross-section that is a hair off the normal (or round-off in the
0.1 px steps) measures 1.0000x px, so a 1 px limit cuts such strokes into one-lane vertices of width
0 — which is what happened on horizontal and vertical synthetic lines before the change.

Vertex attributes:

* ``xy``: the midpoint (by arc length) of the run along the cross-section.  The paper says "centroid
  of the cross-section"; the mean of the crossing points (the reference) is pulled towards the side
  where lanes happen to be denser (lanes are ~0.1 px apart where the seeds' offsets are dense and up
  to 1 px apart where the stroke is axis-aligned), the midpoint of the segment is not.
* ``width``: the cross-section diameter (first to last crossing) **plus half a lane spacing**
  (``lane_pad`` = 0.5).  The reference's diameter alone is 0 for a cross-section crossing a single
  streamline, and it measures between the outermost *lanes*, which sit at pixel centres: on an
  axis-aligned stroke they are 1 px apart and the diameter is one pixel short of the band's extent,
  on a slanted stroke lanes are ~0.1 px apart and the diameter is close to it.  Each crossing stands
  for a strip of the band one lane spacing ``g`` wide (the mean gap between consecutive crossings,
  at most 1 px; 1 px for a lone crossing); the band's edge falls on average halfway through the
  outermost strips, so ``g/4`` is added on each side.  Measured on anti-aliased synthetic strokes of
  width 2, 3 and 5 px at 0–133°, the widths of the vertices away from the caps are within 0.75 px of
  the drawn width (the bare diameter is up to 1.5 px short on axis-aligned strokes; diameter + ``g``
  is up to 1.1 px long where half-covered edge pixels pass the band threshold).
* ``root``: the followed root at ``p`` (unit, oriented along streamline ``k``).

**Where cross-sections are taken.**  The reference takes one at each end of every streamline and
nowhere else.  Our streamlines are long (a straight stroke gives lanes running its whole length), so
that would leave a stroke's graph with vertices only near its ends.  Instead stations are placed
along the streamlines so that every sample of every streamline is within about
``cover_factor · station_spacing`` of a cross-section that contains it: streamlines are visited
longest first; along each, at the first sample not yet covered, a cross-section is taken
``station_spacing/2`` further on (or at the curve's end) and marks all its crossings (on every member
streamline) as covered.  Short uncovered gaps (< ``min_station_gap``) between covered stretches are
skipped.  One cross-section thus serves the whole bundle, and a stroke gets a chain of vertices about
``station_spacing`` apart.

This module holds the numba kernels only: the package ships them compiled, checked against the sha256
of this file.  Their Python entry point (:func:`stages.graph.raw_graph.build_cross_sections`), the
edges between the vertices and the :class:`~stages.graph.raw_graph.RawGraph` they make are in
:mod:`stages.graph.raw_graph`, so that editing those leaves the compiled kernels valid.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from stages.graph.trace import _grow_f, choose_direction, coeffs_at, quartic_roots


#: Sub-cells per pixel side of the crossing lookup (cells of 1/4 px).  A cross-section step looks for
#: the streamline segments that cross it among the samples within h of it: in the whole pixels around
#: it that was ~120 samples a step on the scanned elephant, in the sub-cells 16 (stages/DECISIONS.md,
#: graph).  The crossings come in another order than the pixels' lists gave; sorted (stably) by arc
#: length they are the same but for exact ties.
SUB = 4


@njit(cache=True)
def _cell_index(sx, sy, band):
    """The samples grouped by sub-cell of their band pixel (a counting sort, ascending ids in each cell).

    Returns ``(bidx, cell_start, cell_samples)``: ``bidx[row * W + col]`` the band pixel's index (−1 off
    the band); the samples of sub-cell ``bidx · SUB² + b · SUB + a`` (row ``b``, column ``a`` of the
    pixel) are ``cell_samples[cell_start[c]:cell_start[c + 1]]``, so the cells ``a_lo..a_hi`` of one
    row are one contiguous range.
    """
    H, W = band.shape
    # int32, 4 bytes a pixel of the page (int64 was 8); not np.full: one more specialisation to compile
    bidx = np.empty(H * W, np.int32)
    nb = np.int64(0)
    for i in range(H):
        for j in range(W):
            if band[i, j]:
                bidx[i * W + j] = nb
                nb += 1
            else:
                bidx[i * W + j] = -1
    n = len(sx)
    nc = nb * SUB * SUB
    # int32 like the sample ids it points to (int64 was 64 bytes a band pixel, 36 MB on a 4x4 page)
    cell_start = np.zeros(nc + 1, np.int32)
    for t in range(n):
        cell_start[_sub_cell(sx[t], sy[t], bidx, W)] += 1
    for c in range(1, nc):
        cell_start[c] += cell_start[c - 1]   # the end of each cell
    cell_start[nc] = n
    cell_samples = np.empty(n, np.int32)     # sample ids are int32 like the trace's lists
    # filled from the last sample down, each cell's end moving to its start: the ids come out
    # ascending in each cell with no second array of cell slots (a copy of cell_start was 128 bytes
    # a band pixel, 0.13 GB on a 4x4 page).  Each sample's cell is computed again rather than kept
    # from the count: an int64 a sample (0.27 GB on a 4x4 page) for a few arithmetic operations
    for t in range(n - 1, -1, -1):
        c = _sub_cell(sx[t], sy[t], bidx, W)
        cell_start[c] -= 1
        cell_samples[cell_start[c]] = t
    return bidx, cell_start, cell_samples


@njit(cache=True)
def _sub_cell(sx_t, sy_t, bidx, W):
    """The sub-cell of one sample (see :func:`_cell_index`)."""
    x = np.float64(sx_t)
    y = np.float64(sy_t)
    j = int(x)
    i = int(y)
    # every sample lies on a band pixel (the trace stops before leaving the band)
    return (bidx[i * W + j] * (SUB * SUB) + min(int((y - i) * SUB), SUB - 1) * SUB
            + min(int((x - j) * SUB), SUB - 1))


@njit(cache=True)
def _section(c0, c2, band, singular, sx, sy, c_start, c_len, bidx, cell_start, cell_samples, k, g, f, h,
             max_gap, max_steps, tie, cr_curve, cr_param, cr_s, poly_s, poly_x, poly_y):
    """One cross-section through sample ``g`` of curve ``k`` following unit root ``f``.

    Fills the work buffers (crossings ``cr_*``; the cross-section polyline ``poly_*`` for both sides,
    side +1 first) and returns ``(n_crossings, n_poly_plus, n_poly_minus, sing_plus, sing_minus)`` where
    ``sing_*`` is the arc length at which that side stopped on a singular pixel (inf if it did not).
    """
    H, W = band.shape
    n_curves = len(c_start)
    ncr = 0
    x0 = np.float64(sx[g])   # float64 from the start: a float32 start compiles coeffs_at twice
    y0 = np.float64(sy[g])
    i_seed = g - c_start[k]
    # the seed crossing itself
    cr_curve[0] = k
    cr_param[0] = i_seed
    cr_s[0] = 0.0
    ncr = 1
    npoly = np.zeros(2, np.int64)
    sing = np.full(2, np.inf)
    cap_cr = len(cr_curve)
    cap_poly = poly_s.shape[1]
    for side in range(2):
        sgn = 1.0 if side == 0 else -1.0
        px = x0
        py = y0
        d = 1j * f * sgn
        s = 0.0
        last = 0.0
        poly_s[side, 0] = 0.0
        poly_x[side, 0] = px
        poly_y[side, 0] = py
        npl = 1
        for _ in range(max_steps):
            a0, a2 = coeffs_at(c0, c2, px, py)
            u, v = quartic_roots(a0, a2)
            nd, fam, ok = choose_direction(1j * u, 1j * v, d, tie)
            if not ok:
                break
            # followed root and the other one here, as unit vectors
            if fam == 0:
                fr = u
                gr = v
            else:
                fr = v
                gr = u
            nf = abs(fr)
            ng = abs(gr)
            fr = fr / nf if nf > 0 else 0j
            gr = gr / ng if ng > 0 else 0j
            qx = px + h * nd.real
            qy = py + h * nd.imag
            if qx < 0 or qy < 0 or qx >= W or qy >= H or not band[int(qy), int(qx)]:
                break
            if singular[int(qy), int(qx)]:
                sing[side] = s
                break
            # a streamline segment (one step, h long) that crosses [p, q] starts within h of that
            # segment, so its first sample lies in the box [p, q] ± r (r = h and a little more: float32
            # samples); only the sub-cells meeting the box are searched
            r = h + 1e-3
            x_lo = min(px, qx) - r
            x_hi = max(px, qx) + r
            y_lo = min(py, qy) - r
            y_hi = max(py, qy) + r
            i_lo = max(0, int(y_lo))
            i_hi = min(H - 1, int(y_hi))
            j_lo = max(0, int(x_lo))
            j_hi = min(W - 1, int(x_hi))
            ex = qx - px
            ey = qy - py
            for ii in range(i_lo, i_hi + 1):
                b_lo = min(SUB - 1, int((y_lo - ii) * SUB)) if y_lo > ii else 0
                b_hi = max(0, int((y_hi - ii) * SUB)) if y_hi < ii + 1 else SUB - 1
                for jj in range(j_lo, j_hi + 1):
                    cell0 = bidx[ii * W + jj]
                    if cell0 < 0:
                        continue
                    a_lo = min(SUB - 1, int((x_lo - jj) * SUB)) if x_lo > jj else 0
                    a_hi = max(0, int((x_hi - jj) * SUB)) if x_hi < jj + 1 else SUB - 1
                    for bb in range(b_lo, b_hi + 1):
                        row = cell0 * (SUB * SUB) + bb * SUB
                        for m in range(cell_start[row + a_lo], cell_start[row + a_hi + 1]):
                            t = cell_samples[m]
                            # the sample's curve: the last whose first sample is at or before it (the
                            # curves lie one after another), not a curve id a sample (0.14 GB on a 4x4 page)
                            c = 0
                            c_hi = n_curves
                            while c_hi - c > 1:
                                mid = (c + c_hi) >> 1
                                if c_start[mid] <= t:
                                    c = mid
                                else:
                                    c_hi = mid
                            li = t - c_start[c]
                            if li + 1 < c_len[c]:
                                ax = sx[t]
                                ay = sy[t]
                                bx = sx[t + 1] - ax
                                by = sy[t + 1] - ay
                                den = ex * by - ey * bx
                                if den != 0.0:
                                    wx = ax - px
                                    wy = ay - py
                                    a = (wx * by - wy * bx) / den
                                    b = (wx * ey - wy * ex) / den
                                    if 0.0 <= a < 1.0 and 0.0 <= b < 1.0 and not (
                                            c == k and abs(li + b - i_seed) < 1.5):
                                        nb = math.sqrt(bx * bx + by * by)
                                        tcx = bx / nb
                                        tcy = by / nb
                                        cf = abs(tcx * fr.real + tcy * fr.imag)
                                        cg = abs(tcx * gr.real + tcy * gr.imag)
                                        X = px + a * ex
                                        Y = py + a * ey
                                        yi = min(max(int(Y), 0), H - 1)
                                        xj = min(max(int(X), 0), W - 1)
                                        if cf >= cg and not singular[yi, xj] and ncr < cap_cr:
                                            cr_curve[ncr] = c
                                            cr_param[ncr] = li + b
                                            cr_s[ncr] = sgn * (s + a * h)
                                            ncr += 1
                                            if s + a * h > last:
                                                last = s + a * h
            s += h
            px = qx
            py = qy
            d = nd
            if npl < cap_poly:
                poly_s[side, npl] = s
                poly_x[side, npl] = px
                poly_y[side, npl] = py
                npl += 1
            if s - last > max_gap:
                break
        npoly[side] = npl
    return ncr, npoly[0], npoly[1], sing[0], sing[1]


@njit(cache=True)
def _point_at(poly_s, poly_x, poly_y, npoly, s):
    side = 0 if s >= 0 else 1
    a = abs(s)
    n = npoly[side]
    for q in range(1, n):
        if poly_s[side, q] >= a:
            s0 = poly_s[side, q - 1]
            t = (a - s0) / max(poly_s[side, q] - s0, 1e-12)
            return (poly_x[side, q - 1] + t * (poly_x[side, q] - poly_x[side, q - 1]),
                    poly_y[side, q - 1] + t * (poly_y[side, q] - poly_y[side, q - 1]))
    return poly_x[side, n - 1], poly_y[side, n - 1]


@njit(cache=True)
def _argsort_stable(a, n):
    """Stable argsort of ``a[:n]`` (bottom-up merge sort, O(n log n)).

    Not numba's ``np.argsort``: it compiles its whole quicksort (≈ 2 s of the first run) for this.  Not
    insertion either: a cross-section's crossings come as two runs (one side ascending, the other
    descending), which insertion sorts in O(n²).  At the scanned drawings' ~24 crossings a section
    both cost microseconds; merging bounds a wide stroke's sections (hundreds of lanes, up to the
    4096-crossing buffer).
    """
    idx = np.arange(n)
    tmp = np.empty(n, np.int64)
    width = 1
    while width < n:
        for lo in range(0, n, 2 * width):
            mid = min(lo + width, n)
            hi = min(lo + 2 * width, n)
            i = lo
            j = mid
            k = lo
            while i < mid and j < hi:
                # take from the right run only when strictly smaller: equal keys keep their order
                if a[idx[j]] < a[idx[i]]:
                    tmp[k] = idx[j]
                    j += 1
                else:
                    tmp[k] = idx[i]
                    i += 1
                k += 1
            while i < mid:
                tmp[k] = idx[i]
                i += 1
                k += 1
            while j < hi:
                tmp[k] = idx[j]
                j += 1
                k += 1
        idx, tmp = tmp, idx
        width *= 2
    return idx


@njit(cache=True)
def _is_covered(covered, s):
    """Whether sample ``s`` is covered (``covered`` holds one bit a sample, 8 to a byte)."""
    return (covered[s >> 3] >> (s & 7)) & 1 != 0


@njit(cache=True)
def _cover(covered, s):
    """Mark sample ``s`` covered."""
    covered[s >> 3] |= np.uint8(1 << (s & 7))


@njit(cache=True)
def _build_sections(c0, c2, band, singular, sx, sy, tx, ty, c_start, c_len, order, h, spacing,
                    cover, min_gap, max_gap, max_steps, ambiguity, tie, lane_pad):
    H, W = band.shape
    bidx, cell_start, cell_samples = _cell_index(sx, sy, band)
    n_samples = len(sx)
    # one bit a sample (a bool was 1 byte, 34 MB on a 4x4 page, at the kernel's peak)
    covered = np.zeros((n_samples + 7) // 8, np.uint8)
    half = max(1, spacing // 2)
    vcap = 1024
    v_xy = np.empty((vcap, 2), np.float64)
    v_width = np.empty(vcap, np.float64)
    v_root = np.empty(vcap, np.complex128)
    v_flag = np.empty(vcap, np.uint8)
    v_seed = np.empty(vcap, np.int64)
    nv = 0
    # room for a crossing every 4 samples at once (a 4x4 page has one every 6): doubling from 8192
    # held the old and the new buffers together at its last growth (+45 MB on the page), and the
    # untouched tail takes no memory
    mcap = max(8192, n_samples // 4)
    # int32 (vertex and curve ids): 8 bytes a crossing less, 43–64 MB on a 4x4 page at the kernel's
    # peak; raw_graph widens them once the samples are gone
    m_vertex = np.empty(mcap, np.int32)
    m_curve = np.empty(mcap, np.int32)
    m_param = np.empty(mcap, np.float64)
    nm = 0
    cr_cap = 4096
    cr_curve = np.empty(cr_cap, np.int64)
    cr_param = np.empty(cr_cap, np.float64)
    cr_s = np.empty(cr_cap, np.float64)
    poly_s = np.empty((2, max_steps + 2), np.float64)
    poly_x = np.empty((2, max_steps + 2), np.float64)
    poly_y = np.empty((2, max_steps + 2), np.float64)
    n_fail = 0
    for k in order:
        st = c_start[k]
        L = c_len[k]
        i = 0
        while i < L:
            while i < L and _is_covered(covered, st + i):
                i += 1
            if i == L:
                break
            e = i
            while e < L and not _is_covered(covered, st + e):
                e += 1
            run = e - i
            if i > 0 and e < L and run < min_gap:
                for q in range(i, e):
                    _cover(covered, st + q)
                i = e
                continue
            if e < L:
                j = i + min(half, (run - 1) // 2)
            else:
                j = min(i + half, L - 1)
            g = st + j
            made = False
            # float64 like every other call of coeffs_at (it widens at once anyway): one compile, not two
            x0 = np.float64(sx[g])
            y0 = np.float64(sy[g])
            if not singular[int(y0), int(x0)]:
                a0, a2 = coeffs_at(c0, c2, x0, y0)
                u, v = quartic_roots(a0, a2)
                nu = abs(u)
                nvv = abs(v)
                if nu > 1e-12 and nvv > 1e-12:
                    u = u / nu
                    v = v / nvv
                    t0 = tx[g] + 1j * ty[g]
                    cu = u.real * t0.real + u.imag * t0.imag
                    cv = v.real * t0.real + v.imag * t0.imag
                    if abs(abs(cu) - abs(cv)) >= ambiguity:
                        if abs(cu) > abs(cv):
                            f = u if cu > 0 else -u
                        else:
                            f = v if cv > 0 else -v
                        ncr, np0, np1, sg0, sg1 = _section(
                            c0, c2, band, singular, sx, sy, c_start, c_len, bidx, cell_start, cell_samples,
                            k, g, f, h, max_gap, max_steps, tie, cr_curve, cr_param, cr_s, poly_s, poly_x, poly_y)
                        srt = _argsort_stable(cr_s, ncr)
                        pos0 = 0
                        for q in range(ncr):
                            if srt[q] == 0:
                                pos0 = q
                        lo = pos0
                        while lo > 0 and cr_s[srt[lo]] - cr_s[srt[lo - 1]] <= max_gap:
                            lo -= 1
                        hi = pos0
                        while hi < ncr - 1 and cr_s[srt[hi + 1]] - cr_s[srt[hi]] <= max_gap:
                            hi += 1
                        s_lo = cr_s[srt[lo]]
                        s_hi = cr_s[srt[hi]]
                        nrun = hi - lo + 1
                        diam = s_hi - s_lo
                        pad = lane_pad * (1.0 if nrun == 1 else min(1.0, diam / (nrun - 1)))
                        npoly = np.empty(2, np.int64)
                        npoly[0] = np0
                        npoly[1] = np1
                        cx, cy = _point_at(poly_s, poly_x, poly_y, npoly, 0.5 * (s_lo + s_hi))
                        flag = 0
                        if sg0 - s_hi <= max_gap or sg1 + s_lo <= max_gap:
                            flag = 1
                        if nv >= vcap:
                            vcap *= 2
                            nxy = np.empty((vcap, 2), np.float64)
                            for q in range(nv):
                                nxy[q, 0] = v_xy[q, 0]
                                nxy[q, 1] = v_xy[q, 1]
                            v_xy = nxy
                            v_width = _grow_f(v_width, vcap)
                            v_root = _grow_f(v_root, vcap)
                            v_flag = _grow_f(v_flag, vcap)
                            v_seed = _grow_f(v_seed, vcap)
                        v_xy[nv, 0] = cx
                        v_xy[nv, 1] = cy
                        v_width[nv] = diam + pad
                        v_root[nv] = f
                        v_flag[nv] = flag
                        v_seed[nv] = g
                        for q in range(lo, hi + 1):
                            r = srt[q]
                            c = cr_curve[r]
                            p = cr_param[r]
                            if nm >= mcap:
                                mcap *= 2
                                m_vertex = _grow_f(m_vertex, mcap)
                                m_curve = _grow_f(m_curve, mcap)
                                m_param = _grow_f(m_param, mcap)
                            m_vertex[nm] = nv
                            m_curve[nm] = c
                            m_param[nm] = p
                            nm += 1
                            a = max(0, int(math.floor(p - cover)))
                            b = min(c_len[c] - 1, int(math.ceil(p + cover)))
                            for z in range(a, b + 1):
                                _cover(covered, c_start[c] + z)
                        nv += 1
                        made = True
            if not made:
                n_fail += 1
            # always make progress along this curve, even where no cross-section could be taken
            for q in range(i, min(L, j + half + 1)):
                _cover(covered, st + q)
    # the crossings (millions on a page) as views of their buffers, not copies: the untouched tails
    # of the buffers take no memory
    return (v_xy[:nv].copy(), v_width[:nv].copy(), v_root[:nv].copy(), v_flag[:nv].copy(), v_seed[:nv].copy(),
            m_vertex[:nm], m_curve[:nm], m_param[:nm], n_fail)
