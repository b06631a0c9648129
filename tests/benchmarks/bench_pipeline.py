"""Benchmark: the whole pipeline on real drawings, first run and a λ re-run (not a test).

Each drawing runs in a fresh subprocess (so peak memory is per drawing) through the real engine with
an empty store, single-process (``runtime.cluster=sync``) so stage times are not mixed with cluster
start-up. Then ``flow.lam`` is changed and the run repeated on the same store: only flow → select →
export recompute.

Usage::

    python tests/benchmarks/bench_pipeline.py [IMAGES...]   # default: ../shared/data/drawings/scanned/*.png
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DEFAULT = sorted((REPO.parent / "shared" / "data" / "drawings" / "scanned").glob("*.png"))

CHILD = r"""
import json, resource, sys, time
from hydra import compose, initialize_config_module
from pipeline.engine.execute.batch import run_batch
image, store, lam = sys.argv[1], sys.argv[2], sys.argv[3]
overrides = [f"store.path={store}", "runtime.cluster=sync"] + ([f"flow.lam={lam}"] if lam != "-" else [])
with initialize_config_module(config_module="conf", version_base=None):
    cfg = compose(config_name="config", overrides=overrides)
t0 = time.perf_counter()
batch = run_batch([image], cfg)
wall = time.perf_counter() - t0
per = batch.results[image]
print(json.dumps({"wall_s": wall, "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "stages": {s: [r.status, round(r.duration_s, 3), r.error] for s, r in per.items()}}))
"""


def run(image: Path, store: str, lam: str) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, str(image), store, lam], capture_output=True, text=True,
                         cwd=REPO)
    if out.returncode:
        raise SystemExit(out.stderr)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(images: list[Path]) -> None:
    rows = []
    for image in images:
        with tempfile.TemporaryDirectory() as store:
            first = run(image, store, "-")
            rerun = run(image, store, "0.5")
        rows.append((image.name, first, rerun))
        stages = "  ".join(f"{s} {v[1]:.2f}s" + ("" if v[0] == "computed" else f"({v[0]})")
                           for s, v in first["stages"].items())
        print(f"{image.name}: first run {first['wall_s']:.2f} s, peak {first['peak_mb']:.0f} MB | {stages}")
        recomputed = [s for s, v in rerun["stages"].items() if v[0] == "computed"]
        print(f"    λ re-run {rerun['wall_s']:.2f} s, recomputed: {', '.join(recomputed)}")
        for s, v in first["stages"].items():
            if v[2]:
                print(f"    {s}: {v[2]}")


if __name__ == "__main__":
    main([Path(p) for p in sys.argv[1:]] or DEFAULT)
