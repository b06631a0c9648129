"""The exported SVG opens in Inkscape and in a browser (Chromium) and renders aligned with the input.

Both programs are optional (Debian packages ``inkscape`` and ``chromium``); each test is skipped
where its program is not installed.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy import ndimage

from stages import synthetic


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    from tests.conftest import run_cli

    work = tmp_path_factory.mktemp("svg")
    r = run_cli("runtime.cluster=sync", cwd=work)
    assert r.returncode == 0, r.stderr[-2000:]
    svg = work / "out" / "polyvec-example.svg"
    assert svg.is_file()
    return svg


def _dark(png: Path, shape: tuple[int, int]) -> np.ndarray:
    im = np.asarray(Image.open(png).convert("RGBA"), np.float64)
    alpha = im[..., 3:4] / 255.0
    rgb = im[..., :3] * alpha + 255.0 * (1 - alpha)  # composite on white paper
    h, w = shape
    assert im.shape[0] >= h and im.shape[1] >= w, f"render {im.shape[:2]} smaller than the drawing {shape}"
    return rgb[:h, :w].mean(axis=2) < 160


def _check_aligned(dark: np.ndarray) -> None:
    grey = synthetic.example_drawing().grey
    ink = grey < 0.5
    assert dark.sum() > 300, "the rendered curves are (nearly) empty"
    # Every rendered curve pixel lies on the drawing's ink (±1 px) ...
    on_ink = (dark & ndimage.binary_dilation(ink, iterations=1)).sum() / dark.sum()
    assert on_ink > 0.97, f"only {on_ink:.3f} of the rendered pixels lie on the strokes: misaligned"
    # ... and the curves cover the drawing's strokes.
    from skimage.morphology import skeletonize

    centre = skeletonize(ink)
    covered = (centre & ndimage.binary_dilation(dark, iterations=2)).sum() / centre.sum()
    assert covered > 0.9, f"only {covered:.3f} of the stroke centre lines are drawn"


@pytest.mark.skipif(shutil.which("inkscape") is None, reason="inkscape not installed")
def test_svg_renders_aligned_in_inkscape(exported, tmp_path):
    png = tmp_path / "inkscape.png"
    subprocess.run(["inkscape", str(exported), "--export-type=png", f"--export-filename={png}"],
                   capture_output=True, timeout=180, check=True)
    grey = synthetic.example_drawing().grey
    assert Image.open(png).size == (grey.shape[1], grey.shape[0])  # viewBox 0 0 W H at 96 dpi = W × H px
    _check_aligned(_dark(png, grey.shape))


@pytest.mark.skipif(shutil.which("chromium") is None, reason="chromium not installed")
def test_svg_renders_aligned_in_a_browser(exported, tmp_path):
    png = tmp_path / "chromium.png"
    grey = synthetic.example_drawing().grey
    subprocess.run(["chromium", "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    f"--screenshot={png}", f"--window-size={grey.shape[1] + 100},{grey.shape[0] + 100}",
                    exported.resolve().as_uri()], capture_output=True, timeout=180, check=True)
    _check_aligned(_dark(png, grey.shape))
