"""Upscaled low-resolution versions of validation cases, for prep's upscaled-drawing rule (not a test).

A drawing made at a low resolution with thin anti-aliased strokes and then enlarged by a non-integer
factor with blended block edges (the paper's duck: ~1.3 px strokes enlarged ≈3.5×) is a staircase of
blocks, one stroke's core dark blocks inside grey ones (its anti-aliasing, enlarged into a halo).
Re-renders both styles of every ``step``-th drawing of a validation split folder (made by ``python -m
pipeline.validation_cases``) that way: its strokes placed on a ``512 / factor`` canvas, drawn there in
the case's own style (:func:`pipeline.validation_cases.render_case`) ``width`` px wide, and the image
enlarged to 512² by area-weighted resampling (``--edges box``, PIL ``BOX``: each output pixel the mean of
the source pixels it covers, so a pixel across a block edge blends two blocks) or with softer edges
(``--edges soft``: enlarged by the integer ``ceil(2·factor)`` nearest, then shrunk to 512² bilinear, so
block edges blend over about two pixels and fewer rows repeat: 37–42 % at 3.5×, 60–72 % with ``box``).
Writes ``<name>_up<F>.png`` with a
case JSON in the enlarged pixels (strokes, keypoints and ``width`` times the factor: the acceptance
scorer's radii follow ``width``)::

    python tests/benchmarks/halo_cases.py VALIDATION_DIR OUT_DIR [--factors 2.5 3.5 4.25] [--step 6]
        [--offset 0] [--edges box|soft]
    polyvec OUT_DIR output=ON ; polyvec OUT_DIR output=OFF prep.deblock.enabled=false
    python ../shared/tools/score_folder.py ON OUT_DIR

Built from the validation split's strokes only (never from realvec_dev or the 14 drawings).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

SIZE = 512


def main() -> int:
    from PIL import Image

    import conf
    from pipeline.train import compose_plain
    from pipeline.validation_cases import render_case

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--factors", type=float, nargs="+", default=[2.5, 3.5, 4.25])
    ap.add_argument("--widths", type=float, nargs="+", default=[1.0, 1.5],
                    help="stroke widths at the low resolution (px), one per drawing in turn")
    ap.add_argument("--step", type=int, default=6)
    ap.add_argument("--offset", type=int, default=0, help="first drawing taken (of the sorted drawings)")
    ap.add_argument("--edges", choices=("box", "soft"), default="box")
    ap.add_argument("--seed", type=int, default=13)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(a.seed)
    cfg = compose_plain(Path(conf.__file__).resolve().parent, [])     # once, not per case
    drawings = sorted({p.stem.rsplit("_", 1)[0] for p in a.cases.glob("val_*.json")})[a.offset::a.step]
    n = 0
    for i, d in enumerate(drawings):
        factor = a.factors[i % len(a.factors)]
        width = a.widths[(i // len(a.factors)) % len(a.widths)]
        low = round(SIZE / factor)
        f = SIZE / low                                    # the exact enlargement of this canvas
        for style in ("clean", "pencil"):
            gt = json.loads((a.cases / f"{d}_{style}.json").read_text())
            strokes = [np.asarray(s, np.float64) / f for s in gt["strokes"]]
            case = render_case(rng, strokes, low, width, style, cfg)
            image = case.image.convert("L")
            if a.edges == "soft":
                k = int(np.ceil(2 * factor))
                image = image.resize((low * k, low * k), Image.NEAREST).resize((SIZE, SIZE), Image.BILINEAR)
            else:
                image = image.resize((SIZE, SIZE), Image.BOX)
            truth = dict(case.truth, size=SIZE, width=width * f, style=f"{style}_up",
                         strokes=[np.round(np.asarray(s) * f, 2).tolist() for s in case.truth["strokes"]])
            for key in ("endpoints", "junctions", "corners"):
                truth[key] = np.round(np.asarray(case.truth[key], np.float64).reshape(-1, 2) * f, 2).tolist()
            name = f"{d}_{style}_up{factor:g}" + ("s" if a.edges == "soft" else "")
            image.save(a.out / f"{name}.png")
            (a.out / f"{name}.json").write_text(json.dumps(truth))
            n += 1
    print(f"{n} cases in {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
