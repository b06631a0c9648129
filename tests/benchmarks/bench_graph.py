"""Benchmark of the graph stage: time and peak memory per drawing.

Usage::

    python tests/benchmarks/bench_graph.py [DRAWING.png ...] [--repeat 3] [--render OUT_DIR]

Without drawings it uses ``../shared/data/drawings/scanned/*.png``.  ``prep`` and ``field`` are computed
first (cached as .npz under ``$TMPDIR/polyvec-bench-graph``, keyed by the image bytes and the two
configs); then each drawing's graph stage runs in a fresh subprocess, so its peak resident memory
(``ru_maxrss``) is the graph stage's own on top of the interpreter and the inputs.  The numba kernels
are loaded (or compiled) on a tiny drawing first, so the reported times are steady-state; the
warm-up time is reported separately.  Wall time and CPU time are both given: on a shared, loaded
machine the CPU time is the steadier number.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT / ".." / "shared"
sys.path.insert(0, str(ROOT))


def _cfg(stage: str) -> dict:
    import yaml

    return yaml.safe_load((ROOT / "conf" / stage / "default.yaml").read_text())


def _inputs(path: Path, cache: Path) -> Path:
    """prep + field arrays of one drawing, cached."""
    import numpy as np

    from stages import field, prep

    data = path.read_bytes()
    key = hashlib.sha1(data + json.dumps([_cfg("prep"), _cfg("field")], sort_keys=True).encode()).hexdigest()[:16]
    out = cache / f"{path.stem}-{key}.npz"
    if not out.exists():
        t = time.perf_counter()
        p = prep.run(_cfg("prep"), image_bytes=data, image_name=path.name)
        f = field.run(_cfg("field"), prep=p)
        np.savez(out, grey=p["grey"], mask=p["mask"], c0=f["c0"], c2=f["c2"], roots=f["roots"],
                 singular=f["singular"])
        print(f"  {path.name}: prep + field {time.perf_counter() - t:.1f} s (cached in {out})", file=sys.stderr)
    return out


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _worker(npz: str, repeat: int, render: str | None) -> dict:
    import numpy as np

    from stages import graph, synthetic
    from stages.artifact import Artifact

    cfg = _cfg("graph")
    t = time.perf_counter()
    # warm-up: load (or compile) the numba kernels on a tiny drawing
    from stages import field, prep

    d = synthetic.line()
    p = prep.run(_cfg("prep"), image_bytes=d.png_bytes(), image_name="warmup")
    graph.run(cfg, prep=p, field=field.run(_cfg("field"), prep=p))
    warm = time.perf_counter() - t
    z = np.load(npz)
    p = Artifact(arrays={"grey": z["grey"], "mask": z["mask"]})
    f = Artifact(arrays={k: z[k] for k in ("c0", "c2", "roots", "singular")})
    base = _rss_mb()
    walls, cpus = [], []
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        art = graph.run(cfg, prep=p, field=f)
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    peak = _rss_mb()
    if render:
        from PIL import Image

        Image.fromarray(graph.render_graph(p["grey"], art.arrays)).save(render)
    return {"shape": list(z["mask"].shape), "band_px": int(z["mask"].sum()), "warmup_s": warm,
            "wall_s": min(walls), "cpu_s": min(cpus), "peak_rss_mb": peak, "rss_before_mb": base,
            "stage_timings": art.data["timings"], "counts": art.data["counts"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("drawings", nargs="*", type=Path)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--render", type=Path, default=None, help="write <stem>_graph.png renders here")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "polyvec-bench-graph")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--render-to", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(_worker(args.worker, args.repeat, args.render_to)))
        return 0
    drawings = args.drawings or sorted((SHARED / "data" / "drawings" / "scanned").glob("*.png"))
    if not drawings:
        print("no drawings (../shared absent?)", file=sys.stderr)
        return 1
    args.cache.mkdir(parents=True, exist_ok=True)
    if args.render:
        args.render.mkdir(parents=True, exist_ok=True)
    rows = []
    for path in drawings:
        npz = _inputs(path, args.cache)
        cmd = [sys.executable, __file__, "--worker", str(npz), "--repeat", str(args.repeat)]
        if args.render:
            cmd += ["--render-to", str(args.render / f"{path.stem}_graph.png")]
        res = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
        if res.returncode != 0:
            print(res.stderr, file=sys.stderr)
            return res.returncode
        r = json.loads(res.stdout.strip().splitlines()[-1])
        rows.append((path.stem, r))
        tm, ct = r["stage_timings"], r["counts"]
        print(f"{path.stem:12s} {r['shape'][0]}x{r['shape'][1]} band {r['band_px']:6d} px | "
              f"graph wall {r['wall_s']:5.2f} s cpu {r['cpu_s']:5.2f} s "
              f"(trace {tm['trace_s']:.2f}, sections {tm['sections_s']:.2f}, cleanup {tm['cleanup_s']:.2f}) | "
              f"peak RSS {r['peak_rss_mb']:6.0f} MB (before {r['rss_before_mb']:.0f}) | "
              f"{ct['streamlines']} streamlines, {ct['streamline_samples']} samples, "
              f"V {ct['vertices']} E {ct['edges']} | warm-up {r['warmup_s']:.1f} s")
    print(f"load average during the run: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    sys.exit(main())
