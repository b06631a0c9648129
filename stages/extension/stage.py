"""The PolyVector field extended beyond the narrow band, for the flow (authors' ``scale_ff``).

The flow (paper §4.3) moves curve vertices off the band, where the field stage leaves no field.  The
band is dilated by a disk of radius ``radius``; on the ring only the smart-weighted Laplacian of the
field stage (:func:`stages.field.stage.smart_weights`) is minimised with the band values held fixed;
ring values are then multiplied by ``scale`` × (L1 distance to the band), which makes |p(τ)| large
off the ink: a soft wall pushing flowed curves back into strokes.  0 beyond the ring.

Choices made on purpose
-----------------------
* **A stage of its own**, not the field stage's last step: only the flow reads it, so an in-process
  run computes it in the keypoints child once the keypoints are done, off the field → graph path
  (the elephant's default run: the field stage 0.57 → 0.40 s; stages/DECISIONS.md, engine).
* **From the stored field**: the band values are the field artifact's complex64 coefficients (the
  field stage solved in float64) and the smart weights its float32 ``smart_weights``; the ring moves
  in its last bits against a solve from float64 inputs, below the artifact's complex64 rounding.
* **Memory in the ring's size, not the page's**: a 4×4 page's extension ran in the keypoints child, on
  top of the network's kept heap, and was the page's peak.  Only the ring's rows of the Laplacian are
  kept, the distance and the solution stay ring vectors, and the two complex64 page arrays are made
  once, at the end (no complex128 page, no float64 distance or weights page): the stage alone on the
  page +757 → +482 MB, the child 1.50 → 1.23 GB, bit-identical artifact (stages/DECISIONS.md, extension).
"""

from __future__ import annotations

import time

import numpy as np
import scipy.ndimage as ndi

from stages.artifact import Artifact
from stages.config import from_section
from stages.errors import InputError
from stages.extension import ExtensionConfig
from stages.field.solver import _as_real, _blockwise_cg, _smart_laplacian, _solve_blocks


def extend_field(c0: np.ndarray, c2: np.ndarray, mask: np.ndarray, s: np.ndarray,
                 cfg: ExtensionConfig, dtype: np.dtype | type = np.complex128) -> tuple[np.ndarray, np.ndarray, dict]:
    """Extend the band field into a dilated ring.

    The ring is ``dilate(mask, disk(radius)) − mask``.  On it the smart-weighted Laplacian
    ``L = Σ Dᵀ diag(s) D`` (over band + ring) is minimised with the band values fixed; ring values are
    then multiplied by ``scale · d₁`` with d₁ the L1 (taxicab) distance to the band.  Only the ring's
    rows of ``L`` are kept, and the page arrays are made once, at the end, in ``dtype``.

    Parameters
    ----------
    c0, c2 : numpy.ndarray
        complex (H, W) band field (0 off the band).
    mask : numpy.ndarray
        bool (H, W).
    s : numpy.ndarray
        float (H, W) smart weights (:func:`stages.field.stage.smart_weights`).
    cfg : ExtensionConfig
    dtype : numpy.dtype, optional
        Of the returned arrays.  The stage asks for its artifact's complex64: the ring's float64 solution
        is rounded once, as ``.astype`` of complex128 pages rounded it, and no complex128 page is held
        (two were 192 MB under a 4×4 page's peak).

    Returns
    -------
    c0_ext, c2_ext : numpy.ndarray
        ``dtype`` (H, W): band values on the band, scaled extension on the ring, 0 beyond.
    stats : dict
        ``extension_unknowns``, ``extension_cg_iterations``, ``extension_cg_converged``.
    """
    r = cfg.radius
    if not mask.any() or r <= 0:
        return (_extended_page(c0, mask, None, None, dtype), _extended_page(c2, mask, None, None, dtype),
                {"extension_unknowns": 0, "extension_cg_iterations": 0, "extension_cg_converged": True})
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    disk = xx * xx + yy * yy <= r * r
    dil = ndi.binary_dilation(mask, structure=disk)
    ring = dil & ~mask
    in_ring = ring[dil]
    # only the ring's rows of L are kept (the band's are never read)
    lap_ring = _smart_laplacian(dil, s)[in_ring]
    lrr = lap_ring[:, in_ring]
    rhs = -(lap_ring[:, ~in_ring] @ _as_real(np.stack([c0[mask], c2[mask]], axis=1).astype(np.complex128)))
    del lap_ring
    # Both coefficients share the real operator: one solve over their four real columns.
    k = int(in_ring.sum())
    x, iters, converged = _blockwise_cg(lrr, None, rhs, None, _solve_blocks(dil, ring), cfg.cg_rtol,
                                        cfg.cg_max_iterations)
    del lrr, rhs
    scale = cfg.scale * ndi.distance_transform_cdt(~mask, metric="taxicab")[ring].astype(np.float64)
    xc = x.view(np.complex128)
    return (_extended_page(c0, mask, ring, xc[:, 0] * scale, dtype),
            _extended_page(c2, mask, ring, xc[:, 1] * scale, dtype),
            {"extension_unknowns": 2 * k, "extension_cg_iterations": max(iters),
             "extension_cg_converged": bool(converged)})


def _extended_page(c: np.ndarray, mask: np.ndarray, ring: np.ndarray | None, ring_values: np.ndarray | None,
                   dtype) -> np.ndarray:
    """A ``dtype`` page: ``c`` on the band, ``ring_values`` (complex128, raster order) on the ring, 0 beyond."""
    page = np.zeros(mask.shape, dtype)
    page[mask] = c[mask]
    if ring is not None:
        page[ring] = ring_values
    return page


def run(cfg: dict, **inputs: Artifact) -> Artifact:
    """Stage entry: the extended field of the ``field`` artifact.

    Parameters
    ----------
    cfg : dict
        The ``extension`` config section (keys of :class:`ExtensionConfig`).
    prep : Artifact
        With ``mask`` bool (H, W), the band.
    field : Artifact
        With ``c0``, ``c2`` complex (H, W) and ``smart_weights`` float (H, W).

    Returns
    -------
    Artifact
        Arrays ``c0_ext, c2_ext`` complex64 (H, W); data = solver statistics.
    """
    conf = from_section(ExtensionConfig, cfg, "extension")
    for name in ("prep", "field"):
        if name not in inputs:
            raise InputError(f"extension stage needs the '{name}' artifact")
    mask = np.asarray(inputs["prep"].arrays.get("mask"))
    field = inputs["field"]
    c0, c2, s = (np.asarray(field.arrays.get(n)) for n in ("c0", "c2", "smart_weights"))
    if mask.ndim != 2 or any(a.shape != mask.shape for a in (c0, c2, s)):
        raise InputError(f"extension: mask, c0, c2 and smart_weights must be equal-shaped 2-D arrays, got "
                         f"{mask.shape}, {c0.shape}, {c2.shape}, {s.shape}")
    t = time.perf_counter()
    c0_ext, c2_ext, stats = extend_field(c0, c2, mask.astype(bool), s, conf, dtype=np.complex64)
    stats["extension_seconds"] = time.perf_counter() - t
    notes = []
    if not stats["extension_cg_converged"]:
        notes.append(f"the extension's solve stopped at extension.cg_max_iterations ({conf.cg_max_iterations}) "
                     f"before extension.cg_rtol: the flow's field off the band may be rougher")
    return Artifact(arrays={"c0_ext": c0_ext, "c2_ext": c2_ext},
                    data=stats, notes=notes)
