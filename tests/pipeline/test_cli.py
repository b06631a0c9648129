"""The command lines as a user runs them, in subprocesses."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest

from pipeline.engine.registry import STAGES
from stages import synthetic


def test_default_run_on_the_bundled_example(tmp_path, cli):
    """`polyvec` with no input vectorises the generated example drawing; a rerun is all cache hits. The
    curves JSON beside the SVG has one curve per line."""
    proc = cli(cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "out" / "polyvec-example.png").exists()
    text = (tmp_path / "out" / "polyvec-example.json").read_text()
    curves = json.loads(text)["curves"]
    assert curves and [json.loads(line.strip().rstrip(",")) for line in text.splitlines()[2:2 + len(curves)]] == curves
    assert (tmp_path / "artifacts" / "prep").is_dir()
    assert "computed" in proc.stderr
    assert not list(tmp_path.glob("*.log")), "the run left a Hydra log file in the working directory"
    if (tmp_path / "artifacts" / "export").is_dir():
        assert (tmp_path / "out" / "polyvec-example.svg").exists()
    again = cli(cwd=tmp_path)
    assert again.returncode == 0
    table = [line for line in again.stderr.splitlines() if line.startswith("│")]
    assert table and all(line.split("│")[2].strip() == "0" for line in table), again.stderr


def test_batch_with_a_corrupt_file_finishes_and_exits_nonzero(tmp_path, cli):
    folder = tmp_path / "in"
    folder.mkdir()
    (folder / "a.png").write_bytes(synthetic.line(size=40).png_bytes())
    (folder / "b.png").write_bytes(b"GIF89a broken")
    (folder / "c.png").write_bytes(synthetic.vee(size=48).png_bytes())
    proc = cli(f"input={folder}", "runtime.until=field", "runtime.cluster=sync", cwd=tmp_path)
    assert proc.returncode == 1
    assert "b.png: prep:" in proc.stderr
    assert "Traceback" not in proc.stderr
    # the two good images went all the way
    assert len(list((tmp_path / "artifacts" / "field").glob("*/*"))) == 2


def test_missing_input_is_one_line(tmp_path, cli):
    proc = cli("input=does/not/exist.png", cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.strip() == "polyvec: error: input not found: does/not/exist.png"


def test_multirun_shares_one_store(tmp_path, cli):
    img = tmp_path / "line.png"
    img.write_bytes(synthetic.line(size=40).png_bytes())
    proc = cli("-m", f"input={img}", "field.beta=9,11", "runtime.until=field", "runtime.cluster=sync",
                   cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert len(list((tmp_path / "artifacts" / "prep").glob("*/*"))) == 1
    assert len(list((tmp_path / "artifacts" / "field").glob("*/*"))) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["artifacts", "line.png"], "the sweep left files behind"


def test_inspect_list_show_render(tmp_path, cli):
    img = tmp_path / "vee.png"
    img.write_bytes(synthetic.vee(size=48).png_bytes())
    assert cli(f"input={img}", "runtime.until=extension", "runtime.cluster=sync", cwd=tmp_path).returncode == 0
    listed = cli("list", str(img), cwd=tmp_path, module="pipeline.inspect")
    assert listed.returncode == 0 and "field" in listed.stdout and "prep" in listed.stdout
    shown = cli("show", "field", "--image", str(img), cwd=tmp_path, module="pipeline.inspect")
    assert shown.returncode == 0
    manifest = json.loads(shown.stdout[: shown.stdout.index("\n}\n") + 2])
    assert manifest["stage"] == "field" and "beta" in manifest["config"]
    for stage in ("prep", "field", "extension"):
        out = tmp_path / f"{stage}.png"
        r = cli("render", str(img), stage, "-o", str(out), cwd=tmp_path, module="pipeline.inspect")
        assert r.returncode == 0, r.stderr
        from PIL import Image

        assert Image.open(out).size[0] >= 48
    missing = cli("show", "graph", "ffff", cwd=tmp_path, module="pipeline.inspect")
    assert missing.returncode == 2 and "no graph artifact" in missing.stderr


def test_sparse_drawing_runs_through_prep(tmp_path, cli):
    """One 2-px line on a 600×600 page (0.3 % ink) is vectorised, not refused as blank."""
    import numpy as np
    from PIL import Image

    g = np.full((600, 600), 255, np.uint8)
    g[300:302, 60:540] = 0
    Image.fromarray(g, "L").save(tmp_path / "one-line.png")
    proc = cli("input=one-line.png", "runtime.until=prep", "runtime.cluster=sync", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "blank" not in proc.stderr


def _resampled_run(tmp_path, cli, name: str, img, note: str, *overrides: str):
    """Run the CLI on ``img`` saved as ``name`` (with ``overrides``): its exported curves (drawing
    pixels) after checking the console note and that the SVG's viewBox is the drawing's size."""
    import json

    import numpy as np

    img.save(tmp_path / name)
    proc = cli(name, "runtime.cluster=sync", *overrides, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert note in proc.stderr
    stem = name.rsplit(".", 1)[0]
    assert f'viewBox="0 0 {img.width} {img.height}"' in (tmp_path / "out" / f"{stem}.svg").read_text()
    curves = json.loads((tmp_path / "out" / f"{stem}.json").read_text())["curves"]
    return curves, np.concatenate([np.asarray(c["points"]) for c in curves])


@pytest.mark.slow
def test_thin_aliased_drawing_runs_at_a_higher_resolution_and_comes_back_in_its_pixels(tmp_path, cli):
    """1-px aliased ink (issue #17 item 5): an ellipse and a line give two curves, not a dozen pieces."""
    import numpy as np
    from PIL import Image, ImageDraw

    img = Image.new("L", (240, 200), 255)
    d = ImageDraw.Draw(img)
    d.ellipse([20, 30, 220, 170], outline=110, width=1)
    d.line([(60, 100), (180, 110)], fill=110, width=1)
    curves, pts = _resampled_run(tmp_path, cli, "thin ellipse.png", img, "working at 2x resolution")
    assert len(curves) == 2   # without prep.supersample: 9 pieces
    # On the drawing's ellipse (centre (120, 100), semi-axes 100, 70) or line, in its pixels.
    on_ellipse = np.abs(np.hypot((pts[:, 0] - 120.5) / 100.5, (pts[:, 1] - 100.5) / 70.5) - 1) < 0.03
    on_line = (pts[:, 0] > 55) & (pts[:, 0] < 185) & (np.abs(pts[:, 1] - (100.5 + (pts[:, 0] - 60) / 12)) < 2)
    assert (on_ellipse | on_line).mean() > 0.98


@pytest.mark.slow
def test_wide_strokes_run_at_a_lower_resolution_and_come_back_in_their_pixels(tmp_path, cli):
    """A high-resolution scan (issue #14): 16-px strokes are vectorised at 1/4 and mapped back."""
    import numpy as np
    from PIL import Image, ImageDraw

    big = Image.new("L", (2002, 1606), 255)
    d = ImageDraw.Draw(big)
    d.ellipse([200, 240, 1802, 1366], outline=0, width=32)
    d.line([(600, 803), (1402, 903)], fill=0, width=32)
    img = big.resize((1001, 803), Image.LANCZOS)
    curves, pts = _resampled_run(tmp_path, cli, "wide scan.png", img, "working at 1/4 resolution")
    assert len(curves) == 2
    # On the ellipse's centre line (centre (500.5, 401.5), semi-axes 392.5, 273.5 after the 16-px
    # stroke drawn inward; within ~1.5 px) or on the line, in the drawing's pixels.
    r = np.hypot((pts[:, 0] - 500.5) / 392.5, (pts[:, 1] - 401.5) / 273.5)
    on_ellipse = np.abs(r - 1) < 0.006
    on_line = (pts[:, 0] > 290) & (pts[:, 0] < 711) & (np.abs(pts[:, 1] - (401.5 + (pts[:, 0] - 300) / 8)) < 3)
    assert (on_ellipse | on_line).mean() > 0.98
    assert all(abs(c["width"] - 16) < 2 for c in curves)      # widths in the drawing's pixels too


def _ellipse_and_line():
    """240×200: a 3-px ellipse and a line across it, the sketch the page tests put on sheets."""
    from PIL import Image, ImageDraw

    alone = Image.new("L", (240, 200), 255)
    d = ImageDraw.Draw(alone)
    d.ellipse([20, 30, 220, 170], outline=0, width=3)
    d.line([(60, 100), (180, 110)], fill=0, width=3)
    return alone


@pytest.mark.slow
def test_a_drawing_on_a_large_page_is_vectorised_on_its_ink_and_comes_back_in_the_pages_pixels(tmp_path, cli):
    """A sketch on a scanned sheet with three specks of dust far from it (issue #14): the later stages
    work on the ink's box (prep.crop; the specks left out, and said), and the curves are where they are
    on the page, as those of the same drawing alone, moved. The page is over ``prep.max_pixels`` (set
    low here, as a 600-dpi sheet is over the default): that bounds the box, not the page."""
    from PIL import Image, ImageDraw

    alone = _ellipse_and_line()
    page = Image.new("L", (1700, 1200), 255)
    page.paste(alone, (900, 600))
    for cx, cy in [(100, 100), (1600, 150), (300, 1100)]:
        ImageDraw.Draw(page).ellipse([cx - 4, cy - 4, cx + 4, cy + 4], fill=0)
    curves, pts = _resampled_run(tmp_path, cli, "sheet.png", page,
                                 "working on its 265×205 box at (888, 598), 3 small marks far from it left out",
                                 "prep.max_pixels=1000000")
    (tmp_path / "out").rename(tmp_path / "out_page")
    ref, ref_pts = _resampled_run(tmp_path, cli, "alone.png", alone, "")
    assert len(curves) == len(ref) == 2
    from scipy.spatial import cKDTree

    moved = pts - (900, 600)
    assert cKDTree(ref_pts).query(moved)[0].max() < 0.5 and cKDTree(moved).query(ref_pts)[0].max() < 0.5


@pytest.mark.slow
def test_a_phone_photo_of_a_sheet_at_an_angle_is_vectorised_flat(tmp_path, cli):
    """A JPEG phone photo of a sketch on a sheet turned by 12° and leaned back by 30°, the desk round it
    over most of the picture: prep cuts the sheet out and flattens it (said on the console; the desk made
    the whole photo read as light strokes on dark paper before), and the SVG is the sheet, upright and
    at its proportions: the curves lie on the sketch's strokes where they are on the sheet, and cover
    them; nothing on the desk or along the sheet's edges."""
    import numpy as np
    from PIL import Image
    from scipy.ndimage import distance_transform_edt
    from scipy.spatial import cKDTree

    from photos import photographed

    sheet = Image.new("L", (600, 800), 255)
    sheet.paste(_ellipse_and_line(), (180, 300))
    photo, _ = photographed(sheet, 12, (480, 640), tilt=30)
    photo.save(tmp_path / "photo of my sketch.jpg", quality=88)
    proc = cli("photo of my sketch.jpg", "runtime.cluster=sync", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "a sheet on a darker ground" in proc.stderr and "flattened" in proc.stderr, proc.stderr
    assert "inverted" not in proc.stderr
    svg = (tmp_path / "out" / "photo of my sketch.svg").read_text()
    width, height = (float(svg.split(f'{key}="')[1].split('"')[0]) for key in ("width", "height"))
    assert abs(width / height - 0.75) < 0.01 * 0.75, (width, height)
    curves = json.loads((tmp_path / "out" / "photo of my sketch.json").read_text())["curves"]
    pts = np.concatenate([np.asarray(c["points"]) for c in curves]) * [600 / width, 800 / height]
    ink = np.asarray(sheet) < 128
    assert 2 <= len(curves) <= 6
    to_ink = distance_transform_edt(~ink)
    assert to_ink[pts[:, 1].astype(int), pts[:, 0].astype(int)].max() <= 3
    rows, cols = np.nonzero(ink)
    assert cKDTree(pts).query(np.c_[cols + 0.5, rows + 0.5])[0].max() < 4


def test_a_folder_of_iphone_heic_photos_is_vectorised(tmp_path, cli):
    """A folder as a phone's photos come off it (``IMG_0042.HEIC``, upper case): found and read through
    pillow-heif (the folder was "no image files", a HEIC named alone "not an image")."""
    pillow_heif = pytest.importorskip("pillow_heif", reason="pillow-heif is not installed (the `heic` extra)")
    pillow_heif.register_heif_opener()
    (tmp_path / "camera roll").mkdir()
    _ellipse_and_line().convert("RGB").save(tmp_path / "camera roll" / "IMG_0042.HEIC", "HEIF", quality=90)
    proc = cli("camera roll", "runtime.cluster=sync", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "wrote out/IMG_0042.svg" in proc.stderr
    assert json.loads((tmp_path / "out" / "IMG_0042.json").read_text())["curves"]


@pytest.mark.slow
def test_drawings_far_apart_on_a_page_are_vectorised_side_by_side_and_come_back_in_place(tmp_path, cli):
    """Two sketches in opposite corners of a sheet (issue #14): their common box keeps most of the page,
    so prep lays their boxes side by side (a mosaic, said on the console), and each one's curves come
    back where it is on the page, as those of the same drawing alone, moved. The page is over
    ``prep.max_pixels`` (set low here): the mosaic is not."""
    import numpy as np
    from PIL import Image, ImageDraw

    alone = _ellipse_and_line()
    page = Image.new("L", (1700, 1400), 255)
    page.paste(alone, (100, 80))
    d = ImageDraw.Draw(page)
    d.polygon([(1320, 1300), (1420, 1120), (1520, 1300)], outline=0, width=3)
    curves, pts = _resampled_run(tmp_path, cli, "two sketches.png", page, "2 parts far apart on the page",
                                 "prep.max_pixels=1000000")
    (tmp_path / "out").rename(tmp_path / "out_page")
    ref, ref_pts = _resampled_run(tmp_path, cli, "alone.png", alone, "")
    from scipy.ndimage import distance_transform_edt
    from scipy.spatial import cKDTree

    first = pts[(pts[:, 0] < 850) & (pts[:, 1] < 700)] - (100, 80)
    assert cKDTree(ref_pts).query(first)[0].max() < 0.5 and cKDTree(first).query(ref_pts)[0].max() < 0.5
    # The triangle's curves run along its strokes, in the page's pixels, and cover them.
    second = pts[(pts[:, 0] > 850) & (pts[:, 1] > 700)]
    ink = np.asarray(page) < 128
    to_ink = distance_transform_edt(~ink)
    assert len(second) and to_ink[second[:, 1].astype(int), second[:, 0].astype(int)].max() <= 1.5
    rows, cols = np.nonzero(ink[700:, 850:])
    assert cKDTree(second).query(np.c_[cols + 850.5, rows + 700.5])[0].max() < 3


@pytest.mark.slow
def test_a_rotated_photo_and_a_multi_page_scan_come_out_as_a_viewer_shows_them(tmp_path, cli):
    """An EXIF orientation (phone photos, scanners' JPEGs) is applied: the SVG has the size and the
    curves the place a viewer shows; of a multi-page TIFF the first page is vectorised, and it says so."""
    import json

    import numpy as np
    from PIL import Image, ImageDraw

    (tmp_path / "in").mkdir()
    stored = Image.new("L", (300, 200), 255)   # an L as stored: down x = 50, then along y = 170
    d = ImageDraw.Draw(stored)
    d.line([(50, 30), (50, 170)], fill=0, width=5)
    d.line([(50, 170), (250, 170)], fill=0, width=5)
    exif = Image.Exif()
    exif[0x0112] = 6                            # "rotate 90° clockwise to display"
    stored.save(tmp_path / "in" / "photo.jpg", exif=exif, quality=95)
    pages = [Image.new("L", (200, 160), 255) for _ in range(3)]
    for k, page in enumerate(pages):
        ImageDraw.Draw(page).line([(20, 20 + 40 * k), (180, 80)], fill=0, width=4)
    pages[0].save(tmp_path / "in" / "scan.tif", save_all=True, append_images=pages[1:])
    proc = cli("in", "runtime.cluster=sync", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "3 pages (frames) in the file: the first is vectorised" in proc.stderr
    # Displayed, the photo is 200 × 300: stored (x, y) shows at (199 − y, x).
    assert 'viewBox="0 0 200 300"' in (tmp_path / "out" / "photo.svg").read_text()
    pts = np.concatenate([np.asarray(c["points"]) for c in
                          json.loads((tmp_path / "out" / "photo.json").read_text())["curves"]])
    across = (np.abs(pts[:, 1] - 50.5) < 2) & (pts[:, 0] > 24) & (pts[:, 0] < 175)
    down = (np.abs(pts[:, 0] - 29.5) < 2) & (pts[:, 1] > 45) & (pts[:, 1] < 256)
    assert (across | down).mean() > 0.97
    curves = json.loads((tmp_path / "out" / "scan.json").read_text())["curves"]
    assert len(curves) == 1 and np.asarray(curves[0]["points"])[:, 1].min() > 15   # page 1's line only


def _assert_the_same_curves(out, name, twin, count: int, tolerance_px: float) -> None:
    """``out/<name>.json`` and ``out/<twin>.json`` hold ``count`` curves each, pairwise the same curve:
    every point of one within ``tolerance_px`` of the other (paired by their first points)."""
    import numpy as np

    curves = [json.loads((out / f"{n}.json").read_text())["curves"] for n in (name, twin)]
    assert len(curves[0]) == len(curves[1]) == count
    for a, b in zip(*(sorted(c, key=lambda c: c["points"][0]) for c in curves)):
        pa, pb = np.asarray(a["points"]), np.asarray(b["points"])
        assert np.linalg.norm(pa[:, None] - pb[None], axis=2).min(axis=1).max() < tolerance_px


def test_chalk_on_a_blackboard_gives_the_curves_of_ink_on_paper(tmp_path, cli):
    """``prep.invert``: light strokes on dark paper (a photographed blackboard, a negative) and white
    line art on a transparent page give the curves of the same drawing in ink on white, and the console
    says the image was inverted."""
    import numpy as np
    from PIL import Image, ImageDraw

    img = Image.new("L", (160, 120), 255)
    d = ImageDraw.Draw(img)
    d.ellipse([20, 20, 80, 80], outline=0, width=3)
    d.line([(100, 20), (140, 100)], fill=0, width=3)
    (tmp_path / "in").mkdir()
    img.save(tmp_path / "in" / "paper.png")
    Image.fromarray((40 + (255 - np.asarray(img)) * 0.7).astype(np.uint8)).save(tmp_path / "in" / "board.png")
    art = np.full((120, 160, 4), 255, np.uint8)
    art[..., 3] = 255 - np.asarray(img)
    Image.fromarray(art, "RGBA").save(tmp_path / "in" / "lineart.png")
    proc = cli("in", "runtime.cluster=sync", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "board.png: prep: light strokes on dark paper" in proc.stderr and "paper.png: prep: light" not in proc.stderr
    assert "lineart.png: prep: light strokes on dark paper" in proc.stderr
    _assert_the_same_curves(tmp_path / "out", "board", "paper", count=2, tolerance_px=1.0)
    _assert_the_same_curves(tmp_path / "out", "lineart", "paper", count=2, tolerance_px=1.0)


@pytest.mark.slow
def test_a_photographed_sketch_with_a_shadow_comes_out_as_if_evenly_lit(tmp_path, cli):
    """``prep.lighting``: pencil strokes under a 40 % shadow give the curves of the evenly lit page
    (a loop, a zigzag joined through its corners, a line), and the console says the lighting was evened."""
    import numpy as np
    from PIL import Image, ImageDraw

    def page(shadow):
        img = Image.new("L", (420, 360), 235)
        d = ImageDraw.Draw(img)
        d.ellipse([40, 40, 200, 170], outline=150, width=3)
        d.line([(230, 60), (280, 160), (330, 60), (380, 160)], fill=150, width=3)
        d.line([(50, 280), (380, 240)], fill=150, width=3)
        y, x = np.mgrid[0:360, 0:420]
        a = np.asarray(img, np.float64) * (1.0 - shadow * (x / 420.0) * (0.4 + 0.6 * y / 360.0))
        return Image.fromarray(a.astype(np.uint8))

    (tmp_path / "in").mkdir()
    page(0.4).save(tmp_path / "in" / "photo.png")
    page(0.0).save(tmp_path / "in" / "scan.png")
    proc = cli("in", "runtime.cluster=sync", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "photo.png: prep: uneven lighting" in proc.stderr and "scan.png: prep: uneven" not in proc.stderr
    _assert_the_same_curves(tmp_path / "out", "photo", "scan", count=3, tolerance_px=1.5)


# What only computing needs: over a second of start-up that a run whose artifacts are all stored never pays.
HEAVY = ("numba", "scipy", "skimage", "torch", "dask", "distributed", "networkx", "pulp")

# `polyvec ARGS` in-process, writing the names in sys.modules to modules.json as it exits.
_LIST_MODULES_AT_EXIT = """
import atexit, json, runpy, sys
atexit.register(lambda: open("modules.json", "w").write(json.dumps(sorted(sys.modules))))
sys.argv[0] = "polyvec"
runpy.run_module("pipeline.launch", run_name="__main__")
"""


@pytest.mark.slow
def test_a_cached_run_imports_no_heavy_library(tmp_path, cli, monkeypatch):
    """A re-run whose artifacts are all stored imports no stage's code, nor numba, scipy, scikit-image,
    torch, dask, networkx or PuLP (issue 14: a fully cached run under a second); the same command line
    reads its config from the config cache and imports no Hydra either."""
    import subprocess
    import sys

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))   # the first run fills it
    (tmp_path / "vee.png").write_bytes(synthetic.vee(size=48).png_bytes())
    first = cli("input=vee.png", "runtime.cluster=sync", cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    again = subprocess.run([sys.executable, "-c", _LIST_MODULES_AT_EXIT, "input=vee.png", "runtime.cluster=sync"],
                           cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr[-2000:]
    table = [line for line in again.stderr.splitlines() if line.startswith("│")]
    assert len(table) == len(STAGES) and all(line.split("│")[2].strip() == "0" for line in table), again.stderr  # 0 computed
    assert (tmp_path / "out" / "vee.svg").exists()
    modules = json.loads((tmp_path / "modules.json").read_text())
    assert "pipeline.engine.config" in modules and "stages.flow" in modules     # the listing is there
    heavy = [m for m in modules if m.split(".")[0] in HEAVY or m.endswith(".stage") or ".keypoints.network" in m]
    assert heavy == [], "a cached run imported " + ", ".join(heavy)
    assert "hydra" not in modules, "a command line whose config is cached imported Hydra"


@pytest.mark.slow
def test_export_bezier_true_as_the_readme_spells_it(tmp_path, cli):
    """`export.bezier=true` (README) writes the Bézier SVG beside the polyline one."""
    (tmp_path / "vee.png").write_bytes(synthetic.vee(size=48).png_bytes())
    proc = cli("input=vee.png", "export.bezier=true", "runtime.cluster=sync", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert (tmp_path / "out" / "vee.svg").exists() and (tmp_path / "out" / "vee.bezier.svg").exists()
    # the summary names every file written, the Bézier SVG too (issue 18 item 14)
    assert "wrote out/vee.svg, out/vee.json, out/vee.bezier.svg" in proc.stderr.replace("\n", "")


def test_help_describes_polyvec(tmp_path, cli):
    """`polyvec --help` describes the tool, its stages and examples (not Hydra's generic help)."""
    proc = cli("--help", cwd=tmp_path)
    assert proc.returncode == 0
    assert "powered by Hydra" not in proc.stdout and "bench" not in proc.stdout.split("See also")[0]
    assert "Vectorise" in proc.stdout and "Examples" in proc.stdout
    for stage in STAGES:
        assert stage.name in proc.stdout
    assert not list(tmp_path.iterdir())


def test_help_into_a_closed_pipe_is_quiet(tmp_path):
    """`polyvec --help | head -1`: the reader may close before the help is written; no traceback."""
    import os
    import subprocess
    import sys

    read, write = os.pipe()
    os.close(read)                         # a reader that is already gone
    proc = subprocess.run([sys.executable, "-m", "pipeline.launch", "--help"], stdout=write, stderr=subprocess.PIPE,
                          text=True, timeout=60, cwd=tmp_path)
    os.close(write)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr


def test_plain_paths_with_odd_characters(tmp_path, cli):
    """Paths with ü ( , ✓ work as positional arguments and as input=, beside overrides."""
    folder = tmp_path / "my drawings (2024)"
    folder.mkdir()
    (folder / "cät,✓.png").write_bytes(synthetic.line(size=40).png_bytes())
    (tmp_path / "scans").mkdir()
    (tmp_path / "scans" / "vee.png").write_bytes(synthetic.vee(size=48).png_bytes())
    for args in (("scans/", "my drawings (2024)/cät,✓.png"), ("input=my drawings (2024)/cät,✓.png",)):
        proc = cli(*args, "runtime.until=prep", "runtime.cluster=sync", cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr
    assert len(list((tmp_path / "artifacts" / "prep").glob("*/*"))) == 2


def test_square_brackets_in_paths_are_printed_as_they_are(tmp_path, cli):
    """A file named ``a[v2].png`` in a folder ``t [bold]`` is said to be written as ``a[v2].svg`` (rich read
    ``[v2]`` as markup and dropped it), and a bad image at ``odd[/]bad.png`` is one error line, not
    rich's MarkupError traceback (``[/]`` closed nothing)."""
    (tmp_path / "t [bold]").mkdir()
    (tmp_path / "t [bold]" / "a[v2].png").write_bytes(synthetic.vee(size=48).png_bytes())
    (tmp_path / "t [bold]" / "odd[").mkdir()
    (tmp_path / "t [bold]" / "odd[" / "]bad.png").write_bytes(b"not an image")
    proc = cli("t [bold]/a[v2].png", "t [bold]/odd[/]bad.png", "runtime.cluster=sync", cwd=tmp_path)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    said = proc.stderr.replace("\n", "")
    assert "error t [bold]/odd[/]bad.png: prep: not an image" in said, proc.stderr
    assert "wrote out/a[v2].svg, out/a[v2].json" in said, proc.stderr
    assert (tmp_path / "out" / "a[v2].svg").is_file()
    listed = cli("list", cwd=tmp_path, module="pipeline.inspect")     # the store's images, by name
    assert listed.returncode == 0 and "a[v2].png" in listed.stdout, listed.stdout + listed.stderr


@pytest.mark.parametrize("args, message", [
    (("export.foo=1",), "Could not override 'export.foo'"),
    (("export.bezier.enabled=true",), "export.bezier.enabled"),
    (("output=a(b)",), "cannot read the arguments"),
    (("-m", "flow.lam=0.1,abc"), "Error merging override flow.lam=abc"),   # a sweep's later value too
    (("hydra.run.foo=1",), "Could not override 'hydra.run.foo'"),
    (("does/not/exist.png",), "input not found: does/not/exist.png"),
    (("export.join.max_turn_deg=200",), "join.max_turn_deg"),          # composes, but out of its range
    (("export.gaps.max_turn_deg=120",), "gaps.max_turn_deg"),
    (("keypoints.test_time_views=[mirror]",), "keypoints.test_time_views"),
])
def test_usage_errors_exit_2_with_one_line(tmp_path, cli, args, message):
    proc = cli(*args, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and message in proc.stderr, proc.stderr
    assert proc.stderr.startswith("polyvec: error: ")
    assert not (tmp_path / "artifacts").exists()


def test_test_time_views_from_the_command_line(tmp_path, cli):
    """``keypoints.test_time_views=[transpose]`` runs the keypoints with the transposed drawing's
    heatmaps averaged in; the stored artifact records the setting."""
    proc = cli("keypoints.test_time_views=[transpose]", "runtime.until=keypoints", "runtime.cluster=sync", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    manifests = list((tmp_path / "artifacts" / "keypoints").glob("*/*/manifest.json"))
    assert len(manifests) == 1
    assert json.loads(manifests[0].read_text())["config"]["test_time_views"] == ["transpose"]


@pytest.mark.slow
def test_output_tree_mirrors_the_input_tree(tmp_path, cli):
    """clean/kitten and rough/kitten keep their own names; a failed image takes no other image's name."""
    src = tmp_path / "scans"
    for sub in ("clean", "rough"):
        (src / sub).mkdir(parents=True)
        (src / sub / "kitten.png").write_bytes(synthetic.vee(size=48).png_bytes())
    (src / "clean" / "a-bad.png").write_bytes(b"not an image")
    (src / "clean" / "gone.png").symlink_to(tmp_path / "nowhere.png")
    proc = cli("scans/", "runtime.cluster=sync", cwd=tmp_path)
    assert proc.returncode == 1
    assert "a-bad.png: prep: not an image" in proc.stderr
    assert "gone.png: prep: broken symbolic link" in proc.stderr
    out = tmp_path / "out"
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*.svg")) == ["clean/kitten.svg", "rough/kitten.svg"]
    # the summary names every file written
    assert "wrote out/clean/kitten.svg, out/clean/kitten.json" in proc.stderr.replace("\n", "")


def test_an_output_folder_that_cannot_be_made_is_said_in_one_line(tmp_path, cli):
    """``output=`` naming a file is a usage error before any work; a sub-folder of the output tree whose
    name a file has taken fails that image's files alone, in its error line (both were tracebacks after
    the whole run)."""
    src = tmp_path / "scans"
    for sub in ("clean", "rough"):
        (src / sub).mkdir(parents=True)
        (src / sub / "kitten.png").write_bytes(synthetic.vee(size=48).png_bytes())
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "clean").write_text("a file where out/clean/ would go")
    proc = cli("scans/", "runtime.cluster=sync", cwd=tmp_path)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "error scans/clean/kitten.png: output: cannot write out/clean (File exists)" in proc.stderr.replace("\n", "")
    assert (tmp_path / "out" / "rough" / "kitten.svg").is_file()
    assert not list((tmp_path / "out").glob(".*tmp*"))
    for output, said in (("out/clean", "a file of that name exists"), ("out/clean/deeper", "out/clean is a file")):
        proc = cli("scans/", f"output={output}", "store.path=elsewhere", cwd=tmp_path)
        assert proc.returncode == 2, proc.stderr
        assert proc.stderr.strip() == f"polyvec: error: output={output}: {said}, not a folder", proc.stderr
        assert not (tmp_path / "elsewhere").exists()     # no work began


def _folder_run_to_interrupt(tmp_path):
    """``polyvec`` on a folder of 4 drawings on a local cluster, in its own process group, with the
    default SIGINT disposition, as in a terminal (a suite started as a background job of a
    non-interactive shell inherits SIGINT ignored, and Python then installs no handler for it)."""
    import signal
    import subprocess
    import sys

    src = tmp_path / "in"
    src.mkdir()
    for k in range(4):
        (src / f"v{k}.png").write_bytes(synthetic.vee(size=48 + 4 * k).png_bytes())
    return subprocess.Popen([sys.executable, "-m", "pipeline.launch", "input=in/", "runtime.cluster=local"], cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _interrupted_once(proc) -> None:
    """Ctrl-C to the run's whole process group (as a terminal sends it): exit 130 and one line."""
    import os
    import signal

    os.killpg(proc.pid, signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert err.strip().splitlines() == [err.strip()], err
    assert err.startswith("polyvec: interrupted — ")
    assert re.search(r"\d of 4 images done, \d+ stage results stored; run the same command again", err), err
    assert "Traceback" not in out + err


def test_the_ctrl_c_line_counts_images_done_and_stage_results_stored():
    from pipeline.console import _Progress
    from pipeline.engine.execute.base import TaskResult

    progress, seen = _Progress(), []
    progress.start(3, "export")
    report = progress.counting(seen.append)
    for stage, status in (("prep", "computed"), ("field", "cached"), ("export", "computed"), ("prep", "failed")):
        report(TaskResult("a.png", stage, "k", status))
    assert (progress.done, progress.total, progress.stored, len(seen)) == (1, 3, 2, 4)


@pytest.mark.slow
def test_ctrl_c_prints_one_line(tmp_path):
    """Ctrl-C during a dask batch."""
    import time

    proc = _folder_run_to_interrupt(tmp_path)
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob("artifacts/prep/*/*")) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.1)
    time.sleep(0.5)
    _interrupted_once(proc)


@pytest.mark.slow
def test_ctrl_c_while_the_local_cluster_starts_is_not_lost(tmp_path):
    """Ctrl-C pressed while the dask workers start (the first ~1.5 s of a folder's run) stops the run:
    SIGINT was ignored in that window so that the workers would inherit it, and the run went on to its
    end; it is now held back and raised once the workers are up."""
    import subprocess
    import time

    proc = _folder_run_to_interrupt(tmp_path)

    def children() -> list[str]:
        return subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True, text=True).stdout.split()

    deadline = time.monotonic() + 120
    # multiprocessing's resource tracker, then the nannies: the cluster is starting
    while len(children()) < 2 and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.02)
    assert not list(tmp_path.glob("artifacts/prep/*/*")), "the cluster was up before the test could interrupt it"
    _interrupted_once(proc)
    deadline = time.monotonic() + 10      # the workers' last exits take a moment, as after any run
    while subprocess.run(["pgrep", "-g", str(proc.pid)], capture_output=True).stdout and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not subprocess.run(["pgrep", "-g", str(proc.pid)], capture_output=True, text=True).stdout.split()


def test_local_cluster_leaves_port_8787_alone(tmp_path, cli):
    """Another dask (here: a socket) holding the dashboard's default port 8787 causes no warning."""
    import socket

    (tmp_path / "in").mkdir()
    for k in range(2):
        (tmp_path / "in" / f"l{k}.png").write_bytes(synthetic.line(size=40 + k).png_bytes())
    with socket.socket() as sock:
        try:
            sock.bind(("127.0.0.1", 8787))
            sock.listen()
        except OSError:
            pass  # already taken by someone else: the test holds all the same
        proc = cli("input=in/", "runtime.until=prep", "runtime.cluster=local", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "8787" not in proc.stderr and "Warning" not in proc.stderr, proc.stderr


@pytest.mark.slow
def test_remote_scheduler_with_the_default_relative_store(tmp_path, cli):
    """Workers started in another directory write to the driver's relative store; a store they cannot
    reach (memory://, private to the driver) is refused before any work."""
    import subprocess
    import sys

    from conftest import free_port

    port = free_port()
    addr = f"tcp://127.0.0.1:{port}"
    elsewhere = tmp_path / "worker-cwd"
    elsewhere.mkdir()
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                               "--port", str(port), "--no-dashboard"], cwd=elsewhere,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", addr, "--nthreads", "1",
                                   "--no-dashboard"], cwd=elsewhere, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL))
    try:
        from conftest import wait_for_dask_worker

        wait_for_dask_worker(addr)
        (tmp_path / "line.png").write_bytes(synthetic.line(size=40).png_bytes())
        proc = cli("input=line.png", "runtime.until=field", f"runtime.scheduler_address={addr}", cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr
        assert len(list((tmp_path / "artifacts" / "field").glob("*/*"))) == 1
        assert not (elsewhere / "artifacts").exists()
        refused = cli("input=line.png", "runtime.until=field", "store.path=memory://polyvec-test",
                      f"runtime.scheduler_address={addr}", cwd=tmp_path)
        assert refused.returncode == 2, refused.stderr
        assert "is not reachable from 1 of 1 dask workers" in refused.stderr
        assert len(refused.stderr.strip().splitlines()) == 1, refused.stderr
    finally:
        for p in procs[::-1]:
            p.terminate()
            p.wait(20)


def test_inspect_after_a_sweep(tmp_path, cli):
    """polyvec-inspect: `show STAGE` alone picks the image's artifact, `list IMAGE` shows what differs
    between a sweep's artifacts, `render --scale` holds for every stage, a missing store is not created."""
    from PIL import Image

    img = tmp_path / "line.png"
    img.write_bytes(synthetic.line(size=40).png_bytes())
    proc = cli("-m", f"input={img}", "field.beta=9,11", "runtime.until=field", "runtime.cluster=sync", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    shown = cli("show", "prep", cwd=tmp_path, module="pipeline.inspect")
    assert shown.returncode == 0, shown.stderr
    assert '"stage": "prep"' in shown.stdout
    newest = cli("show", "field", cwd=tmp_path, module="pipeline.inspect")  # two of one image: the newest
    assert newest.returncode == 0 and '"stage": "field"' in newest.stdout, newest.stderr
    listed = cli("list", str(img), cwd=tmp_path, module="pipeline.inspect")
    field_rows = [line for line in listed.stdout.splitlines() if "field" in line]
    assert len(field_rows) == 2 and '"beta":9' in field_rows[0] + field_rows[1] \
        and '"beta":11' in field_rows[0] + field_rows[1], listed.stdout
    for stage in ("prep", "field"):
        out = tmp_path / f"{stage}.png"
        key = [] if stage == "prep" else ["--key", field_rows[0].split("│")[2].strip()]
        r = cli("render", str(img), stage, *key, "--scale", "3", "-o", str(out), cwd=tmp_path,
                module="pipeline.inspect")
        assert r.returncode == 0, r.stderr
        assert Image.open(out).size == (120, 120), stage
    missing = cli("--store", str(tmp_path / "nonexistent"), "list", cwd=tmp_path, module="pipeline.inspect")
    assert missing.returncode == 2 and "no artifact store" in missing.stderr
    assert not (tmp_path / "nonexistent").exists()


def _readme_block(heading: str) -> list[str]:
    """The commands of the first ```bash block after a README heading (comments dropped)."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    block = text[text.index(heading):].split("```bash\n", 1)[1].split("```", 1)[0]
    return [line.split("  #")[0].strip() for line in block.splitlines() if line.strip()]


@pytest.mark.slow
def test_readme_running_commands(tmp_path, cli):
    """Every command of the README's "Running" block works as written (stopped after prep, in-process)."""
    import shlex

    from PIL import Image

    (tmp_path / "scans" / "clean").mkdir(parents=True)
    (tmp_path / "my drawings (2024)").mkdir()
    line = synthetic.line(size=40).png_bytes()
    for p in ("drawing.png", "scans/clean/cat.png", "my drawings (2024)/cat.png"):
        (tmp_path / p).write_bytes(line)
    Image.fromarray((synthetic.vee(size=48).grey * 255).astype("uint8")).save(tmp_path / "scans" / "vee.jpg")
    commands = _readme_block("## Running")
    assert len(commands) >= 5
    for command in commands:
        args = shlex.split(command)
        assert args[0] == "polyvec"
        extra = ["runtime.cluster=sync"] + ([] if any(a.startswith("runtime.until=") for a in args)
                                            else ["runtime.until=prep"])
        proc = cli(*args[1:], *extra, cwd=tmp_path)
        assert proc.returncode == 0, (command, proc.stderr)


@pytest.mark.slow
def test_first_run_says_it_compiles_kernels(tmp_path):
    """With no numba cache and no shipped kernels for it (``runtime.shipped_kernels=false``: another CPU) the
    run says why it is slow; once cached, or with nothing to compute, it says nothing."""
    import os
    import subprocess
    import sys

    (tmp_path / "vee.png").write_bytes(synthetic.vee(size=48).png_bytes())
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"))
    runs = [subprocess.run([sys.executable, "-m", "pipeline.launch", "vee.png", "runtime.until=graph",
                            "runtime.cluster=sync", "runtime.shipped_kernels=false",
                            f"store.path={tmp_path / f'store{k}'}"], cwd=tmp_path,
                           capture_output=True, text=True, env=env, timeout=600) for k in range(2)]
    assert all(r.returncode == 0 for r in runs), runs[0].stderr + runs[1].stderr
    assert "compiling kernels, first run only (about half a minute; runtime.shipped_kernels=false)" in runs[0].stderr
    assert "compiling kernels" not in runs[1].stderr
    # Nothing to compute, nothing compiled: an empty numba cache does not matter then.
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "another-numba-cache")
    cached = subprocess.run([sys.executable, "-m", "pipeline.launch", "vee.png", "runtime.until=graph",
                             f"store.path={tmp_path / 'store0'}"], cwd=tmp_path, capture_output=True, text=True,
                            env=env, timeout=600)
    assert cached.returncode == 0 and "compiling kernels" not in cached.stderr, cached.stderr


def test_keypoints_edits_is_read_as_the_edits_stage_file():
    """The issue's spelling ``keypoints.edits=FILE`` reaches the edits stage, not the detector's config."""
    from pipeline.hydra_command import split_arguments

    args, paths = split_arguments(["cat.png", "keypoints.edits=cat.keypoints.json", "flow.lam=0.5"])
    assert paths == ["cat.png"]
    assert args == ["keypoint_edits.file=cat.keypoints.json", "flow.lam=0.5"]


@pytest.mark.slow
def test_readme_inspect_commands(tmp_path, cli):
    """Every command of the README's "Inspecting intermediate artifacts" block works as written,
    after the README's first command has vectorised the bundled example (stopped after graph)."""
    import shlex

    assert cli("runtime.until=graph", "runtime.cluster=sync", cwd=tmp_path).returncode == 0
    commands = _readme_block("## Inspecting intermediate artifacts")
    assert len(commands) == 4
    for command in commands:
        args = shlex.split(command)
        assert args[0] == "polyvec-inspect"
        proc = cli(*args[1:], cwd=tmp_path, module="pipeline.inspect")
        assert proc.returncode == 0, (command, proc.stderr)
    assert "polyvec-example.png" in cli("list", cwd=tmp_path, module="pipeline.inspect").stdout
    assert (tmp_path / "field.png").stat().st_size > 1000


def test_a_plain_command_line_composes_its_config_once(monkeypatch, tmp_path):
    """One job's plain overrides are composed once (Hydra's compose API), into the config that
    ``@hydra.main`` gives; a sweep or a ``hydra.`` key still goes through Hydra's app (issue 14:
    ``@hydra.main`` composes twice, ~0.2 s of every run). An empty config cache of its own: a cached
    composition (pipeline.engine.compose) is not composed at all."""
    import hydra
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from omegaconf import OmegaConf

    from pipeline.hydra_command import ExitCode, check_overrides

    loads = []
    original = ConfigLoaderImpl.load_configuration
    monkeypatch.setattr(ConfigLoaderImpl, "load_configuration",
                        lambda self, *a, **k: loads.append(1) or original(self, *a, **k))
    seen = {}

    def job(cfg):
        seen.setdefault("cfg", []).append(OmegaConf.to_container(cfg, resolve=True))
        return False

    @hydra.main(version_base=None, config_path="pkg://conf", config_name="config")
    def app(cfg):
        exit_code.job(job, cfg)

    args = ["flow.lam=0.5", "export.precision=3"]
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    for single in ((job, "config"), None):
        exit_code = ExitCode("polyvec", positional=True)
        monkeypatch.setattr("sys.argv", ["polyvec", "drawing.png", *args])
        loads.clear()
        with pytest.raises(SystemExit) as done:
            exit_code.main(app, single=single)
        assert done.value.code == 0
        assert len(loads) == (1 if single else 2)
    assert seen["cfg"][0] == seen["cfg"][1] and seen["cfg"][0]["flow"]["lam"] == 0.5
    assert check_overrides(args)
    assert not check_overrides(["flow.lam=0.1,0.2"]) and not check_overrides(["hydra.verbose=true"])
    assert not check_overrides(["-m", "flow.lam=1"]) and not check_overrides(["--cfg", "job"])


@pytest.mark.parametrize("args", [
    ["-m", "flow.lam=0.05,0.2", "flow.dt=0.005,0.01", "output=o", "store.path=s"],
    ["--multirun", "runtime=local", "runtime.cluster=sync,auto", "field.beta=9,11", "runtime.until=graph"],
    ["-m", "flow.lam=range(1,3)", "export.precision=3", "flow.iterations=7"],
    ["-m", "output='a b',c"],
    ["-m"],
])
def test_a_plain_sweep_runs_the_jobs_hydra_would_in_their_folders(monkeypatch, tmp_path, args):
    """A sweep of plain overrides is run by the CLI itself (issue 14: Hydra's multirun composed every job
    twice, ~0.4 s each): the same jobs in the same order, the same configs and folders as Hydra's
    basic sweeper and ``override_dirname``, with fewer compositions. An empty config cache of its own."""
    import hydra
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from omegaconf import OmegaConf

    from pipeline.hydra_command import ExitCode, multirun_folder

    loads = []
    original = ConfigLoaderImpl.load_configuration
    monkeypatch.setattr(ConfigLoaderImpl, "load_configuration",
                        lambda self, *a, **k: loads.append(1) or original(self, *a, **k))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    seen: dict = {}

    def job(cfg):
        seen[mode].append((str(multirun_folder(Path(str(cfg.output)))), OmegaConf.to_container(cfg)))
        return False

    @hydra.main(version_base=None, config_path="pkg://conf", config_name="config")
    def app(cfg):
        exit_code.job(job, cfg)

    composed = {}
    for mode, single in (("hydra", None), ("cli", (job, "config"))):
        seen[mode], exit_code = [], ExitCode("polyvec", positional=True)
        monkeypatch.setattr("sys.argv", ["polyvec", "drawing.png", *args])
        loads.clear()
        with pytest.raises(SystemExit) as done:
            exit_code.main(app, single=single)
        assert done.value.code == 0
        composed[mode] = len(loads)
    assert seen["cli"] == seen["hydra"] and seen["cli"]
    assert composed["cli"] < composed["hydra"]
    assert not (tmp_path / "multirun.yaml").exists()


_FINALISED_AT_EXIT = """
import atexit, sys
class Witness:
    def __del__(self):
        print("finalised", flush=True)
witness = Witness()
atexit.register(lambda: print("atexit ran", flush=True))
sys.argv = ["polyvec", *sys.argv[1:]]
from pipeline.cli import main
main()
"""


@pytest.mark.parametrize("args, code", [(["missing.png"], 2), (["input=vee.png", "runtime.cluster=sync"], 0)])
def test_the_command_ends_without_the_interpreters_teardown(tmp_path, args, code):
    """``polyvec`` leaves with its exit status once everything is written, skipping Python's
    finalisation (~1 s with torch and numba loaded); atexit handlers still run."""
    import subprocess
    import sys

    (tmp_path / "vee.png").write_bytes(synthetic.vee(size=48).png_bytes())
    proc = subprocess.run([sys.executable, "-c", _FINALISED_AT_EXIT, *args], cwd=tmp_path, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == code, proc.stderr[-2000:]
    assert "atexit ran" in proc.stdout and "finalised" not in proc.stdout
    if code == 0:
        assert (tmp_path / "out" / "vee.svg").read_text().startswith("<")


_GC_AT_EXIT = """
import atexit, gc, json, sys
atexit.register(lambda: open("gc.json", "w").write(json.dumps({"threshold": gc.get_threshold(),
                                                                "full": gc.get_stats()[2]["collections"]})))
sys.argv = ["polyvec", *sys.argv[1:]]
from pipeline.cli import main
main()
"""


def test_a_run_makes_few_full_garbage_collections(tmp_path):
    """A full collection scans every live object (~0.1 s once numba and the stages are imported) and
    finds almost nothing: the run in this process makes them rare (issue 14; DECISIONS, engine)."""
    import subprocess
    import sys

    from pipeline.engine.execute.process import FULL_COLLECTION_EVERY

    proc = subprocess.run([sys.executable, "-c", _GC_AT_EXIT, "runtime.cluster=sync"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "out" / "polyvec-example.svg").exists()
    gc_at_exit = json.loads((tmp_path / "gc.json").read_text())
    assert gc_at_exit["threshold"][2] == FULL_COLLECTION_EVERY
    assert gc_at_exit["full"] <= 1, gc_at_exit        # CPython's default thresholds: 4-6 full collections


def test_a_composed_config_is_cached_and_composed_again_when_its_files_change(tmp_path, monkeypatch):
    """pipeline.engine.compose: the second composition of a command line is read back (the planted
    entry proves it), a changed conf file or override makes a new entry, a corrupt one is recomposed."""
    import shutil

    from omegaconf import OmegaConf

    from pipeline.engine import compose as config_cache

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    first = config_cache.compose_config("config", ["flow.lam=0.3"])
    entry = config_cache.cache_dir() / f"{config_cache.config_digest('config', ['flow.lam=0.3'])}.pkl"
    assert entry.is_file()
    again = config_cache.compose_config("config", ["flow.lam=0.3"])
    assert OmegaConf.to_container(again) == OmegaConf.to_container(first) and again.flow.lam == 0.3
    planted = first.copy()
    planted.flow.lam = 0.9
    entry.write_bytes(__import__("pickle").dumps(planted))
    assert config_cache.compose_config("config", ["flow.lam=0.3"]).flow.lam == 0.9      # read back
    assert config_cache.compose_config("config", ["flow.lam=0.4"]).flow.lam == 0.4      # another line
    entry.write_bytes(b"not a pickle")
    assert config_cache.compose_config("config", ["flow.lam=0.3"]).flow.lam == 0.3      # recomposed
    # Any change of a conf file changes the digest (a copy of the package with one value edited).
    copy = tmp_path / "conf"
    shutil.copytree(config_cache._conf_root(), copy)
    before = config_cache.config_digest("config", ["flow.lam=0.3"])
    monkeypatch.setattr(config_cache, "_conf_root", lambda: copy)
    assert config_cache.config_digest("config", ["flow.lam=0.3"]) == before
    flow = copy / "flow" / "default.yaml"
    flow.write_text(flow.read_text() + "\n# edited\n")
    assert config_cache.config_digest("config", ["flow.lam=0.3"]) != before


_SIMPLE_VALUES = ["0", "-0", "+5", "12", "0.5", "-0.25", "+3.0", "true", "false", "null", "abc", "a.b", "a.5",
                  "x-1e5", "out/svg", "/tmp/x", "my-out", "_x", "a//b", "/"]
_HYDRAS_VALUES = ["007", "1_000", ".5", "5.", "1e3", "inf", "-inf", "nan", "NaN", "True", "FALSE", "NULL",
                  "./out", "/tmp/x y", "a,b", "[1,2]", "${oc.env:HOME}", "'q'", "a=b", "é", "a@b", "a b", "",
                  "0x10", "2x", "-x"]


def test_the_simplest_overrides_are_read_as_hydra_reads_them_without_hydra():
    """pipeline.engine.compose.plain_values: where it reads a line (numbers, true/false/null, words and
    paths), its keys, values and types are Hydra's parser's; anything else (a float Hydra spells otherwise,
    inf, a capitalised bool, a sweep, a list, a quote, an interpolation, a space, a ``hydra.`` key) is
    left to Hydra. A λ re-run with a new value then imports no Hydra (issue 14: ~0.13 s)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from pipeline.engine.compose import plain_values

    parser = OverridesParser.create()
    for value in _SIMPLE_VALUES:
        line = f"flow.lam={value}"
        [(key, mine)] = plain_values([line])
        theirs = parser.parse_overrides([line])[0]
        assert (key, mine, type(mine)) == (theirs.key_or_group, theirs.value(), type(theirs.value())), line
    for value in _HYDRAS_VALUES:
        assert plain_values([f"output={value}"]) is None, value
    assert plain_values(["flow.lam=0.5", "-m"]) is None and plain_values(["hydra.verbose=true"]) is None
    assert plain_values(["+flow.x=1"]) is None and plain_values(["~flow.lam"]) is None
    assert plain_values([]) == [] and plain_values(["runtime=local", "output=a/b"]) == [("runtime", "local"),
                                                                                       ("output", "a/b")]


def test_a_lambda_rerun_with_a_new_value_imports_no_hydra(tmp_path):
    """Once a line's base is cached, a new value of a plain key is checked, composed and run without Hydra."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, XDG_CACHE_HOME=str(tmp_path / "cache"))
    code = ("import sys\nfrom pipeline.hydra_command import check_overrides\nfrom pipeline.engine.compose import compose_config\n"
            "args = ['output=o', sys.argv[1]]\nassert check_overrides(args)\n"
            "print(compose_config('config', args).flow.lam, 'hydra' in sys.modules)\n")
    run = [subprocess.run([sys.executable, "-c", code, f"flow.lam={lam}"], capture_output=True, text=True, env=env)
           for lam in ("0.3", "0.45")]
    assert [r.returncode for r in run] == [0, 0], run[0].stderr + run[1].stderr
    assert run[0].stdout.split() == ["0.3", "True"]      # the first line composes its base with Hydra
    assert run[1].stdout.split() == ["0.45", "False"]    # the next value: no Hydra at all


def test_a_line_that_changes_only_values_starts_from_the_cached_base(tmp_path, monkeypatch):
    """pipeline.engine.compose: ``output=…``, ``store.path=…``, ``flow.lam=…`` set on the cached
    composition of the other overrides give Hydra's config exactly (no composition at all); a group, a
    list, an unknown key or a refused value go through Hydra, with Hydra's error."""
    from hydra import compose, initialize_config_module
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from omegaconf import OmegaConf

    from pipeline.engine import compose as config_cache

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    config_cache.compose_config("config", ["runtime=local"])
    loads = []
    original = ConfigLoaderImpl.load_configuration
    monkeypatch.setattr(ConfigLoaderImpl, "load_configuration",
                        lambda self, *a, **k: loads.append(1) or original(self, *a, **k))
    lines = {
        ("runtime=local", "output=/tmp/o", "store.path=/tmp/s", "flow.lam=1e-3"): 0,
        ("runtime=local", "input='my file (1).png'", "keypoints.junction_threshold=null"): 0,
        ("runtime=local", "prep.downsample.enabled=false", "export.precision=3"): 0,
        ("flow=default", "flow.lam=0.5"): 1,                                  # a group override
        ("runtime=local", "keypoints.detection_ensemble=[packaged_procedural]"): 1,   # a list
    }
    for line, compositions in lines.items():
        loads.clear()
        got = config_cache.compose_config("config", list(line))
        assert len(loads) == compositions, line
        with initialize_config_module(config_module="conf", version_base=None):
            want = compose("config", overrides=list(line))
        assert OmegaConf.to_container(got) == OmegaConf.to_container(want), line
    for bad in (["runtime=local", "flow.lam=abc"], ["runtime=local", "flow.nokey=3"], ["runtime=local", "nokey=3"]):
        with pytest.raises(Exception) as cached:
            config_cache.compose_config("config", bad)
        with pytest.raises(Exception) as fresh, initialize_config_module(config_module="conf", version_base=None):
            compose("config", overrides=bad)
        assert str(cached.value) == str(fresh.value)


def test_repeated_commands_read_their_config_from_the_cache(tmp_path, cli, monkeypatch):
    """As a user: the same command twice, then into another output folder, then with the cache
    corrupted: every run works and writes the same curves; the cache holds the compositions."""
    import numpy as np
    from PIL import Image

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    g = np.full((120, 160), 255, np.uint8)
    g[60:62, 20:140] = 0
    Image.fromarray(g, "L").save(tmp_path / "line.png")
    outs = []
    for k, out in enumerate(["a", "a", "b", "c"]):
        if k == 3:
            for entry in (tmp_path / "cache" / "polyvec" / "config").glob("*.pkl"):
                entry.write_bytes(b"torn")
        proc = cli("line.png", f"output={out}", "runtime.cluster=sync", cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr
        outs.append((tmp_path / out / "line.svg").read_text())
    assert len(set(outs)) == 1
    assert list((tmp_path / "cache" / "polyvec" / "config").glob("*.pkl"))


@pytest.mark.skipif(sys.platform == "win32", reason="needs a pseudo-terminal")
def test_in_a_terminal_the_progress_display_redraws_at_most_twice_a_second(tmp_path):
    """Run in a terminal (a pseudo-terminal on stdin, stdout and stderr), `polyvec` shows one bar per
    stage while it works, redrawn at most :data:`pipeline.console.REFRESH_PER_SECOND` (2) times a second:
    each redraw renders every row on a thread of the process whose stages need the GIL (rich's ten a
    second made a drawing's run 0.1–0.6 s longer; stages/DECISIONS.md, engine)."""
    import os
    import pty
    import subprocess
    import time

    from pipeline.console import REFRESH_PER_SECOND

    primary, secondary = pty.openpty()
    started = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.launch", "runtime.until=field", "runtime.cluster=sync"],
                            cwd=tmp_path, stdin=secondary, stdout=secondary, stderr=secondary,
                            env=dict(os.environ, COLUMNS="100", TERM="xterm"))
    os.close(secondary)
    out = b""
    while True:
        try:
            chunk = os.read(primary, 65536)
        except OSError:  # the terminal's other side closed: the command is done
            break
        if not chunk:
            break
        out += chunk
    os.close(primary)
    assert proc.wait(timeout=600) == 0, out.decode(errors="replace")
    wall = time.monotonic() - started
    # One frame of the display per line like "     field ━━━━ 0/1 …" (the summary table has no bar).
    frames = len(re.findall(r"     field \S*━+\S* \S*\d+/1", out.decode(errors="replace")))
    assert frames >= 2, out.decode(errors="replace")             # it is shown, and redrawn
    assert frames <= REFRESH_PER_SECOND * wall + 3, (frames, wall)
