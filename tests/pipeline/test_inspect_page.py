"""The inspection page and keypoint corrections, end to end: the page writer, the CLI's pick-up of
``<stem>.keypoints.json``, the README's commands, and a round trip through a real (headless) browser.

One store is built once for the module (the bundled example, in-process scheduler); every test
works on its own copy of the drawing (same bytes, so the same cached artifacts).
"""

from __future__ import annotations

import json
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import REPO, run_cli
from tests.pipeline.cdp import chromium_path

needs_chromium = pytest.mark.skipif(
    chromium_path() is None,
    reason="chromium is not installed (Debian package `chromium`; .ci/run installs it with apt-get)")

LAYERS = ("drawing", "band", "h1", "hclass", "field", "graph", "candidates", "selected", "curves", "ends")
RERUN = {"keypoint_edits", "topology", "flow", "select", "export"}


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A folder with ``out/polyvec-example.png`` and a store holding all its artifacts."""
    work = tmp_path_factory.mktemp("page")
    r = run_cli("runtime.cluster=sync", cwd=work)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "reused from earlier runs" not in r.stderr   # a first run reuses nothing and says nothing
    return work


def _copy_image(work: Path, name: str) -> Path:
    d = work / name
    d.mkdir()
    img = d / "polyvec-example.png"
    shutil.copy(work / "out" / "polyvec-example.png", img)
    return img


def _written_after(work: Path, image: Path, t0: float) -> set[str]:
    from pipeline.engine.lookup import artifacts_of
    from pipeline.engine.store import ArtifactStore

    rows = artifacts_of(ArtifactStore(str(work / "artifacts")), str(image))
    return {stage for stage, _, m in rows if m.get("written_at", 0) >= t0}


def _curve_ends(svg_json: Path) -> np.ndarray:
    curves = json.loads(svg_json.read_text())["curves"]
    return np.array([p for c in curves for p in (c["points"][0], c["points"][-1])], float)


def test_page_has_every_layer_and_stays_small(work):
    r = run_cli("page", "out/polyvec-example.png", "-o", "pages/example.html", cwd=work, module="pipeline.inspect")
    assert r.returncode == 0, r.stderr
    page = work / "pages" / "example.html"
    text = page.read_text()
    for layer in LAYERS:
        assert f'id="layer-{layer}"' in text, layer
        assert f'id="toggle-{layer}"' in text, layer
    assert 'id="save"' in text and 'id="edits-json"' in text
    # self-contained: no URL outside the file (SVG namespace aside), images embedded
    urls = set(re.findall(r'(?:src|href)="([^"]+)"', text))
    assert urls and all(u.startswith("data:image/png;base64,") for u in urls), urls
    assert page.stat().st_size < 1_000_000
    # the side panel: every stage with its key and seconds, the counts
    for stage in ("prep", "keypoints", "keypoint_edits", "field", "extension", "graph", "topology", "flow", "select",
                  "export"):
        assert f"<tr><td>{stage}</td>" in text
    assert '"keypoints"' in text and "curves" in text


def test_runtime_pages_writes_one_page_per_drawing(work):
    r = run_cli("runtime.cluster=sync", "runtime.pages=true", cwd=work)
    assert r.returncode == 0, r.stderr
    assert (work / "out" / "polyvec-example.html").is_file()
    assert "wrote out/polyvec-example.html" in r.stderr


def test_edits_beside_the_input_are_picked_up_and_rerun_only_topology_on(work):
    img = _copy_image(work, "cli")
    edits = img.with_name("polyvec-example.keypoints.json")
    edits.write_text(json.dumps({"format": "polyvec-keypoint-edits", "version": 1,
                                 "added": [{"x": 40.0, "y": 150.0, "type": "junction"}]}))
    t0 = time.time()
    r = run_cli(f"input={img}", "output=cli/out", cwd=work)
    assert r.returncode == 0, r.stderr
    assert f"keypoint edits: {edits} for {img} (found beside the input)" in r.stderr
    assert _written_after(work, img, t0) == RERUN
    # the flow reused the paths the edit did not touch, and says so
    reused = re.search(r"flow: (\d+) of (\d+) paths reused from earlier runs", r.stderr)
    assert reused and 0 < int(reused.group(1)) < int(reused.group(2)), r.stderr[-1500:]
    ends = _curve_ends(work / "cli" / "out" / "polyvec-example.json")
    assert np.hypot(*(ends - [40.0, 150.0]).T).min() < 1.0, "no curve ends at the added junction"
    before = _curve_ends(work / "out" / "polyvec-example.json")
    assert np.hypot(*(before - [40.0, 150.0]).T).min() > 10.0
    # the page of the drawing now draws the corrected run: the added junction is an edit on it
    r = run_cli("page", str(img), "-o", str(img.with_suffix(".html")), cwd=work, module="pipeline.inspect")
    assert r.returncode == 0, r.stderr
    assert '{"x": 40.0, "y": 150.0, "orig": 0, "cur": 3}' in img.with_suffix(".html").read_text()


def test_malformed_edits_are_one_error_line(work):
    img = _copy_image(work, "bad")
    edits = img.with_name("polyvec-example.keypoints.json")
    edits.write_text('{"added": [{"x": 3, "y": 4, "type": "tee"}]}')
    r = run_cli(f"input={img}", "output=bad/out", cwd=work)
    assert r.returncode == 2
    assert r.stderr.strip() == (f"polyvec: error: keypoint edits {edits}: added[0]: type must be endpoint, "
                                "junction or corner (or 1, 3, 5), got 'tee'")
    edits.write_text("{not json")
    r = run_cli(f"input={img}", "output=bad/out", cwd=work)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "not JSON" in r.stderr


def test_the_readme_commands_run(work):
    """Every command of the README's section on the page and keypoint corrections, as written."""
    readme = (REPO / "README.md").read_text()
    section = readme.split("## Correcting keypoints on the inspection page", 1)[1].split("\n## ", 1)[0]
    block = section.split("```bash", 1)[1].split("```", 1)[0]
    commands = [ln.split("#", 1)[0].strip() for ln in block.splitlines() if ln.split("#", 1)[0].strip()]
    assert len(commands) >= 4
    d = work / "readme"
    d.mkdir()
    (d / "out").mkdir()
    shutil.copy(work / "out" / "polyvec-example.png", d / "out" / "polyvec-example.png")
    fix = {"format": "polyvec-keypoint-edits", "version": 1, "added": [{"x": 180.0, "y": 150.0, "type": "junction"}]}
    (d / "out" / "polyvec-example.keypoints.json").write_text(json.dumps(fix))
    (d / "fix.keypoints.json").write_text(json.dumps(fix))
    shutil.copytree(work / "artifacts", d / "artifacts")
    for cmd in commands:
        prog, *args = cmd.split()
        module = {"polyvec": "pipeline.launch", "polyvec-inspect": "pipeline.inspect"}[prog]
        r = run_cli(*args, cwd=d, module=module)
        assert r.returncode == 0, f"{cmd}: {r.stderr[-1500:]}"
    assert (d / "out" / "polyvec-example.html").is_file()


