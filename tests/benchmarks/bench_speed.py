"""Benchmark: every row of issue #14's speed table, and the per-stage curve at 1×, 2×, 4× (not a test).

Each row is the real command (``polyvec IMAGE output=… store.path=…``) in a fresh process, timed from
outside with ``/usr/bin/time`` (wall seconds, peak RSS of the main process); stage seconds come from
the manifests the run wrote. The issue measured the 2019 paper's 500×714 scanned penguin, which is not
in ``../shared/data``; the stand-in is the 500×753 scanned elephant of ``../shared/data/drawings``.

Rows:

- fresh install, first image: empty numba and config caches (``NUMBA_CACHE_DIR``, ``XDG_CACHE_HOME``)
  and an empty store; the package's compiled kernels are copied into the numba cache
  (:mod:`pipeline.engine.kernels.shipped`), and the same with ``runtime.shipped_kernels=false`` (their compile, as on
  a machine they do not fit);
- empty store, kernels compiled: the default run (``runtime.cluster=auto``; the same command line again
  on the emptied store, as a user's next drawing) and ``runtime.cluster=sync`` (a new command line);
- every artifact a hit; a λ re-run (``flow.lam=0.5``: flow → select → export); a λ sweep of four jobs
  (``-m flow.lam=0.1,0.2,0.3,0.4``, one process);
- the drawing upscaled 2× and 4× (bicubic), with per-stage seconds and peak MB (the linear-cost curve);
  their strokes are wide enough for ``prep.downsample`` (7.9 and 15.2 px), so they run at 1/2 and 1/4;
  ``--full-resolution`` adds the same rows with ``prep.downsample.enabled=false`` (the stages' own curve);
- the drawing on an A4 sheet at 300 dpi (2480×3508, grey levels of its own paper around it; the issue's
  "page scanned at 300 dpi"), the same with ``prep.crop.enabled=false``, the sheet with six specks of
  dust far from the drawing, the drawing and itself turned 180° in opposite corners of the sheet, and
  the drawing 2× on the sheet at 600 dpi (4961×7016);
- 8 drawings at 512² (the 13 drawings' first 8, fitted into 512×512 on white) with 1 and 2 workers of
  a local cluster (``runtime.cluster=local``), and the speed-up.

Usage::

    python tests/benchmarks/bench_speed.py [--image PNG] [--skip-batch] [--skip-scale] [--full-resolution]
                                           [--batch-repeat N]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline.engine.registry import STAGES as REGISTRY

REPO = Path(__file__).resolve().parents[2]
SHARED = REPO.parent / "shared" / "data" / "drawings"
STAND_IN = SHARED / "scanned" / "elephant.png"
STAGES = tuple(s.name for s in REGISTRY)   # the DAG, in its order


def polyvec(inputs: list[str], out: str, store: str, *overrides: str, env: dict | None = None) -> dict:
    """Run the polyvec command once; wall seconds, peak MB and the stages it computed (from manifests)."""
    exe = str(Path(sys.executable).with_name("polyvec"))
    started = time.time()
    cmd = ["/usr/bin/time", "-f", "TIME %e %M", exe, *inputs, f"output={out}", f"store.path={store}", *overrides]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, env=env or dict(os.environ))
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stdout}\n{proc.stderr}")
    wall, peak_kb = proc.stderr.strip().splitlines()[-1].split()[1:3]
    stages: dict[str, list[float]] = {}
    for manifest in Path(store).glob("*/*/*/manifest.json"):
        m = json.loads(manifest.read_text())
        if m.get("written_at", 0) >= started:
            stages.setdefault(m["stage"], []).append(m["duration_s"])
    return {"wall_s": float(wall), "peak_mb": int(peak_kb) / 1024,
            "stages": {s: sum(v) for s, v in stages.items()}}


def scaled(image: Path, factor: int, folder: Path) -> Path:
    """The drawing upscaled by ``factor`` (bicubic), written as PNG."""
    from PIL import Image

    im = Image.open(image)
    path = folder / f"{image.stem}_x{factor}.png"
    im.resize((im.width * factor, im.height * factor), Image.BICUBIC).save(path)
    return path


def on_a4_sheet(image: Path, folder: Path, dust: bool = False, dpi: int = 300, two: bool = False) -> Path:
    """The drawing pasted on a 2480×3508 sheet (A4 at 300 dpi) of its own paper: grey levels drawn from
    its pixels lighter than its median (a flat sheet would change the page's contrast statistics); with
    ``dust``, six dark specks 5–13 px across far from it (scanner dust); at ``dpi`` 600 the drawing
    upscaled 2× (bicubic) on a 4961×7016 sheet; with ``two``, the drawing turned 180° in the opposite
    corner too (two sketches far apart on one sheet)."""
    import numpy as np
    from PIL import Image

    im = Image.open(image).convert("L")
    if dpi == 600:
        im = im.resize((im.width * 2, im.height * 2), Image.BICUBIC)
    grey = np.asarray(im)
    paper = grey[grey >= np.median(grey)]
    shape, at = ((3508, 2480), (400, 300)) if dpi == 300 else ((7016, 4961), (800, 600))
    sheet = np.random.default_rng(0).choice(paper, size=shape).astype(np.uint8)
    sheet[at[0]:at[0] + grey.shape[0], at[1]:at[1] + grey.shape[1]] = grey
    if two:
        sheet[shape[0] - at[0] - grey.shape[0]:shape[0] - at[0], shape[1] - at[1] - grey.shape[1]:shape[1] - at[1]] = \
            grey[::-1, ::-1]
    if dust:
        yy, xx = np.ogrid[:3508, :2480]
        for cx, cy, r in [(120, 3300, 4), (2300, 200, 3), (2200, 3100, 5), (1500, 2600, 2.5), (150, 150, 3),
                          (2000, 1800, 6)]:
            sheet[(xx - cx) ** 2 + (yy - cy) ** 2 <= r * r] = 60
    path = folder / f"{image.stem}_a4{'_dust' if dust else ''}{'_600' if dpi == 600 else ''}{'_two' if two else ''}.png"
    Image.fromarray(sheet).save(path)
    return path


def fitted_512(images: list[Path], folder: Path) -> list[str]:
    """Each drawing fitted into a 512×512 white canvas (aspect kept)."""
    from PIL import Image

    paths = []
    for i, image in enumerate(images):
        im = Image.open(image).convert("L")
        s = 512 / max(im.size)
        im = im.resize((round(im.width * s), round(im.height * s)), Image.BICUBIC)
        canvas = Image.new("L", (512, 512), 255)
        canvas.paste(im, ((512 - im.width) // 2, (512 - im.height) // 2))
        path = folder / f"d{i}_{image.parent.name}_{image.stem}.png"
        canvas.save(path)
        paths.append(str(path))
    return paths


def stage_line(r: dict) -> str:
    return "  ".join(f"{s} {r['stages'][s]:.2f}" for s in STAGES if s in r["stages"])


def row(name: str, r: dict) -> None:
    print(f"{name:<58}{r['wall_s']:>8.1f} s {r['peak_mb']:>7.0f} MB   {stage_line(r)}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--image", type=Path, default=STAND_IN)
    ap.add_argument("--skip-batch", action="store_true")
    ap.add_argument("--skip-scale", action="store_true")
    ap.add_argument("--batch-repeat", type=int, default=1,
                    help="run the 1- and 2-worker batches this many times, alternated (their ratio varies by ±0.2)")
    ap.add_argument("--full-resolution", action="store_true",
                    help="also the scaled rows with prep.downsample.enabled=false")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # A fresh install: empty numba and config caches (pipeline.engine.compose) of its own.
        env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp / "numba-cache"), XDG_CACHE_HOME=str(tmp / "cache"))
        img, out, store = str(args.image), str(tmp / "out"), str(tmp / "store")
        h, w = __import__("PIL.Image", fromlist=["Image"]).open(args.image).size[::-1]
        print(f"drawing: {args.image} ({w}×{h})")
        print(f"{'case':<58}{'wall':>10} {'peak':>10}   stage seconds (manifests)")
        row("fresh numba cache, empty store, first image", polyvec([img], out, store, env=env))
        # Where the shipped kernels do not fit (another CPU or Python): the first run compiles them.
        row("same, no shipped kernels (runtime.shipped_kernels=false)",
            polyvec([img], out, str(tmp / "s0"), "runtime.shipped_kernels=false",
                    env=dict(env, NUMBA_CACHE_DIR=str(tmp / "numba-cache-0"), XDG_CACHE_HOME=str(tmp / "cache-0"))))
        # The user's next command, the same line on an emptied store (a new drawing's artifacts are
        # missing as an empty store's are): its config composition is cached by now.
        shutil.rmtree(store)
        row("empty store, kernels compiled, default run", polyvec([img], out, store, env=env))
        row("same, runtime.cluster=sync", polyvec([img], out, str(tmp / "s2"), "runtime.cluster=sync", env=env))
        row("again, every artifact a hit", polyvec([img], out, store, env=env))
        row("λ re-run (flow.lam=0.5: flow → select → export)",
            polyvec([img], out, store, "flow.lam=0.5", env=env))
        # The design card's use: a Hydra sweep of λ on a stored drawing (one process, four jobs).
        row("λ sweep, 4 jobs (-m flow.lam=0.1,0.2,0.3,0.4)",
            polyvec([img], out, store, "-m", "flow.lam=0.1,0.2,0.3,0.4", env=env))
        if not args.skip_scale:
            for factor in (2, 4):
                big = scaled(args.image, factor, tmp)
                row(f"×{factor} ({w * factor}×{h * factor}), empty store",
                    polyvec([str(big)], out, str(tmp / f"sx{factor}"), env=env))
                if args.full_resolution:
                    row(f"×{factor}, same, prep.downsample.enabled=false",
                        polyvec([str(big)], out, str(tmp / f"fx{factor}"), "prep.downsample.enabled=false", env=env))
            sheet = str(on_a4_sheet(args.image, tmp))
            row("on an A4 sheet at 300 dpi (2480×3508), empty store", polyvec([sheet], out, str(tmp / "a4"), env=env))
            row("same, prep.crop.enabled=false",
                polyvec([sheet], out, str(tmp / "a4f"), "prep.crop.enabled=false", env=env))
            dusty = str(on_a4_sheet(args.image, tmp, dust=True))
            row("same sheet with 6 specks of dust far from it", polyvec([dusty], out, str(tmp / "a4d"), env=env))
            pair = str(on_a4_sheet(args.image, tmp, two=True))
            row("it and itself turned 180° in opposite corners of the sheet", polyvec([pair], out, str(tmp / "a42"), env=env))
            fine = str(on_a4_sheet(args.image, tmp, dpi=600))
            row("the drawing 2× on an A4 sheet at 600 dpi (4961×7016)", polyvec([fine], out, str(tmp / "a4x"), env=env))
        if not args.skip_batch:
            drawings = sorted(SHARED.glob("*/*.png"))[:8]
            folder = tmp / "batch"
            folder.mkdir()
            batch = fitted_512(drawings, folder)
            ratios = []
            for k in range(max(1, args.batch_repeat)):
                one = polyvec([str(folder)], out, str(tmp / f"b1-{k}"), "runtime.cluster=local", "runtime.workers=1",
                              env=env)
                two = polyvec([str(folder)], out, str(tmp / f"b2-{k}"), "runtime.cluster=local", "runtime.workers=2",
                              env=env)
                row("8 drawings 512², local cluster, 1 worker", one)
                row("8 drawings 512², local cluster, 2 workers", two)
                ratios.append(one["wall_s"] / two["wall_s"])
                print(f"2 workers vs 1 worker: {ratios[-1]:.2f}×")
            if len(ratios) > 1:
                print(f"2 workers vs 1 worker over {len(ratios)} pairs: median {float(np.median(ratios)):.2f}× "
                      f"(min {min(ratios):.2f}, max {max(ratios):.2f})")


if __name__ == "__main__":
    main()
