"""Benchmark: what a fresh install's first run spends compiling numba kernels (not a test).

Runs the bundled example drawing through the engine twice in fresh subprocesses
(``runtime.cluster=sync``, empty stores), the first with an empty numba cache
(``NUMBA_CACHE_DIR`` set to a new folder), the second reusing that cache, and prints per-stage seconds
of both and, per compiled kernel, how many type specialisations the first run compiled (each one is
a separate compile).

Usage::

    python tests/benchmarks/bench_compile.py [IMAGE]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

CHILD = r"""
import json, sys, time
from hydra import compose, initialize_config_module
from pipeline.engine.execute.batch import run_batch
image, store = sys.argv[1], sys.argv[2]
with initialize_config_module(config_module="conf", version_base=None):
    cfg = compose(config_name="config", overrides=[f"store.path={store}", "runtime.cluster=sync"])
t0 = time.perf_counter()
batch = run_batch([image], cfg)
wall = time.perf_counter() - t0
import numba.core.registry as reg
from numba.core.dispatcher import Dispatcher
import gc
kernels = {}
for obj in gc.get_objects():
    if isinstance(obj, Dispatcher) and obj.py_func.__module__.startswith("stages"):
        kernels[f"{obj.py_func.__module__}.{obj.py_func.__name__}"] = len(obj.signatures)
print(json.dumps({"wall_s": wall, "stages": {s: round(r.duration_s, 3) for s, r in batch.results[image].items()},
                  "kernels": kernels}))
"""


def _run(image: str, cache: str) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=cache, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    with tempfile.TemporaryDirectory() as store:
        out = subprocess.run([sys.executable, "-c", CHILD, image, store], capture_output=True, text=True,
                             cwd=REPO, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        if len(sys.argv) > 1:
            image = sys.argv[1]
        else:
            from stages.synthetic import example_drawing

            image = str(Path(tmp) / "example.png")
            Path(image).write_bytes(example_drawing().png_bytes())
        cache = str(Path(tmp) / "numba-cache")
        cold, warm = _run(image, cache), _run(image, cache)
    print(f"{'stage':<10}{'empty cache s':>15}{'warm cache s':>14}")
    for s in cold["stages"]:
        print(f"{s:<10}{cold['stages'][s]:>15.2f}{warm['stages'][s]:>14.2f}")
    print(f"{'wall':<10}{cold['wall_s']:>15.2f}{warm['wall_s']:>14.2f}")
    print("kernels compiled on the first run (specialisations):")
    for k, n in sorted(cold["kernels"].items(), key=lambda kv: -kv[1]):
        print(f"  {n:>2}  {k}")


if __name__ == "__main__":
    main()