# -- a real browser ----------------------------------------------------------------------------
@needs_chromium
def test_browser_round_trip_toggle_add_a_junction_save_and_rerun(work, tmp_path):
    pytest.importorskip("websocket", reason="websocket-client is not installed (the `test` extra)")
    from tests.pipeline.cdp import Browser
    img = _copy_image(work, "browser")
    r = run_cli("page", str(img), "-o", str(img.with_suffix(".html")), cwd=work, module="pipeline.inspect")
    assert r.returncode == 0, r.stderr
    downloads = tmp_path / "downloads"
    downloads.mkdir()
    browser = Browser()
    try:
        browser.browser_command("Browser.setDownloadBehavior", behavior="allow", downloadPath=str(downloads))
        browser.open(img.with_suffix(".html").resolve().as_uri())
        # toggle a layer on: the traced graph shows
        assert browser.eval("getComputedStyle(document.getElementById('layer-graph')).display") == "none"
        browser.click_selector("#toggle-graph")
        assert browser.eval("getComputedStyle(document.getElementById('layer-graph')).display") != "none"
        # zoom to 4× around the right wall, then add a junction there by a click
        browser.eval("polyvecPage.setView(150, 120, 75)")
        browser.click_selector("#add-t3")
        x, y = browser.eval("(() => {const p = polyvecPage.toScreen(180.2, 150); return [p.x, p.y]})()")
        n0 = browser.eval("polyvecPage.points.length")
        browser.click(x, y)
        assert browser.eval("polyvecPage.points.length") == n0 + 1
        browser.click_selector("#save")
        target = downloads / "polyvec-example.keypoints.json"
        deadline = time.time() + 20
        while not target.is_file() and time.time() < deadline:
            time.sleep(0.1)
        assert target.is_file(), f"no download in {list(downloads.iterdir())}"
        shown = json.loads(browser.eval("document.getElementById('edits-json').value"))
    finally:
        browser.close()
    saved = json.loads(target.read_text())
    assert saved == shown
    assert saved["removed"] == [] and saved["retyped"] == []
    (added,) = saved["added"]
    assert added["type"] == "junction" and abs(added["x"] - 180.2) < 0.6 and abs(added["y"] - 150) < 0.6
    # the download goes beside the drawing, and the CLI re-run takes it
    shutil.copy(target, img.with_name(target.name))
    t0 = time.time()
    r = run_cli(f"input={img}", "output=browser/out", cwd=work)
    assert r.returncode == 0, r.stderr
    assert "found beside the input" in r.stderr
    assert _written_after(work, img, t0) == RERUN
    ends = _curve_ends(work / "browser" / "out" / "polyvec-example.json")
    before = _curve_ends(work / "out" / "polyvec-example.json")
    at = np.array([added["x"], added["y"]])
    assert np.hypot(*(ends - at).T).min() < 1.0 < 10.0 < np.hypot(*(before - at).T).min()


