"""Evaluation of vectorisations: the metrics behind ``polyvec-bench`` (shared/reference/metrics.md).

- :mod:`stages.evaluate.raster` — Chamfer, Hausdorff and F1 of Yan et al. 2020 and the thin-stroke
  rasteriser that normalises vectors for them;
- :mod:`stages.evaluate.curve_topology` — free ends, junctions, junction gaps, dangling branches and
  duplicated curve length by valence, and their F1 against vector ground truth;
- :mod:`stages.evaluate.keypoints` — keypoint F1 (the authors' and one-to-one);
- :mod:`stages.evaluate.matching` — one-to-one matching within a radius;
- :mod:`stages.evaluate.score` — one case's scores, timings from manifests, summaries;
- :mod:`stages.evaluate.svg` — polylines from SVG text; :mod:`stages.evaluate.report_pictures` — report pictures.

Not a pipeline stage: no ``run``; pure functions of arrays used by ``pipeline/bench.py``. The settings
of the metrics (``bench.raster``, ``bench.topology``) are here, apart from the code, which imports
scipy: the configs (:mod:`pipeline.engine.config`) need them at every start-up of ``polyvec``, the
``bench`` group's own dataclasses (:class:`BenchConfig`) among them.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class TopologyParams:
    """Tolerances of the topology extraction (conf/bench/default.yaml ``topology``), one field per key."""

    meet_min_px: float
    match_min_px: float
    resample_px: float
    crossing_min_angle_deg: float
    junction_merge_factor: float
    gap_max_px: float
    gap_max_widths: float
    dangling_max_px: float
    dangling_max_widths: float
    overlap_max_angle_deg: float
    overlap_exclusion_factor: float
    overlap_self_separation: float


@dataclass
class RasterParams:
    """Raster metric settings (conf/bench/default.yaml ``raster``), one field per key."""

    stroke_width_permille: float
    min_stroke_width_px: float
    renderer: str
    long_edge: int | None
    supersample: int
    ink_threshold: float
    f1_permille: tuple[float, ...]
    f1_pixels: tuple[float, ...]
    fidelity_reference: str

    def __post_init__(self) -> None:
        if self.fidelity_reference not in ("input", "skeleton"):
            raise ValueError(f"raster.fidelity_reference must be input or skeleton, not {self.fidelity_reference!r}")
        if self.renderer not in ("cairo", "supersample"):
            raise ValueError(f"raster.renderer must be cairo or supersample, not {self.renderer!r}")
        if self.long_edge is not None and int(self.long_edge) < 1:
            raise ValueError(f"raster.long_edge must be a positive number of pixels or null, not {self.long_edge!r}")


@dataclass
class BenchKeypointsConfig:
    """``bench.keypoints``: the authors' keypoint F1 and a one-to-one F1 (metrics.md §3)."""

    radius_height_fraction: float
    one_to_one_radius_px: float


@dataclass
class BenchReportConfig:
    """``bench.report``: the summary tables and ``report.html``."""

    sort_by: str
    html: bool
    max_html_cases: int
    image_scale: int
    gt_columns: list[str]
    fidelity_columns: list[str]


@dataclass
class BenchConfig:
    """The ``bench`` config group of ``polyvec-bench`` (``conf/bench/default.yaml``), one field per key."""

    cases: list[str]
    out: str
    limit: int | None
    run_pipeline: bool
    raster: RasterParams
    keypoints: BenchKeypointsConfig
    topology: TopologyParams
    report: BenchReportConfig
