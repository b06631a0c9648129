"""Benchmark: prep + field time and peak memory on the scanned drawings.

Run from the repository root::

    python tests/benchmarks/bench_field.py [--rtol 1e-6] [--beta 10] [DRAWING.png ...]

Each drawing runs in its own subprocess so that the peak resident memory (``ru_maxrss``) is that
drawing's alone.  Defaults to ``../shared/data/drawings/scanned/*.png``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT / ".." / "shared"

_CHILD = r"""
import json, resource, sys, time
from pathlib import Path
import yaml
sys.path.insert(0, sys.argv[1])
import numpy as np
from stages import prep, field, extension
path, overrides = sys.argv[2], json.loads(sys.argv[3])
root = Path(sys.argv[1])
pcfg = yaml.safe_load(open(root / "conf/prep/default.yaml"))
fcfg = yaml.safe_load(open(root / "conf/field/default.yaml"))
ecfg = yaml.safe_load(open(root / "conf/extension/default.yaml"))
fcfg.update(overrides)
data = Path(path).read_bytes()
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t0 = time.perf_counter(); c0 = time.process_time()
p = prep.run(pcfg, image_bytes=data, image_name=Path(path).name)
t1 = time.perf_counter()
f = field.run(fcfg, prep=p)
e = extension.run(ecfg, prep=p, field=f)
t2 = time.perf_counter(); c2 = time.process_time()
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
d = f.data
print(json.dumps({"name": Path(path).stem, "shape": list(p["grey"].shape),
                  "band": d["band_pixels"], "prep_s": t1 - t0, "field_s": t2 - t1,
                  "cpu_s": c2 - c0, "solve_s": d["solve_seconds"], "ext_s": e.data["extension_seconds"],
                  "cg": d["cg_iterations"], "sing": d["singular_pixels"],
                  "ext_cg": e.data["extension_cg_iterations"],
                  "rss_start_mb": rss0 / 1024, "peak_rss_mb": rss / 1024}))
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("drawings", nargs="*")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a field config key (YAML value), e.g. --set beta=50")
    args = ap.parse_args()
    import yaml

    overrides = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in args.set)}
    paths = args.drawings or sorted(str(p) for p in (SHARED / "data/drawings/scanned").glob("*.png"))
    if not paths:
        print("no drawings (../shared absent?)")
        return 0
    print(f"{'drawing':12s} {'size':>9s} {'band':>7s} {'prep s':>7s} {'field s':>8s} {'total s':>8s} "
          f"{'cpu s':>6s} {'peak MB':>8s}  CG iterations / singular pixels per solve")
    for path in paths:
        out = subprocess.run([sys.executable, "-c", _CHILD, str(ROOT), path, json.dumps(overrides)],
                             capture_output=True, text=True)
        if out.returncode:
            print(path, "FAILED\n", out.stderr[-2000:])
            continue
        r = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"{r['name']:12s} {r['shape'][1]:4d}x{r['shape'][0]:<4d} {r['band']:7d} {r['prep_s']:7.2f} "
              f"{r['field_s']:8.2f} {r['prep_s'] + r['field_s']:8.2f} {r['cpu_s']:6.2f} {r['peak_rss_mb']:8.0f}  "
              f"{r['cg']} / {r['sing']} ext {r['ext_cg']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