def _thin_drawing(path):
    """240 x 200, 1-px aliased ellipse and line: prep.supersample runs it at 2x."""
    from PIL import Image, ImageDraw

    img = Image.new("L", (240, 200), 255)
    d = ImageDraw.Draw(img)
    d.ellipse([20, 30, 220, 170], outline=110, width=1)
    d.line([(60, 100), (180, 110)], fill=110, width=1)
    img.save(path)


def _wide_drawing(path):
    """1001 x 803, a 16-px ellipse: prep.downsample runs it at 1/4 (251 x 201 internal pixels)."""
    from PIL import Image, ImageDraw

    big = Image.new("L", (2002, 1606), 255)
    ImageDraw.Draw(big).ellipse([200, 240, 1802, 1366], outline=0, width=32)
    big.resize((1001, 803), Image.LANCZOS).save(path)


def _drawing_on_a_sheet(path):
    """1200 x 1000, a 3-px ellipse in its lower right: prep.crop runs its ink's box (from (568, 368))."""
    from PIL import Image, ImageDraw

    img = Image.new("L", (1200, 1000), 255)
    ImageDraw.Draw(img).ellipse([600, 400, 840, 560], outline=0, width=3)
    img.save(path)


def _drawings_far_apart(path):
    """1600 x 1400, a 3-px rectangle top left and ellipse bottom right: prep.crop lays their boxes side by
    side, the ellipse's (from (1168, 1068)) at the mosaic's corner, the rectangle's below it."""
    from PIL import Image, ImageDraw

    img = Image.new("L", (1600, 1400), 255)
    d = ImageDraw.Draw(img)
    d.rectangle([100, 100, 260, 220], outline=0, width=3)
    d.ellipse([1200, 1100, 1440, 1260], outline=0, width=3)
    img.save(path)


@pytest.mark.parametrize("draw, size, scale, on_page, in_drawing, near, said", [
    # the ellipse's top at (120, 30.5) drawing px is at (240, 61) on the 2x page
    (_thin_drawing, (240, 200), 2.0, (240, 61), (120.0, 30.5), 1.5, "working at 2x resolution"),
    # the ellipse's top at (500.5, 128) drawing px is at (125.125, 32) on the 1/4 page; the old page
    # divided its own size by the scale and saved edits for a 1004 x 804 drawing
    (_wide_drawing, (1001, 803), 0.25, (125.125, 32), (500.5, 128.0), 3.0, "working at 1/4 resolution"),
    # the ellipse's top at (720, 401) drawing px is at (152, 33) on the page of its ink's box from (568, 368)
    (_drawing_on_a_sheet, (1200, 1000), 1.0, (152, 33), (720.0, 401.0), 1.5, "box at (568, 368)"),
    # the ellipse's top at (1320, 1101) drawing px is at (152, 33) on the page of the mosaic; a page that
    # added its origin (0, 0) saved it there
    (_drawings_far_apart, (1600, 1400), 1.0, (152, 33), (1320.0, 1101.0), 1.5, "2 parts far apart on the page"),
], ids=["supersampled", "downsampled", "cropped", "mosaic"])
@needs_chromium
def test_page_of_a_resampled_drawing_saves_edits_in_the_drawings_pixels(tmp_path, draw, size, scale, on_page,
                                                                        in_drawing, near, said):
    """Thin strokes run at 2x (prep.supersample), wide ones at 1/4 (prep.downsample): the page shows
    that resolution, and says so in its side panel (as the console did: why the page is not the
    drawing as it came); the edits it saves are for the drawing, in its pixels, and the re-run takes them."""
    pytest.importorskip("websocket", reason="websocket-client is not installed (the `test` extra)")
    from tests.pipeline.cdp import Browser
    draw(tmp_path / "drawing.png")
    r = run_cli("drawing.png", "runtime.cluster=sync", "runtime.pages=true", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    page = next(tmp_path.rglob("drawing*.html"))
    browser = Browser()
    try:
        browser.open(page.resolve().as_uri())
        assert browser.eval("polyvecPage.data.scale") == scale
        assert said in browser.eval("document.getElementById('notes').textContent")
        browser.eval(f"polyvecPage.points.push({{x: {on_page[0]}, y: {on_page[1]}, orig: 0, cur: 3}})")
        saved = browser.eval("polyvecPage.edits()")
    finally:
        browser.close()
    assert (saved["width"], saved["height"]) == size
    assert saved["added"] == [{"x": in_drawing[0], "y": in_drawing[1], "type": "junction"}]
    (tmp_path / "drawing.keypoints.json").write_text(json.dumps(saved))
    r = run_cli("drawing.png", "runtime.cluster=sync", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "found beside the input" in r.stderr
    ends = _curve_ends(tmp_path / "out" / "drawing.json")
    assert np.hypot(*(ends - in_drawing).T).min() < near    # the ellipse now has curve ends at the junction
