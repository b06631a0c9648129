"""Benchmark: a batch of hundreds of drawings and a folder with failed images (issue 54, items 4 and 5).

1. **The driver's memory over a batch.** ``N`` small synthetic drawings (:mod:`stages.synthetic`: lines,
   crosses, tees, wyes, vees and circles at varied angles, sizes and widths, so that no two share a
   key) in a fresh folder, vectorised by ``polyvec FOLDER`` into a fresh store with
   ``runtime.cluster=MODE``. A watcher samples the main process's ``VmRSS`` (``/proc/PID/status``)
   every 0.2 s and counts the export artifacts in the store; it prints the RSS when the 1st, the
   100th, … and the last drawing's export is stored, the peak (``VmHWM``) and the wall time.
2. **A failed image's re-run.** A folder of three small drawings, a 3000-byte junk file named ``junk.png``
   and an all-white PNG, run once; then, paired and alternating, its second run against a run of a
   folder of the three drawings alone (only stored hits) into the same store, ``REPEATS`` times each.

Usage::

    python tests/benchmarks/bench_batch.py [--images N] [--modes sync,local] [--repeats K] [--skip-batch]

The code on ``PYTHONPATH`` runs (``polyvec`` as ``python -m pipeline.launch``), so a checkout of older
code can be measured with the same script.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def small_drawings(folder: Path, n: int) -> None:
    """``n`` distinct small synthetic drawings as ``folder/d000.png`` …"""
    from stages import synthetic

    makers = (synthetic.line, synthetic.cross, synthetic.tee, synthetic.wye, synthetic.vee, synthetic.circle)
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        make = makers[i % len(makers)]
        size = 64 + 8 * (i // len(makers) % 5)
        kwargs = {"size": size, "width": 2.5 + 0.5 * (i % 3)}
        turn = 1.3 * i % 180.0   # distinct for every i < 1800
        if make is synthetic.cross:
            kwargs.update(angle1=turn, angle2=turn + 60.0)
        elif make is synthetic.circle:
            kwargs["radius"] = 12.0 + 0.2 * (i // len(makers))
        else:
            kwargs["angle"] = turn
        (folder / f"d{i:03d}.png").write_bytes(make(**kwargs).png_bytes())


def _rss_kb(pid: int, field: str = "VmRSS") -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def _polyvec(*args: str) -> list[str]:
    return [sys.executable, "-m", "pipeline.launch", *args]


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([p for p in (env.get("PYTHONPATH"), str(REPO)) if p])
    return env


def batch_memory(n: int, mode: str, work: Path) -> dict:
    """Run ``n`` drawings in one batch; the driver's RSS (MB) as drawings finish, peak and wall."""
    folder, store, out = work / f"in{n}", work / f"store-{mode}", work / f"out-{mode}"
    if not folder.exists():
        small_drawings(folder, n)
    t0 = time.perf_counter()
    proc = subprocess.Popen(_polyvec(str(folder), f"output={out}", f"store.path={store}", f"runtime.cluster={mode}",
                                     "runtime.progress=false"),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=_env(), cwd=work)
    marks = sorted({1, *range(100, n + 1, 100), n})
    curve: dict[int, float] = {}
    peak = [0]

    def watch() -> None:
        exports = store / "export"
        while proc.poll() is None:
            rss = _rss_kb(proc.pid)
            hwm = _rss_kb(proc.pid, "VmHWM")
            if hwm:
                peak[0] = max(peak[0], hwm)
            done = sum(1 for _ in exports.glob("*/*")) if exports.is_dir() else 0
            for m in marks:
                if done >= m and m not in curve and rss:
                    curve[m] = rss / 1024
            time.sleep(0.2)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    _, err = proc.communicate()
    watcher.join()
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        print(err[-3000:], file=sys.stderr)
    return {"mode": mode, "n": n, "rc": proc.returncode, "wall_s": wall, "rss_mb": curve, "peak_mb": peak[0] / 1024}


def failed_rerun(work: Path, repeats: int) -> dict:
    """Second runs of a folder with two failed images against runs of its hits alone, paired."""
    import numpy as np
    from PIL import Image

    mixed, hits = work / "mixed", work / "hits"
    small_drawings(mixed, 3)
    small_drawings(hits, 3)   # the same three drawings: stored hits once the mixed folder ran
    (mixed / "junk.png").write_bytes(np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    Image.fromarray(np.full((300, 300), 255, np.uint8)).save(mixed / "white.png")
    store = work / "store-failed"

    def run(folder: Path) -> float:
        t = time.perf_counter()
        subprocess.run(_polyvec(str(folder), f"output={work / 'out-failed'}", f"store.path={store}",
                                "runtime.progress=false"), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                       env=_env(), cwd=work)
        return time.perf_counter() - t

    first = run(mixed)
    with_failed, only_hits = [], []
    for _ in range(repeats):
        with_failed.append(run(mixed))
        only_hits.append(run(hits))
    return {"first_s": first, "second_s": with_failed, "hits_s": only_hits}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=300)
    parser.add_argument("--modes", default="sync,local")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--skip-batch", action="store_true")
    parser.add_argument("--skip-failed", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_batch-") as tmp:
        work = Path(tmp)
        if not args.skip_batch:
            for mode in args.modes.split(","):
                r = batch_memory(args.images, mode, work)
                curve = "  ".join(f"after {k}: {v:.0f}" for k, v in sorted(r["rss_mb"].items()))
                print(f"batch of {r['n']} ({r['mode']}): wall {r['wall_s']:.1f} s, exit {r['rc']}; driver RSS MB "
                      f"{curve}; peak {r['peak_mb']:.0f}", flush=True)
        if not args.skip_failed:
            r = failed_rerun(work, args.repeats)
            med = statistics.median
            print(f"folder with junk.png and white.png: first run {r['first_s']:.2f} s; second runs "
                  + " ".join(f"{s:.2f}" for s in r["second_s"]) + f" (median {med(r['second_s']):.2f}); "
                  + "its hits alone " + " ".join(f"{s:.2f}" for s in r["hits_s"])
                  + f" (median {med(r['hits_s']):.2f})", flush=True)


if __name__ == "__main__":
    main()
