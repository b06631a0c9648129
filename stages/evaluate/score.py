"""Scoring of one benchmark case: raster metrics, topology, keypoints, timings; and summaries.

Pure functions of arrays and dicts. The benchmark driver (``pipeline/bench.py``) reads cases, runs
the pipeline, loads artifacts and writes the report; everything that turns those into numbers is
here, so it is testable without files.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from stages.evaluate import RasterParams, TopologyParams
from stages.evaluate.curve_topology import compare_topology, curve_topology
from stages.evaluate.raster import (benchmark_stroke_width, binarise, rasterise_polylines, rasterise_polylines_cairo,
                                    raster_metrics)

__all__ = [
    "RasterParams",
    "estimate_stroke_width",
    "gt_scale",
    "render_ink",
    "score_raster",
    "score_topology",
    "stage_timings",
    "summarise",
]


def render_ink(curves: Sequence[np.ndarray], shape: tuple[int, int], params: RasterParams,
               scale: float = 1.0) -> np.ndarray:
    """Ink mask of curves normalised as the benchmark does (uniform thin stroke, 8-bit, threshold).

    Parameters
    ----------
    curves : sequence of numpy.ndarray
        Polylines (n, 2) in (x, y) pixel units of the image.
    shape : (H, W)
        The image's size.
    params : RasterParams
    scale : float
        Render at this multiple of the image's size (see :func:`gt_scale`), as the benchmark renders
        its 1000-px variant; the stroke width follows the rendered long edge.

    Returns
    -------
    numpy.ndarray
        bool (round(H·scale), round(W·scale)).
    """
    out = (int(round(shape[0] * scale)), int(round(shape[1] * scale)))
    curves = [np.asarray(c, np.float64).reshape(-1, 2) * scale for c in curves]
    width = benchmark_stroke_width(out, params.stroke_width_permille, params.min_stroke_width_px)
    if params.renderer == "cairo":
        grey = rasterise_polylines_cairo(curves, out, width)
    else:
        grey = rasterise_polylines(curves, out, width, params.supersample)
    return binarise(np.round(grey * 255.0), params.ink_threshold)


def gt_scale(shape: tuple[int, int], params: RasterParams) -> float:
    """Scale at which output and ground truth are rendered for the comparison: ``long_edge`` / the
    image's long edge (1 when ``long_edge`` is null)."""
    return 1.0 if params.long_edge is None else params.long_edge / float(max(shape))


def score_raster(test_ink: np.ndarray, ref_ink: np.ndarray, params: RasterParams, prefix: str = "",
                 scale: float = 1.0) -> dict:
    """Chamfer, Hausdorff and F1 (metrics.md §2) with keys prefixed by ``prefix``.

    Only the headline numbers are kept (``chamfer``, ``hausdorff``, ``f1_<d>``), not the per-tolerance
    precision and recall, to keep per-case rows readable.  ``scale`` is the one the masks were
    rendered at: the pixel tolerances (``f1_<d>px``) stay in pixels of the image.
    """
    m = raster_metrics(test_ink, ref_ink, params.f1_permille, params.f1_pixels, pixel_scale=scale)
    keep = {k: v for k, v in m.items() if k in ("chamfer", "hausdorff", "blank") or k.startswith("f1_")}
    return {prefix + k: v for k, v in keep.items()}


def fidelity_reference(input_ink: np.ndarray, params: RasterParams) -> np.ndarray:
    """The target of fidelity mode: the binarised input, or its skeleton (``fidelity_reference``)."""
    if params.fidelity_reference == "skeleton":
        from skimage.morphology import skeletonize

        return skeletonize(input_ink)
    return input_ink


