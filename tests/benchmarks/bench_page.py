"""Benchmark: a full page of ink — one drawing tiled n×n — against the drawing alone (issue 54; not a test).

Tiling is the honest test of cost against ink: the page has n² times the ink at the same stroke width
(upscaling widens the strokes, and prep then downsamples them). The stand-in for the issue's 500×714
scanned penguin is the 500×753 scanned elephant of ``../shared/data/drawings``. Each row is the real
command (``polyvec PAGE output=… store.path=…``) in a fresh process on an empty store, timed from outside
with ``/usr/bin/time`` (wall seconds, peak RSS of the largest process: the main one or the keypoints
child); stage seconds come from the manifests. ``×1`` is each stage's time divided by its time on the
drawing alone (the issue's target: every stage ≤ 17× on the 4×4 page, 16× the ink).

``--code DIR ...`` runs each row once per source tree (``PYTHONPATH=DIR``, e.g. a ``git archive`` of the
code before), interleaved, so that a before/after pair shares the machine's minutes.

Usage::

    python tests/benchmarks/bench_page.py [--image PNG] [--sizes 1 4 6] [--code DIR ...] [--repeat N]
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
from bench_speed import STAGES, STAND_IN, polyvec


def tiled(image: Path, n: int, folder: Path) -> Path:
    """The drawing repeated ``n`` × ``n`` times side by side, as a grey PNG."""
    from PIL import Image

    grey = np.asarray(Image.open(image).convert("L"))
    path = folder / f"{image.stem}_{n}x{n}.png"
    Image.fromarray(np.tile(grey, (n, n))).save(path)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--image", type=Path, default=STAND_IN)
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 4, 6])
    parser.add_argument("--code", nargs="+", default=[""], help="source trees to run (PYTHONPATH); '' = installed")
    parser.add_argument("--repeat", type=int, default=1)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="polyvec-bench-page-"))
    try:
        pages = {n: tiled(args.image, n, work) for n in args.sizes}
        best: dict[tuple[str, int], dict] = {}
        for _ in range(args.repeat):
            for n in args.sizes:
                for code in args.code:
                    env = dict(os.environ)
                    if code:
                        env["PYTHONPATH"] = str(Path(code).resolve())
                    store, out = work / "store", work / "out"
                    shutil.rmtree(store, ignore_errors=True)
                    row = polyvec([str(pages[n])], str(out), str(store), env=env)
                    if (code, n) not in best or row["wall_s"] < best[(code, n)]["wall_s"]:
                        best[(code, n)] = row
        for code in args.code:
            print(f"\n## code: {code or 'installed'}  ({args.image.name}, best of {args.repeat})")
            one = best.get((code, 1)) or best[(code, min(args.sizes))]
            header = "| stage | " + " | ".join(f"{n}×{n} s | ×1" for n in args.sizes) + " |"
            print(header)
            print("|" + "---|" * (1 + 2 * len(args.sizes)))
            for stage in STAGES:
                cells = []
                for n in args.sizes:
                    s = best[(code, n)]["stages"].get(stage, 0.0)
                    base = one["stages"].get(stage, 0.0)
                    cells.append(f"{s:.2f} | {s / base:.1f}" if base else f"{s:.2f} | –")
                print(f"| {stage} | " + " | ".join(cells) + " |")
            print("| **wall** | " + " | ".join(f"{best[(code, n)]['wall_s']:.1f} | "
                                               f"{best[(code, n)]['wall_s'] / one['wall_s']:.1f}"
                                               for n in args.sizes) + " |")
            print("| **peak MB** | " + " | ".join(f"{best[(code, n)]['peak_mb']:.0f} | "
                                                  f"{best[(code, n)]['peak_mb'] / one['peak_mb']:.1f}"
                                                  for n in args.sizes) + " |")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
