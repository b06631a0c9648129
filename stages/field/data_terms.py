"""The data terms of the field's energy: image tangents and the weights derived from them (steps 1, 2, 6).

The field stage (:mod:`stages.field.stage`, whose docstring describes the energy and its choices)
fits the PolyVector field to the image tangents τ of a 3×3 Sobel (:func:`image_tangents`), each term
weighted by how well a pixel's tangent agrees with its neighbours' (:func:`coherence_weights`); the
smoothness term is weighted by the *smart weights* of those (:func:`smart_weights`), which the
extension stage reuses.  Apart from the solve (:mod:`stages.field.solver`) because they are plain
image filters, computed once per drawing (per mosaic piece) before it.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi


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


def band_ring(w: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 4-neighbours of the band pixels that :func:`band_smart_weights` reads.

    The singularity loop changes ``w`` on band pixels only: the neighbours off the band keep their
    weights, so they are read from the image once here and the loop works on band vectors.

    Parameters
    ----------
    w : numpy.ndarray
        float (H, W), the coherence weights before the loop.
    mask : numpy.ndarray
        bool (H, W), the narrow band.

    Returns
    -------
    inner : numpy.ndarray
        bool (n,), band pixels off the image border (the others have s = 1).
    neighbour : numpy.ndarray
        int (n_inner, 4), band position of the up, down, left and right neighbour, −1 off the band.
    w_off : numpy.ndarray
        float (n_inner, 4), their weights in ``w`` (read where ``neighbour`` is −1).
    """
    h, wd = mask.shape
    pos = np.flatnonzero(mask)
    i, j = np.divmod(pos, wd)
    inner = (i > 0) & (i < h - 1) & (j > 0) & (j < wd - 1)
    q = pos[inner][:, None] + np.array([-wd, wd, -1, 1])
    k = np.minimum(np.searchsorted(pos, q), max(len(pos) - 1, 0))
    neighbour = np.where(pos[k] == q, k, -1) if len(pos) else k
    return inner, neighbour, w.reshape(-1)[q]


def band_smart_weights(w_b: np.ndarray, ring: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """:func:`smart_weights` on the band pixels alone, for band weights ``w_b`` (the same bits).

    ``ring`` is :func:`band_ring` of the image's weights, whose values off the band still hold.
    """
    inner, neighbour, w_off = ring
    w_n = np.where(neighbour >= 0, w_b[neighbour], w_off)
    one_minus = 1.0 - w_n
    s = np.ones(len(w_b))
    s[inner] = 0.25 * (one_minus[:, 0] + one_minus[:, 1] + one_minus[:, 2] + one_minus[:, 3])
    return s
