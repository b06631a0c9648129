"""Benchmark: a keypoint correction's re-run and the inspection page on a 700×700 drawing (not a test).

Targets (issue 15): the corrected re-run ≤ 2 s; the page ≤ 5 MB, written in ≤ 2 s.

1. A 700×700 drawing — ``../shared/data/drawings/clean/kitten.png`` resized, or the bundled example
   scaled up when ``../shared`` is absent — is vectorised once into a fresh store (``polyvec``,
   in-process scheduler).
2. A junction is added in the middle of the longest final curve (``<stem>.keypoints.json`` beside the
   input) and ``polyvec`` re-runs: the batch's wall time (what the engine spends: keypoint_edits,
   topology, flow, select, export) and the whole command's (with Python's start-up and imports).
3. ``write_page`` draws the page of the corrected run: its time and size; then ``polyvec-inspect
   page`` as a command.

Usage::

    python tests/benchmarks/bench_inspect.py [IMAGE]
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
DEFAULT = REPO.parent / "shared" / "data" / "drawings" / "clean" / "kitten.png"
SIZE = 700


def _drawing(src: Path | None, out: Path) -> Path:
    from PIL import Image

    if src is not None and src.is_file():
        img = Image.open(src).convert("L")
    else:
        sys.path.insert(0, str(REPO))
        from stages.synthetic import example_drawing

        import io

        img = Image.open(io.BytesIO(example_drawing().png_bytes())).convert("L")
    img.resize((SIZE, SIZE), Image.LANCZOS).save(out)
    return out


def _polyvec(*args: str, cwd: Path) -> tuple[float, float, str]:
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "pipeline.cli", *args], cwd=cwd, capture_output=True, text=True,
                       env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO)})
    wall = time.perf_counter() - t0
    if r.returncode:
        raise SystemExit(r.stderr[-3000:])
    m = re.search(r"1 image\(s\) in ([0-9.]+) s", r.stderr)
    return wall, float(m.group(1)) if m else float("nan"), r.stderr


def main(argv: list[str]) -> int:
    """Run the benchmark and print its numbers."""
    src = Path(argv[0]) if argv else DEFAULT
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        img = _drawing(src, work / "drawing.png")
        print(f"drawing: {src if src.is_file() else 'bundled example'} resized to {SIZE}×{SIZE}")
        wall, batch, _ = _polyvec(f"input={img}", "runtime.cluster=sync", cwd=work)
        print(f"first run (all stages)           : {batch:6.2f} s batch, {wall:6.2f} s command")
        curves = json.loads((work / "out" / "drawing.json").read_text())["curves"]
        longest = max(curves, key=lambda c: len(c["points"]))
        x, y = longest["points"][len(longest["points"]) // 2]
        edits = {"format": "polyvec-keypoint-edits", "version": 1, "width": SIZE, "height": SIZE,
                 "added": [{"x": round(x, 1), "y": round(y, 1), "type": "junction"}]}
        (work / "drawing.keypoints.json").write_text(json.dumps(edits))
        wall, batch, log = _polyvec(f"input={img}", cwd=work)
        rows = [[c.strip() for c in ln.split("│")[1:-1]] for ln in log.splitlines() if ln.startswith("│")]
        recomputed = [f"{r[0]} {float(r[5]):.2f} s" for r in rows if r[1] == "1"]
        print(f"corrected re-run (junction added): {batch:6.2f} s batch, {wall:6.2f} s command "
              f"(target ≤ 2 s); recomputed: {', '.join(recomputed)}")
        reused = re.search(r"flow: \d+ of \d+ paths reused[^\n]*", log)
        if reused:
            print(f"                                   {reused.group(0)}")
        sys.path.insert(0, str(REPO))
        from pipeline.engine.lookup import latest_keys
        from pipeline.page import write_page
        from pipeline.engine.store import ArtifactStore

        store = ArtifactStore(str(work / "artifacts"))
        keys = latest_keys(store, img)
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            page = write_page(store, img, work / "drawing.html", keys)
            times.append(time.perf_counter() - t0)
        size = page.stat().st_size
        print(f"page: {size / 1e6:.2f} MB (target ≤ 5 MB), written in {np.median(times):.2f} s "
              f"(median of 3; target ≤ 2 s)")
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "pipeline.inspect", "--store", str(work / "artifacts"), "page",
                        str(img), "-o", str(work / "cmd.html")], check=True, capture_output=True, cwd=work)
        print(f"`polyvec-inspect page` command   : {time.perf_counter() - t0:6.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
