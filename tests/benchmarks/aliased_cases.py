"""Thin aliased versions of validation cases, for the supersampling rule of ``prep`` (not a test).

Re-renders every ``step``-th ``val_qd_*_clean`` case of a validation split folder (made by
``python -m pipeline.validation_cases``) from its strokes as aliased grey lines (PIL ``ImageDraw.line``,
no anti-aliasing) 1 and 2 px wide, and writes ``<name>_alias<W>.png`` with a case JSON whose ``width``
is W, so that the acceptance scorer can score them::

    python tests/benchmarks/aliased_cases.py VALIDATION_DIR OUT_DIR [--step 3] [--count 20]
    polyvec OUT_DIR output=ON ; polyvec OUT_DIR output=OFF prep.supersample.enabled=false
    python ../shared/tools/score_folder.py ON OUT_DIR

PIL marks pixel indices, so the ink lies 0.5 px right of and below the strokes' corner-origin
coordinates (the same for both runs; it only shifts the geometric figures).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--step", type=int, default=3)
    ap.add_argument("--count", type=int, default=20)
    ap.add_argument("--grey", type=int, default=110, help="ink level 0-255")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    chosen = sorted(a.cases.glob("val_qd_*_clean.json"))[::a.step][:a.count]
    for path in chosen:
        gt = json.loads(path.read_text())
        size = gt.get("size", 512)
        h, w = (size, size) if isinstance(size, int) else size
        name = path.stem.replace("_clean", "")
        for width in (1, 2):
            img = Image.new("L", (w, h), 255)
            draw = ImageDraw.Draw(img)
            for stroke in gt["strokes"]:
                draw.line([tuple(p) for p in np.asarray(stroke, float)], fill=a.grey, width=width)
            img.save(a.out / f"{name}_alias{width}.png")
            (a.out / f"{name}_alias{width}.json").write_text(json.dumps(dict(gt, width=float(width), style="alias")))
    print(f"{2 * len(chosen)} cases in {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