def estimate_stroke_width(ink: np.ndarray) -> float:
    """Typical stroke width of a binarised line drawing (pixels), at least 1.

    Ink area over skeleton length, less 0.5 px: the ink threshold (25 % coverage) keeps about a
    quarter pixel of each anti-aliased edge. Used to set the topology tolerances of drawings without
    ground truth. Returns 1.0 for a blank image.
    """
    from skimage.morphology import skeletonize

    ink = np.asarray(ink, dtype=bool)
    n_skel = int(skeletonize(ink).sum())
    if n_skel == 0:
        return 1.0
    return max(1.0, float(ink.sum()) / n_skel - 0.5)


def score_topology(curves: Sequence[np.ndarray], gt_strokes: Sequence[np.ndarray] | None, width: float,
                   params: TopologyParams) -> dict:
    """Topology counts of the output and, with ground truth, endpoint and junction F1.

    Returns
    -------
    dict
        Without ground truth: the output's counts (``curves``, ``free_ends``, ``junctions``,
        ``junction_gaps``, ``dangling``, ``duplicated_px`` ...). With it, also
        ``endpoint_{precision,recall,f1}``, ``junction_{precision,recall,f1}`` and ``gt_*`` counts.
    """
    out = curve_topology(curves, width, params)
    if gt_strokes is None:
        return out.counts()
    gt = curve_topology(gt_strokes, width, params)
    return compare_topology(out, gt, width, params)


def stage_timings(manifests: dict[str, dict]) -> dict:
    """Per-stage time and memory from artifact manifests, and their end-to-end totals.

    Parameters
    ----------
    manifests : dict
        Stage name → manifest (with ``duration_s`` and ``peak_rss_mb``).

    Returns
    -------
    dict
        ``t_<stage>`` seconds and ``rss_<stage>`` MB per stage; ``time_s`` = the sum of the stage
        durations (the end-to-end compute time of the image, whether or not this run recomputed it),
        ``peak_rss_mb`` = the largest peak resident memory of a worker that ran one of its stages.
    """
    row: dict = {}
    total, peak = 0.0, 0.0
    for stage, m in manifests.items():
        d = float(m.get("duration_s", math.nan))
        r = float(m.get("peak_rss_mb", math.nan))
        row[f"t_{stage}"] = d
        row[f"rss_{stage}"] = r
        if math.isfinite(d):
            total += d
        if math.isfinite(r):
            peak = max(peak, r)
    row["time_s"] = total if manifests else math.nan
    row["peak_rss_mb"] = peak if manifests else math.nan
    return row


def _finite(values: Iterable) -> np.ndarray:
    out = []
    for v in values:
        if isinstance(v, bool) or v is None:
            continue
        if isinstance(v, (int, float, np.integer, np.floating)) and math.isfinite(float(v)):
            out.append(float(v))
    return np.array(out, dtype=np.float64)


def summarise(rows: Sequence[dict], columns: Sequence[str], group_by: str | None = None) -> list[dict]:
    """Median, mean and count of each column over the rows, overall and per group.

    Parameters
    ----------
    rows : sequence of dict
        Per-case rows; a row with a non-empty ``error`` counts as a failure.
    columns : sequence of str
        Numeric columns to summarise (missing or NaN values are skipped).
    group_by : str, optional
        Row key that splits the summary (e.g. ``style``); groups are listed after ``all``.

    Returns
    -------
    list of dict
        One dict per group: ``group``, ``cases``, ``failures``, and ``<col>`` → ``{"median", "mean",
        "n"}``.
    """
    groups: dict[str, list[dict]] = {"all": list(rows)}
    if group_by:
        for r in rows:
            g = r.get(group_by)
            if g not in (None, ""):
                groups.setdefault(str(g), []).append(r)
        if len(groups) == 2:  # one group only: it is "all"
            groups = {"all": list(rows)}
    out = []
    for name, rs in groups.items():
        entry: dict = {"group": name, "cases": len(rs), "failures": sum(1 for r in rs if r.get("error"))}
        for c in columns:
            v = _finite(r.get(c) for r in rs)
            entry[c] = {"median": float(np.median(v)) if len(v) else math.nan,
                        "mean": float(v.mean()) if len(v) else math.nan, "n": int(len(v))}
        out.append(entry)
    return out
