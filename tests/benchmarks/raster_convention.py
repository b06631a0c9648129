"""Benchmark: Yan F1@2 and Chamfer of polyvec outputs under three rasterisations (not a test; issue 18).

For each case (a realvec-style ``<name>.png`` + ``<name>.json`` with ground-truth strokes) and the
polyvec output ``OUT/<name>.json`` of the same drawing:

* ``old``   — the bench before issue 18: supersampled capsules at the image's own size;
* ``bench`` — the bench now (``conf/bench`` raster section: cairo at long edge 1000);
* ``svg``   — independent of the bench's code path: both curve sets written as normalised SVGs
  (0.001·L round-capped black strokes on white), rendered by cairosvg at long edge 1000, read back
  with PIL as 8-bit grey and thresholded at 191.25 (metrics.md §2.1–2.2).

Usage::

    python tests/benchmarks/raster_convention.py OUT CASE.png [CASE.png ...]
"""

from __future__ import annotations

import io
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def normalised_svg(curves: list[np.ndarray], shape: tuple[int, int], long_edge: int) -> str:
    """The benchmark's normalised SVG of curves in image pixels, sized to ``long_edge``."""
    h, w = shape
    s = long_edge / max(h, w)
    paths = "".join('<path d="M ' + " L ".join(f"{x:.4f} {y:.4f}" for x, y in c) + '"/>'
                    for c in curves if len(c))
    return (f'<svg xmlns="http://www.w3.org/2000/svg" width="{round(w * s)}" height="{round(h * s)}" '
            f'viewBox="0 0 {w} {h}"><rect width="{w}" height="{h}" fill="white"/>'
            f'<g fill="none" stroke="#000000" stroke-width="{0.001 * max(h, w)}" stroke-linecap="round" '
            f'stroke-linejoin="round">{paths}</g></svg>')


def main(out: Path, cases: list[Path]) -> None:
    import json

    import cairosvg
    from PIL import Image

    from pipeline.bench import load_case, load_grey
    from stages.evaluate.raster import INK_THRESHOLD, raster_metrics
    from stages.config import from_section
    from stages.evaluate.score import RasterParams, gt_scale, render_ink, score_raster
    from tests.benchmarks._common import stage_cfg

    raster = stage_cfg("bench")["raster"]
    new = from_section(RasterParams, raster, "bench.raster")
    old = from_section(RasterParams, dict(raster, renderer="supersample", long_edge=None), "bench.raster")
    print(f"{'case':32s} {'F1@2 old':>9s} {'bench':>7s} {'svg':>7s}   {'chamfer px@1000 bench':>22s} {'svg':>7s}")
    for image in cases:
        case = load_case(image)
        curves = [np.asarray(c["points"], np.float64).reshape(-1, 2)
                  for c in json.loads((out / f"{image.stem}.json").read_text())["curves"]]
        shape = load_grey(image).shape
        m_old = score_raster(render_ink(curves, shape, old), render_ink(case.strokes, shape, old), old)
        scale = gt_scale(shape, new)
        m_new = score_raster(render_ink(curves, shape, new, scale), render_ink(case.strokes, shape, new, scale), new,
                             scale=scale)
        ink = [np.asarray(Image.open(io.BytesIO(cairosvg.svg2png(bytestring=normalised_svg(c, shape, 1000).encode())))
                          .convert("L"), np.float64) < INK_THRESHOLD for c in (curves, case.strokes)]
        m_svg = raster_metrics(ink[0], ink[1], (2,))
        print(f"{case.name:32s} {m_old['f1_2']:9.4f} {m_new['f1_2']:7.4f} {m_svg['f1_2']:7.4f}   "
              f"{1000 * m_new['chamfer']:22.3f} {1000 * m_svg['chamfer']:7.3f}")


if __name__ == "__main__":
    main(Path(sys.argv[1]), [Path(a) for a in sys.argv[2:]])
