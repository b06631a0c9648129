"""Roots of the PolyVector field and its singularities (steps 4 and 5 of the field stage).

The roots ``±u, ±v`` of ``z⁴ + c2 z² + c0`` in closed form (:func:`polyvector_roots`), the root
pairing between neighbouring pixels (:func:`root_matching`) and the 2×2 parity test that finds the
singular cells and pixels (:func:`singular_cells`, :func:`singular_pixels`), which drives the field
stage's singularity loop (:func:`stages.field.stage.compute_field`); and the tie-break that orders
roots of equal modulus by the smoothed image tangent (:func:`_order_ties`: why, in its docstring and
the stage's).  Public helpers: the graph, the flow and the field pictures read roots the same way.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi


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
    odd = _odd_cells(roots[ci, cj], roots[ci, cj + 1], roots[ci + 1, cj + 1], roots[ci + 1, cj])
    out[ci[odd], cj[odd]] = True
    return out


def _odd_cells(r00: np.ndarray, r01: np.ndarray, r11: np.ndarray, r10: np.ndarray) -> np.ndarray:
    """The parity test of :func:`singular_cells` on cells given by their corners' roots (in walk order)."""
    parity = (root_matching(r00, r01).astype(np.int8) + root_matching(r01, r11)
              + root_matching(r11, r10) + root_matching(r10, r00)) % 2
    return parity == 1


def band_cells(mask: np.ndarray, index: np.ndarray) -> np.ndarray:
    """The cells that :func:`singular_cells` tests, as band positions of their corners.

    Returns
    -------
    numpy.ndarray
        int (cells, 4): the band positions (``index``) of pixels ``[i, j], [i, j+1], [i+1, j+1],
        [i+1, j]`` of each cell with all four in ``mask``, in raster order of the cells.
    """
    if mask.shape[0] < 2 or mask.shape[1] < 2:
        return np.zeros((0, 4), np.int64)
    full = mask[:-1, :-1] & mask[:-1, 1:] & mask[1:, 1:] & mask[1:, :-1]
    ci, cj = np.nonzero(full)
    return np.stack([index[ci, cj], index[ci, cj + 1], index[ci + 1, cj + 1], index[ci + 1, cj]], axis=1)


def band_singular_pixels(roots_b: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """:func:`singular_pixels` of :func:`singular_cells` on the band alone.

    Parameters
    ----------
    roots_b : numpy.ndarray
        complex (n, 2), the roots of the band pixels.
    cells : numpy.ndarray
        int (cells, 4), :func:`band_cells`.

    Returns
    -------
    numpy.ndarray
        bool (n,): band pixels touching a singular cell (every corner of a tested cell is in the band).
    """
    out = np.zeros(len(roots_b), dtype=bool)
    odd = _odd_cells(*(roots_b[cells[:, c]] for c in range(4)))
    out[cells[odd].reshape(-1)] = True
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


# Rows of the image per strip of the tie-break's smoothing: its temporaries stay a strip's, not a page's.
TIE_STRIP_PIXELS = 1 << 18


def _order_ties(roots_b: np.ndarray, mask: np.ndarray, tau: np.ndarray, gmag: np.ndarray,
                tolerance: float, sigma: float) -> int:
    """Order the band's roots of near-equal modulus by the smoothed image tangent (in place).

    For an axis-aligned stroke the frame {x, y} fits the alignment and orthogonality terms exactly,
    and it is the *same* polynomial (c0 = −1, c2 = 0) for a horizontal and a vertical stroke: the
    moduli tie and "larger modulus" alone would put the normal first on one of them.  Where
    ``|v| ≥ (1 − tolerance)·|u|`` the root closer to the Gaussian-smoothed (σ = ``sigma``) structure
    tensor orientation of the image goes first.  ``roots_b`` (n, 2) are the roots of the band pixels
    (``mask``) in raster order.  The smoothing runs on strips of rows holding ties, each with the
    filter's reach above and below (the same values as on the whole image).  Returns the number of
    swapped pixels.
    """
    m = np.abs(roots_b)
    tie = (m[:, 1] >= (1.0 - tolerance) * m[:, 0]) & (m[:, 0] > 0)
    h, w = mask.shape
    rows, cols = np.divmod(np.flatnonzero(mask)[tie], w)
    orient = np.zeros(len(rows), np.complex128)
    reach = int(4.0 * sigma + 0.5)  # gaussian_filter's truncate = 4
    height = max(1, TIE_STRIP_PIXELS // max(w, 1))
    strip = rows // height
    for k in np.unique(strip):
        top, bottom = k * height, min(h, (k + 1) * height)
        lo, hi = max(0, top - reach), min(h, bottom + reach)
        t2g = (tau[lo:hi] * gmag[lo:hi]) ** 2
        smooth = ndi.gaussian_filter(t2g.real, sigma) + 1j * ndi.gaussian_filter(t2g.imag, sigma)
        here = strip == k
        orient[here] = smooth[rows[here] - lo, cols[here]]
    kept = np.abs(orient) > 0
    sel = np.flatnonzero(tie)[kept]
    r = roots_b[sel]
    t = np.sqrt(orient[kept])  # a direction whose doubled angle is the orientation's
    swap = _abs_cos(r[:, 1], t) > _abs_cos(r[:, 0], t)
    roots_b[sel[swap]] = r[swap][:, ::-1]
    return int(swap.sum())
