"""Raster metrics of Yan et al. 2020 ("A Benchmark for Rough Sketch Cleanup").

Implements shared/reference/metrics.md §2: both images are binarised (ink = 8-bit grey < 191.25),
``a`` = distance from every output ink pixel to the nearest ground-truth ink pixel, ``b`` the reverse,
``L`` = long edge in pixels, and

- Chamfer   = (mean(a) + mean(b)) / 2 / L
- Hausdorff = max(max(a), max(b)) / L
- F1 at d   = harmonic mean of P = |a <= τ| / |a| and R = |b <= τ| / |b| with τ = d · L / 1000.

Vectors are rasterised the way the benchmark normalises them (black, round caps and joins, stroke width
0.001 × long edge, anti-aliased, on white) by cairo (:func:`rasterise_polylines_cairo`, through
cairocffi and the system's libcairo), the renderer of Inkscape, rsvg and cairosvg: the same coverage
rule, so the same 8-bit grey levels at the ink threshold.  :func:`rasterise_polylines` (supersampled
capsules) is kept for ``renderer: supersample``.

Choices made on purpose
-----------------------
- **1-px minimum stroke width** (metrics.md §2.5). A line crossing a pixel column spreads a coverage
  of at least ``width`` over at most two pixels of it, so one of them reaches ``width / 2``; the ink
  threshold needs 25 %. Below 0.5 px (long edge < 500, e.g. the 288-px fixtures) oblique lines break
  into dots; at 512 px (width 0.512, realvec_dev) they stay connected only by the margin of 8-bit
  rounding. With at least 1 px the mask is a connected 1–2 px wide line at any angle, for ground
  truth and output alike (tested). ``min_width_px`` is a parameter; 0 reproduces the benchmark's
  width literally.
- **Coverage by supersampling**: a pixel's coverage is the fraction of ``s × s`` sub-pixel sample points
  (at the centres of an ``s × s`` grid in the pixel) that lie inside the union of capsules (a segment
  swept by a disc of radius width / 2). The union is exact (no double darkening where strokes overlap,
  as with an opaque stroke in Inkscape). The grey value is quantised to 8 bits (as a PNG would be)
  before thresholding.
- Undefined metrics (a blank image on either side) are returned as NaN and flagged ``blank``; the caller
  counts them as failures (§2.4).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import ndimage

__all__ = [
    "INK_THRESHOLD",
    "benchmark_stroke_width",
    "binarise",
    "rasterise_polylines",
    "rasterise_polylines_cairo",
    "raster_metrics",
]

#: Grey level (0–255) below which a pixel is ink: L/255 < 1 − 0.25 (metrics.md §2.2).
INK_THRESHOLD = 191.25


def binarise(grey_u8: np.ndarray, threshold: float = INK_THRESHOLD) -> np.ndarray:
    """Ink mask of an 8-bit grey image, as the benchmark computes it.

    Parameters
    ----------
    grey_u8 : numpy.ndarray
        (H, W) grey values in 0–255 (PIL mode ``L``: 299 R + 587 G + 114 B over 1000, alpha dropped).
    threshold : float
        Pixels strictly darker than this are ink.

    Returns
    -------
    numpy.ndarray
        bool (H, W).
    """
    grey = np.asarray(grey_u8)
    if grey.ndim != 2:
        raise ValueError(f"expected a 2-D grey image, got shape {grey.shape}")
    return grey.astype(np.float64) < threshold


def benchmark_stroke_width(shape: tuple[int, int], permille: float, min_width_px: float) -> float:
    """Normalised stroke width: ``permille`` / 1000 of the long edge, at least ``min_width_px``.

    Parameters
    ----------
    shape : (H, W)
    permille : float
        Width in thousandths of ``max(H, W)`` (the benchmark uses 1).
    min_width_px : float
        Lower bound in pixels (see the module notes; 0 disables it).
    """
    return max(permille * max(shape) / 1000.0, min_width_px)


def _split_segments(polylines: Sequence[np.ndarray], max_len: float) -> tuple[np.ndarray, np.ndarray]:
    """All segments of all polylines, cut into pieces no longer than ``max_len``.

    Cutting does not change the union of capsules, and bounded pieces let every piece use one fixed-size
    window of sub-samples. A single-point polyline becomes a zero-length piece (a dot).
    """
    starts, ends = [], []
    for pl in polylines:
        p = np.asarray(pl, dtype=np.float64).reshape(-1, 2)
        if len(p) == 0:
            continue
        if len(p) == 1:
            p = np.vstack([p, p])
        a, b = p[:-1], p[1:]
        n = np.maximum(1, np.ceil(np.hypot(*(b - a).T) / max_len)).astype(np.int64)
        seg = np.repeat(np.arange(len(a)), n)
        k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        t0 = (k / n[seg])[:, None]
        t1 = ((k + 1) / n[seg])[:, None]
        d = b[seg] - a[seg]
        starts.append(a[seg] + t0 * d)
        ends.append(a[seg] + t1 * d)
    if not starts:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate(starts), np.concatenate(ends)


def rasterise_polylines(
    polylines: Sequence[np.ndarray],
    shape: tuple[int, int],
    width: float,
    supersample: int = 4,
    chunk: int = 4096,
) -> np.ndarray:
    """Anti-aliased rendering of polylines drawn black on white with round caps and joins.

    Parameters
    ----------
    polylines : sequence of numpy.ndarray
        Each (n, 2) in (x, y) pixel units, origin at the top-left corner of the image (pixel ``[i, j]``
        spans ``x ∈ [j, j + 1]``, ``y ∈ [i, i + 1]``).
    shape : (H, W)
        Output size.
    width : float
        Stroke width in pixels.
    supersample : int
        Sub-samples per pixel along each axis.
    chunk : int
        Segment pieces processed at once (bounds memory).

    Returns
    -------
    numpy.ndarray
        float64 (H, W) grey in [0, 1], 1 = white paper.
    """
    h, w = int(shape[0]), int(shape[1])
    s = int(supersample)
    if s < 1 or width <= 0:
        raise ValueError("supersample must be >= 1 and width > 0")
    r = width / 2.0
    a, b = _split_segments(polylines, max_len=1.0)
    hit = np.zeros((h * s, w * s), dtype=bool)
    if len(a):
        # Sub-sample (u, v) sits at x = (u + 0.5) / s. A piece (length <= 1) plus radius r fits in a
        # window of `win` sub-samples per axis starting at the sub-sample left of its bounding box.
        win = int(math.ceil((1.0 + 2.0 * r) * s)) + 2
        off = np.arange(win)
        for c0 in range(0, len(a), chunk):
            pa, pb = a[c0:c0 + chunk], b[c0:c0 + chunk]
            lo = np.floor((np.minimum(pa, pb) - r) * s - 0.5).astype(np.int64)  # (n, 2) in (u, v)
            u = lo[:, 0:1] + off  # (n, win) columns
            v = lo[:, 1:2] + off  # (n, win) rows
            x = (u + 0.5) / s
            y = (v + 0.5) / s
            d = pb - pa
            ll = np.einsum("ij,ij->i", d, d)
            # Distance of each window sample to its piece, vectorised over (piece, row, col).
            px = x[:, None, :] - pa[:, 0, None, None]
            py = y[:, :, None] - pa[:, 1, None, None]
            with np.errstate(invalid="ignore", divide="ignore"):
                t = (px * d[:, 0, None, None] + py * d[:, 1, None, None]) / ll[:, None, None]
            t = np.where(ll[:, None, None] > 0, np.clip(t, 0.0, 1.0), 0.0)
            inside = (px - t * d[:, 0, None, None]) ** 2 + (py - t * d[:, 1, None, None]) ** 2 <= r * r
            vv = np.broadcast_to(v[:, :, None], inside.shape)
            uu = np.broadcast_to(u[:, None, :], inside.shape)
            keep = inside & (vv >= 0) & (vv < h * s) & (uu >= 0) & (uu < w * s)
            hit[vv[keep], uu[keep]] = True
    coverage = hit.reshape(h, s, w, s).mean(axis=(1, 3))
    return 1.0 - coverage


def rasterise_polylines_cairo(polylines: Sequence[np.ndarray], shape: tuple[int, int], width: float) -> np.ndarray:
    """Polylines drawn by cairo, black on white, with round caps and joins (a normalised SVG's rendering).

    Cairo is what Inkscape, rsvg and cairosvg rasterise SVG paths with, so this is the benchmark's
    rendering itself rather than an approximation of it: each polyline is one path (``M`` then
    ``L``s) stroked on its own, as each ``<path>`` of an SVG is, so a stroke overlapping itself
    darkens no pixel twice while two strokes' anti-aliased edges composite one over the other.

    Parameters
    ----------
    polylines : sequence of numpy.ndarray
        Each (n, 2) in (x, y) pixel units, origin at the top-left corner of the image.  A single point
        is drawn as a round dot (a zero-length segment with round caps).
    shape : (H, W)
        Output size.
    width : float
        Stroke width in pixels.

    Returns
    -------
    numpy.ndarray
        float64 (H, W) grey in [0, 1], 1 = white paper, on the 8-bit levels cairo wrote (times 1/255).
    """
    try:
        import cairocffi as cairo
    except OSError as exc:  # cairocffi is installed, the C library it loads is not
        raise RuntimeError(f"the bench's rasteriser needs the system library libcairo2 (Debian: apt-get install "
                           f"libcairo2): {exc}") from None

    h, w = int(shape[0]), int(shape[1])
    if width <= 0:
        raise ValueError("width must be > 0")
    surface = cairo.ImageSurface(cairo.FORMAT_RGB24, w, h)
    ctx = cairo.Context(surface)
    ctx.set_source_rgb(1, 1, 1)
    ctx.paint()
    ctx.set_source_rgb(0, 0, 0)
    ctx.set_line_width(float(width))
    ctx.set_line_cap(cairo.LINE_CAP_ROUND)
    ctx.set_line_join(cairo.LINE_JOIN_ROUND)
    for pl in polylines:
        p = np.asarray(pl, dtype=np.float64).reshape(-1, 2)
        if len(p) == 0 or not np.all(np.isfinite(p)):
            continue
        if len(p) == 1:
            p = np.vstack([p, p])
        ctx.move_to(*p[0])
        for x, y in p[1:].tolist():
            ctx.line_to(x, y)
        ctx.stroke()
    surface.flush()
    stride = surface.get_stride()
    # RGB24 is one 32-bit word per pixel (xRGB, native byte order); the blue byte is the grey level.
    data = np.frombuffer(surface.get_data(), np.uint8).reshape(h, stride)[:, :4 * w].reshape(h, w, 4)
    blue = 0 if np.little_endian else 3
    return data[..., blue].astype(np.float64) / 255.0


def raster_metrics(
    test_ink: np.ndarray,
    gt_ink: np.ndarray,
    f1_permille: Sequence[float] = (2, 4, 6, 8, 10),
    f1_pixels: Sequence[float] = (),
    pixel_scale: float = 1.0,
) -> dict:
    """Chamfer, Hausdorff and F1 of an output ink mask against a ground-truth ink mask (§2.3–2.4).

    Parameters
    ----------
    test_ink, gt_ink : numpy.ndarray
        bool (H, W) masks of the same shape (T = algorithm output, G = ground truth).
    f1_permille : sequence of float
        Tolerances d in thousandths of the long edge (τ = d · L / 1000 px); keys ``f1_<d>``.
    f1_pixels : sequence of float
        Extra tolerances in pixels (metrics.md §2.5 recommends them for small images); keys
        ``f1_<d>px``.
    pixel_scale : float
        The masks' pixels per pixel of ``f1_pixels`` (masks rendered at a multiple of the image's
        size keep their pixel tolerances in pixels of the image).

    Returns
    -------
    dict
        ``chamfer`` and ``hausdorff`` (fractions of the long edge), ``f1_*``, ``precision_*`` and
        ``recall_*`` per tolerance, ``ink_test``/``ink_gt`` pixel counts and ``blank`` (True, with every
        metric NaN, when either mask has no ink).
    """
    test_ink = np.asarray(test_ink, dtype=bool)
    gt_ink = np.asarray(gt_ink, dtype=bool)
    if test_ink.shape != gt_ink.shape or test_ink.ndim != 2:
        raise ValueError(f"masks must be 2-D of one shape, got {test_ink.shape} and {gt_ink.shape}")
    long_edge = float(max(test_ink.shape))
    tols = [(_key(d), d * long_edge / 1000.0) for d in f1_permille]
    tols += [(_key(d) + "px", float(d) * pixel_scale) for d in f1_pixels]
    out: dict = {"ink_test": int(test_ink.sum()), "ink_gt": int(gt_ink.sum())}
    if out["ink_test"] == 0 or out["ink_gt"] == 0:
        out.update(blank=True, chamfer=math.nan, hausdorff=math.nan)
        for name, _ in tols:
            out.update({f"f1_{name}": math.nan, f"precision_{name}": math.nan, f"recall_{name}": math.nan})
        return out
    a = ndimage.distance_transform_edt(~gt_ink)[test_ink]  # i_to_g
    b = ndimage.distance_transform_edt(~test_ink)[gt_ink]  # g_to_i
    out["blank"] = False
    out["chamfer"] = float((a.mean() + b.mean()) / 2.0 / long_edge)
    out["hausdorff"] = float(max(a.max(), b.max()) / long_edge)
    for name, tau in tols:
        p = float(np.count_nonzero(a <= tau)) / a.size
        r = float(np.count_nonzero(b <= tau)) / b.size
        out[f"precision_{name}"] = p
        out[f"recall_{name}"] = r
        out[f"f1_{name}"] = 0.0 if p + r == 0 else 2.0 * p * r / (p + r)
    return out


def _key(d: float) -> str:
    """``2`` → ``"2"``, ``2.5`` → ``"2.5"`` (keys stay readable in tables)."""
    d = float(d)
    return str(int(d)) if d.is_integer() else f"{d:g}"
