"""Evaluation of vectorisations: the metrics behind ``polyvec-bench`` (shared/reference/metrics.md).

- :mod:`stages.evaluate.raster` — Chamfer, Hausdorff and F1 of Yan et al. 2020 and the thin-stroke
  rasteriser that normalises vectors for them;
- :mod:`stages.evaluate.curve_topology` — free ends, junctions, junction gaps, dangling branches and
  duplicated curve length by valence, and their F1 against vector ground truth;
- :mod:`stages.evaluate.keypoints` — keypoint F1 (the authors' and one-to-one);
- :mod:`stages.evaluate.matching` — one-to-one matching within a radius;
- :mod:`stages.evaluate.score` — one case's scores, timings from manifests, summaries;
- :mod:`stages.evaluate.svg` — polylines from SVG text; :mod:`stages.evaluate.report_pictures` — report pictures.

Not a pipeline stage: no ``run``; pure functions of arrays used by ``pipeline/bench.py``.
"""
