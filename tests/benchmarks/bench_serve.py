"""Benchmark: ``polyvec serve``'s round trips on a 700×700 drawing, in headless Chromium (not a test).

Target (issue 56): from the click to the redrawn curves ≤ 1.5 s, for a keypoint edit and for a λ change.

1. A 700×700 drawing — ``../shared/data/drawings/clean/kitten.png`` resized, or the bundled example
   scaled up when ``../shared`` is absent — in a fresh folder; ``polyvec serve`` on it with a fresh
   store, and its first run awaited.
2. The drawing's page in headless Chromium. Five times: a junction added by a click on the middle of
   a different final curve (keypoint_edits → topology → flow → select → export re-run), then five λ
   values set on the slider (flow → select → export).
3. Each round trip is timed in the page (``polyvecLive.seconds``: from the click's handler, which posts
   the edit, to the new curve layers in the page) and from here (the click sent over the DevTools
   protocol until the page says it redrew, polled every 20 ms), with the server's own part (its job:
   the batch and the layers); each is printed, then the medians.

Usage::

    python tests/benchmarks/bench_serve.py [IMAGE]
"""

from __future__ import annotations

import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
DEFAULT = REPO.parent / "shared" / "data" / "drawings" / "clean" / "kitten.png"
SIZE = 700
REPEATS = 5
LAMBDAS = (1.0, 1.5, 2.0, 2.5, 4.0)


def _drawing(src: Path, out: Path) -> Path:
    import io

    from PIL import Image

    if src.is_file():
        img = Image.open(src).convert("L")
    else:
        from stages.synthetic import example_drawing

        img = Image.open(io.BytesIO(example_drawing().png_bytes())).convert("L")
    img.resize((SIZE, SIZE), Image.LANCZOS).save(out)
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _listing(base: str) -> list[dict]:
    with urllib.request.urlopen(base + "/api/drawings", timeout=10) as r:
        return json.load(r)["drawings"]


def _timed(browser, act, redraws: int) -> tuple[float, float, float]:
    """Run ``act`` (a click, a slider move); (seconds in the page, seen from here, of the server's job)."""
    t0 = time.perf_counter()
    act()
    while browser.eval("polyvecLive.redraws") < redraws:
        status = browser.eval("polyvecLive.status")
        if status and not status.startswith(("running", "redrawn")):
            raise SystemExit(f"the page says: {status}")
        time.sleep(0.02)
    seen = time.perf_counter() - t0
    return browser.eval("polyvecLive.seconds"), seen, browser.eval("polyvecLive.serverSeconds")


def main(argv: list[str]) -> int:
    """Run the benchmark and print its numbers."""
    from tests.pipeline.cdp import Browser, chromium_path

    if chromium_path() is None:
        raise SystemExit("chromium is not installed")
    src = Path(argv[0]) if argv else DEFAULT
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        (work / "drawings").mkdir()
        _drawing(src, work / "drawings" / "drawing.png")
        print(f"drawing: {src if src.is_file() else 'bundled example'} resized to {SIZE}×{SIZE}")
        port = _free_port()
        base = f"http://127.0.0.1:{port}"
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "pipeline.launch", "serve", "drawings", "--port", str(port),
                                 f"store.path={work / 'store'}"], cwd=work, env=dict(os.environ, PYTHONUNBUFFERED="1"))
        browser = None
        try:
            while True:
                try:
                    (d,) = _listing(base)
                    if d["state"] in ("done", "failed"):
                        break
                except OSError:
                    pass
                if proc.poll() is not None:
                    raise SystemExit("polyvec serve stopped")
                time.sleep(0.2)
            if d["state"] == "failed":
                raise SystemExit(f"the first run failed: {d['error']}")
            print(f"first run (server start to done): {time.perf_counter() - t0:.2f} s")
            browser = Browser()
            t0 = time.perf_counter()
            browser.open(base + "/d/drawing.png", ready="window.polyvecLive !== undefined", timeout=120)
            print(f"page load: {time.perf_counter() - t0:.2f} s")
            # the middle vertices of the longest final curves: points on strokes, one per edit
            points = browser.eval("""(() => Array.from(document.querySelectorAll('#layer-curves path'))
                .map(p => p.getAttribute('d').replace('M', '').split(' ').map(Number))
                .sort((a, b) => b.length - a.length).slice(0, %d)
                .map(n => {const k = Math.floor(n.length / 4) * 2; return [n[k], n[k + 1]]}))()""" % REPEATS)
            browser.eval("document.getElementById('add-t3').checked = true")
            edit, lam, redraws = [], [], 0
            for x, y in points:
                redraws += 1
                sx, sy = browser.eval(f"(() => {{const p = polyvecPage.toScreen({x}, {y}); return [p.x, p.y]}})()")
                edit.append(_timed(browser, lambda: browser.click(sx, sy), redraws))
                print(f"keypoint edit {redraws}: {edit[-1][0]:.2f} s in the page, {edit[-1][1]:.2f} s seen from here "
                      f"(the server's run {edit[-1][2]:.2f} s)")
            for value in LAMBDAS:
                redraws += 1
                js = ("(() => {const s = document.getElementById('lam'); s.value = %r;"
                      "s.dispatchEvent(new Event('input')); s.dispatchEvent(new Event('change'))})()" % value)
                lam.append(_timed(browser, lambda: browser.eval(js), redraws))
                print(f"λ = {value}: {lam[-1][0]:.2f} s in the page, {lam[-1][1]:.2f} s seen from here "
                      f"(the server's run {lam[-1][2]:.2f} s)")
            for name, times in (("keypoint edit", edit), ("λ change", lam)):
                print(f"median {name}: {statistics.median(t[0] for t in times):.2f} s in the page, "
                      f"{statistics.median(t[1] for t in times):.2f} s seen from here (target ≤ 1.5 s)")
        finally:
            if browser is not None:
                browser.close()
            proc.send_signal(signal.SIGINT)
            proc.wait(30)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
