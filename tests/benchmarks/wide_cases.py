"""Large versions of validation cases, for the downsampling rule of ``prep`` (not a test).

Re-renders both styles of every ``step``-th drawing of a validation split folder (made by ``python -m
pipeline.validation_cases``) ``factor`` times larger — canvas, strokes and stroke width — in the
case's own style (clean or pencil, :func:`pipeline.validation_cases.render_case`), as a scan at a
higher resolution would give, and writes ``<name>_x<F>.png`` with a case JSON in those pixels (the
acceptance scorer's radii follow ``width``)::

    python tests/benchmarks/wide_cases.py VALIDATION_DIR OUT_DIR [--factor 3] [--step 4]
    polyvec OUT_DIR output=ON ; polyvec OUT_DIR output=OFF prep.downsample.enabled=false
    python ../shared/tools/score_folder.py ON OUT_DIR
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main() -> int:
    import conf
    from pipeline.train import compose_plain
    from pipeline.validation_cases import render_case

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--factor", type=int, default=3)
    ap.add_argument("--step", type=int, default=4)
    ap.add_argument("--seed", type=int, default=11)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(a.seed)
    cfg = compose_plain(Path(conf.__file__).resolve().parent, [])     # once, not per case
    drawings = sorted({p.stem.rsplit("_", 1)[0] for p in a.cases.glob("val_*.json")})[::a.step]
    chosen = [a.cases / f"{d}_{style}.json" for d in drawings for style in ("clean", "pencil")]
    for path in chosen:
        gt = json.loads(path.read_text())
        size = int(gt.get("size", 512)) * a.factor
        strokes = [np.asarray(s, np.float64) * a.factor for s in gt["strokes"]]
        case = render_case(rng, strokes, size, float(gt["width"]) * a.factor, gt["style"], cfg)
        name = f"{path.stem}_x{a.factor}"
        case.image.save(a.out / f"{name}.png")
        (a.out / f"{name}.json").write_text(json.dumps(case.truth))
    print(f"{len(chosen)} cases in {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
