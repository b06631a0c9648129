"""Benchmark: per-stage seconds on random scribbles of growing density (not a test; issue 18 item 4).

A scribble is ``N`` random straight 2-px lines on a 400×400 white canvas (fixed seed per ``N``), so the
number of crossings, and with it the number of curves the export joins and contracts, grows as N².
Every stage runs in-process (``runtime.cluster=sync``) on an empty store; then the export stage is run
once more directly on the stored select artifacts, so its time can be compared before and after a
change to export alone (``--export-only`` reuses the stores of an earlier run).

Usage::

    python tests/benchmarks/bench_scribble.py [--lines 100 200 400] [--work DIR] [--export-only]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]

CHILD = r"""
import json, sys
from hydra import compose, initialize_config_module
from pipeline.engine.execute.batch import run_batch
image, store = sys.argv[1], sys.argv[2]
with initialize_config_module(config_module="conf", version_base=None):
    cfg = compose(config_name="config", overrides=[f"store.path={store}", "runtime.cluster=sync"])
batch = run_batch([image], cfg)
per = batch.results[image]
print(json.dumps({s: [r.status, round(r.duration_s, 3), r.error, r.key, list(r.warnings)] for s, r in per.items()}))
"""


def scribble(n_lines: int, size: int = 400, seed: int = 0) -> bytes:
    """PNG bytes of ``n_lines`` random 2-px black lines on white (end points uniform on the canvas)."""
    import io

    from PIL import Image, ImageDraw

    rng = np.random.default_rng(seed + n_lines)
    img = Image.new("L", (size, size), 255)
    draw = ImageDraw.Draw(img)
    for x0, y0, x1, y1 in rng.uniform(10, size - 10, (n_lines, 4)):
        draw.line([(x0, y0), (x1, y1)], fill=0, width=2)
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue()


def export_seconds(store: Path, keys: dict[str, str]) -> tuple[float, int]:
    """Seconds of the export stage run directly on the stored upstream artifacts, and its curve count."""
    from omegaconf import OmegaConf

    from pipeline.engine.store import ArtifactStore
    from stages import export

    st = ArtifactStore(str(store), create=False)
    inputs = {name: st.load(name, keys[name]) for name in ("prep", "topology", "flow", "select")}
    cfg = OmegaConf.to_container(OmegaConf.load(REPO / "conf" / "export" / "default.yaml"))
    t0 = time.perf_counter()
    art = export.run(cfg, **inputs)
    return time.perf_counter() - t0, len(art.data["curves"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    ap.add_argument("--lines", type=int, nargs="+", default=[100, 200, 400])
    ap.add_argument("--work", type=Path, default=Path("/tmp/polyvec_scribble"))
    ap.add_argument("--export-only", action="store_true", help="reuse the stores of an earlier run")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    for n in args.lines:
        image, store, keys_file = (args.work / f"scribble{n}.png", args.work / f"store{n}",
                                   args.work / f"keys{n}.json")
        if not args.export_only or not keys_file.exists():
            image.write_bytes(scribble(n))
            out = subprocess.run([sys.executable, "-c", CHILD, str(image), str(store)], capture_output=True,
                                 text=True, cwd=REPO)
            if out.returncode:
                raise SystemExit(out.stderr)
            stages = json.loads(out.stdout.strip().splitlines()[-1])
            keys_file.write_text(json.dumps(stages))
            print(f"{n} lines: " + "  ".join(f"{s} {v[1]:.2f}s" + ("" if v[0] == "computed" else f"({v[0]})")
                                             for s, v in stages.items()), flush=True)
            failed = [f"{s}: {v[2]}" for s, v in stages.items() if v[0] == "failed"]
            if failed:
                print("    failed: " + "; ".join(failed))
            for s, v in stages.items():                     # guards that bound (Artifact.notes)
                for note in v[4]:
                    print(f"    warning: {s}: {note}")
        stages = json.loads(keys_file.read_text())
        if all(stages.get(s, ["failed"])[0] in ("computed", "cached") for s in ("prep", "topology", "flow", "select")):
            sec, n_curves = export_seconds(store, {s: v[3] for s, v in stages.items()})
            print(f"{n} lines: export alone {sec:.2f} s ({n_curves} curves)", flush=True)


if __name__ == "__main__":
    main()
