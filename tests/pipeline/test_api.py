"""The Python API (issue 56): ``from pipeline import vectorize`` on a path, bytes, a PIL image and arrays.

The README's ```python block under ``## Python API`` runs as written, as a script, beside a small
synthetic drawing; the other tests call :func:`pipeline.vectorize` in this process, on one store
shared by the module (after the first drawing the network and kernels are loaded: a 64-px drawing then
takes well under a second).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stages import synthetic
from stages.errors import InputError

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _readme_block(heading: str, lang: str) -> str:
    """The first ```lang block below ``## heading`` of the README (as tests/test_readme.py reads them)."""
    current, fence, lines = None, None, []
    for line in (REPO / "README.md").read_text().splitlines():
        if fence is None and line.startswith("## "):
            current = line[3:].strip()
        elif fence is None and line.startswith("```"):
            fence = line[3:].strip()
        elif fence is not None and line.startswith("```"):
            if current == heading and fence == lang:
                return "\n".join(lines) + "\n"
            fence, lines = None, []
        elif fence is not None:
            lines.append(line)
    raise AssertionError(f"README.md has no ```{lang} block under '## {heading}'")


def _manifests(store: Path) -> set[str]:
    return {str(p.relative_to(store)) for p in store.glob("*/*/*/manifest.json")}


@pytest.fixture(scope="module")
def drawing() -> synthetic.Drawing:
    return synthetic.vee(size=64)


@pytest.fixture(scope="module")
def folder(tmp_path_factory, drawing) -> Path:
    """A folder with ``drawing.png``; the tests' store is its ``artifacts``."""
    where = tmp_path_factory.mktemp("api")
    (where / "drawing.png").write_bytes(drawing.png_bytes())
    return where


@pytest.fixture(scope="module")
def first(folder):
    """The drawing vectorised by path, into the module's store."""
    from pipeline import vectorize

    return vectorize(folder / "drawing.png", store=folder / "artifacts")


def _same_curves(a, b) -> None:
    assert [c["end_types"] for c in a.curves] == [c["end_types"] for c in b.curves]
    for ca, cb in zip(a.curves, b.curves):
        assert ca["points"].shape == cb["points"].shape
        assert np.abs(ca["points"] - cb["points"]).max() < 0.5


# -- the README ----------------------------------------------------------------------------------
@pytest.mark.slow
def test_the_readme_python_block_runs_as_written(tmp_path, drawing):
    """The block, saved as a script and run by ``python`` beside ``drawing.png``: it ends, prints the
    SVG's start, a line per curve and the keypoints, and writes the files it names."""
    (tmp_path / "drawing.png").write_bytes(drawing.png_bytes())
    (tmp_path / "readme_api.py").write_text(_readme_block("Python API", "python"))
    proc = subprocess.run([sys.executable, "readme_api.py"], cwd=tmp_path, capture_output=True, text=True, check=False,
                          env=dict(os.environ, PYTHONPATH=str(REPO)), timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "<svg" in proc.stdout and re.search(r"^\(\d+, 2\) \[\d, \d\]$", proc.stdout, re.MULTILINE)
    assert re.search(r"^\[\([\d.]+, [\d.]+, [135]\)", proc.stdout, re.MULTILINE)   # the keypoints
    for name in ("drawing.svg", "drawing.json", "drawing.bezier.svg"):
        assert (tmp_path / "out" / name).is_file(), name
    saved = json.loads((tmp_path / "out" / "drawing.json").read_text())
    assert saved["curves"] and saved["source"] == "drawing.png"
    # the store the README names: artifacts/ of the working directory, and the non-path inputs kept there
    assert _manifests(tmp_path / "artifacts") and list((tmp_path / "artifacts" / ".inputs").glob("*.png"))


# -- inputs --------------------------------------------------------------------------------------
def test_a_path_gives_curves_keypoints_and_the_svg(first, drawing):
    assert first.svg.startswith("<?xml") and "<path" in first.svg
    assert first._repr_svg_() == first.svg     # what a notebook shows
    assert list(first.keys) == ["prep", "keypoints", "keypoint_edits", "field", "extension", "graph",
                                "topology", "flow", "select", "export"]
    assert first.curves and all(c["points"].ndim == 2 and c["points"].shape[1] == 2 for c in first.curves)
    assert first.bezier_svg is None
    # the vee's two endpoints and its corner, each near its true place, in the drawing's pixels
    truth = np.array([(x, y) for x, y, _ in drawing.keypoints])
    assert len(first.keypoints) == len(truth)
    for x, y, t in first.keypoints:
        assert t in (1, 3, 5) and np.hypot(*(truth - (x, y)).T).min() < 3
    # a curve's ends are the keypoints they name
    for c in first.curves:
        for end, k in zip((c["points"][0], c["points"][-1]), c["end_keypoints"]):
            if k >= 0:
                assert np.hypot(*(end - first.keypoints[k][:2])) < 1e-3
    assert "drawing.png" in repr(first) and "<svg" not in repr(first)


def test_bytes_a_pil_image_and_arrays_give_the_drawings_curves(first, folder, drawing):
    """The file's bytes are the file: every artifact is read back. A PIL image and arrays (grey uint8,
    float in [0, 1], RGB, RGBA, uint16) give the same curves."""
    from PIL import Image

    from pipeline import vectorize

    store = folder / "artifacts"
    again = vectorize((folder / "drawing.png").read_bytes(), store=store)
    assert again.keys == first.keys and again.svg == first.svg
    grey = np.asarray(Image.open(folder / "drawing.png"))
    assert grey.dtype == np.uint8 and grey.ndim == 2
    for image in (Image.open(folder / "drawing.png"), grey, grey / 255.0, np.dstack([grey] * 3),
                  np.dstack([grey] * 3 + [np.full_like(grey, 255)]), grey.astype(np.uint16) * 257):
        result = vectorize(image, store=store)
        assert Path(result.source).parent == store / ".inputs", type(image)
        _same_curves(result, first)


def test_a_pil_image_keeps_its_exif_orientation(tmp_path, folder, drawing):
    """A phone's JPEG turned by its EXIF orientation: its PIL image gives the curves its path gives (the
    drawing as a viewer shows it, 48 × 64); its pixels as an array are the unturned 64 × 48."""
    from PIL import Image

    from pipeline import vectorize

    exif = Image.Exif()
    exif[0x0112] = 6     # "rotate 90° clockwise to view"
    Image.fromarray((drawing.grey[:48] * 255).astype(np.uint8)).save(tmp_path / "turned.jpg", exif=exif.tobytes(),
                                                                     quality=95)
    by_path = vectorize(tmp_path / "turned.jpg", store=folder / "artifacts")
    by_pil = vectorize(Image.open(tmp_path / "turned.jpg"), store=folder / "artifacts")
    assert 'viewBox="0 0 48 64"' in by_path.svg and 'viewBox="0 0 48 64"' in by_pil.svg
    _same_curves(by_pil, by_path)
    by_array = vectorize(np.asarray(Image.open(tmp_path / "turned.jpg")), store=folder / "artifacts")
    assert 'viewBox="0 0 64 48"' in by_array.svg


def test_the_same_array_twice_computes_nothing(folder, drawing):
    from pipeline import vectorize

    store = folder / "artifacts"
    array = (np.asarray(drawing.grey) * 0.9).astype(np.float32)   # fainter ink: an image of its own
    one = vectorize(array, store=store)
    before, inputs = _manifests(store), sorted((store / ".inputs").iterdir())
    two = vectorize(array.copy(), store=store)
    assert two.keys == one.keys and two.source == one.source
    assert _manifests(store) == before and sorted((store / ".inputs").iterdir()) == inputs


def test_the_command_line_reads_back_what_the_api_computed(first, folder, cli):
    """Same configs, same store: ``polyvec drawing.png`` computes nothing and writes the API's SVG,
    and ``save`` writes the command line's files."""
    before = _manifests(folder / "artifacts")
    proc = cli("drawing.png", cwd=folder)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert _manifests(folder / "artifacts") == before
    assert (folder / "out" / "drawing.svg").read_text() == first.svg
    written = first.save(folder / "api" / "drawing.svg")
    assert written == [folder / "api" / "drawing.svg", folder / "api" / "drawing.json"]
    assert written[0].read_text() == first.svg
    cli_json = json.loads((folder / "out" / "drawing.json").read_text())
    api_json = json.loads(written[1].read_text())
    assert api_json == dict(cli_json, source=first.source)


def test_overrides_as_on_the_command_line(first, folder):
    from pipeline import vectorize

    store = folder / "artifacts"
    bezier = vectorize(folder / "drawing.png", "export.bezier=true", store=store)
    assert bezier.bezier_svg and bezier.keys["flow"] == first.keys["flow"] and bezier.keys["export"] != first.keys["export"]
    assert [p.name for p in bezier.save(folder / "bz" / "drawing")] == ["drawing.svg", "drawing.json", "drawing.bezier.svg"]
    # store.path= is store=
    assert vectorize(folder / "drawing.png", f"store.path={store}").keys == first.keys
    # stopped before the export: the stages run have keys, there is nothing to draw or save
    early = vectorize(folder / "drawing.png", "runtime.until=graph", store=store)
    assert list(early.keys) == ["prep", "field", "graph"] and early.svg is None and early.curves == []
    assert early._repr_svg_() is None
    with pytest.raises(ValueError, match="before export"):
        early.save(folder / "early.svg")


# -- errors: one line each -----------------------------------------------------------------------
@pytest.mark.parametrize("override, words", [
    ("flow.lamb=0.5", "Key 'lamb' not in 'FlowConfig'"),
    ("flow.lam=abc", "could not be converted to Float"),
    ("nonsense", "nonsense"),
])
def test_an_unknown_or_ill_typed_override_is_one_clear_error(tmp_path, override, words):
    from pipeline import vectorize

    with pytest.raises(ValueError) as info:
        vectorize(tmp_path / "any.png", override, store=tmp_path / "store")
    assert words in str(info.value) and "\n" not in str(info.value)
    assert not (tmp_path / "store").exists()    # refused before anything was opened


def test_a_value_out_of_its_range_is_one_clear_error(folder):
    from pipeline import vectorize

    with pytest.raises(InputError, match="max_turn_deg"):
        vectorize(folder / "drawing.png", "export.join.max_turn_deg=200", store=folder / "artifacts")


@pytest.mark.parametrize("image, kind, words", [
    (b"this is not an image", InputError, "not an image"),
    (b"", InputError, "empty"),
    (np.zeros((0, 8), np.uint8), InputError, "empty image array"),
    (np.zeros((8, 8, 2), np.uint8), InputError, r"\(H, W\)"),
    (np.full((8, 8), 2.0), InputError, r"\[0, 1\]"),
    (np.full((8, 8), np.nan), InputError, "NaN"),
    (np.zeros((8, 8), bool), InputError, "not bool"),
    (np.full((8, 8), 300, np.int64), InputError, "0 … 255"),
    ("missing.png", InputError, "cannot read file"),
    (3.5, TypeError, "'float'"),
])
def test_a_bad_image_is_one_clear_error(tmp_path, image, kind, words):
    from pipeline import vectorize

    store = tmp_path / "store"
    with pytest.raises(kind, match=words) as info:
        vectorize(tmp_path / image if isinstance(image, str) else image, store=store)
    assert "\n" not in str(info.value)
    assert not (store / ".inputs").is_dir() or not any((store / ".inputs").iterdir())   # no junk kept


@pytest.mark.parametrize("error, detail, kind", [
    ("not an image (unrecognised file format)", None, InputError),
    ("internal error in stage graph: ZeroDivisionError: division by zero", "Traceback …", "VectorizationError"),
    ("worker lost: BrokenPipeError: [Errno 32] Broken pipe", None, "VectorizationError"),
])
def test_a_failed_stage_is_the_inputs_fault_or_a_vectorization_error(folder, monkeypatch, error, detail, kind):
    """A stage's InputError (its own words, no traceback) is the input's; an internal error, a lost worker
    process or no memory is a VectorizationError that carries the traceback, if any."""
    import pipeline.engine.execute.batch as batch_module
    from pipeline import api
    from pipeline.engine.execute.base import BatchResult, TaskResult

    def failing(images, cfg, **_):
        (image,) = images
        return BatchResult(results={image: {"graph": TaskResult(image, "graph", "k", "failed", error, detail)}},
                           stages=["prep", "field", "graph"])

    monkeypatch.setattr(batch_module, "run_batch", failing)
    kind = getattr(api, kind) if isinstance(kind, str) else kind
    with pytest.raises(kind, match="graph: ") as info:
        api.vectorize(folder / "drawing.png", store=folder / "artifacts")
    assert str(info.value) == f"{folder / 'drawing.png'}: graph: {error}"
    if kind is api.VectorizationError:
        assert info.value.detail == detail


def test_the_package_imports_the_api_only_when_asked():
    """``import pipeline`` (which ``polyvec``'s launcher does before anything else) imports nothing;
    ``from pipeline import vectorize`` then imports the API, and sub-modules import as before."""
    code = ("import sys, pipeline\n"
            "assert 'pipeline.api' not in sys.modules and 'numpy' not in sys.modules, sorted(sys.modules)\n"
            "from pipeline import vectorize, Vectorization, inputs\n"
            "assert vectorize.__module__ == 'pipeline.api' and inputs.__name__ == 'pipeline.inputs'\n"
            "assert 'vectorize' in dir(pipeline)\n"
            "try:\n    pipeline.nothing\nexcept AttributeError:\n    pass\nelse:\n    raise SystemExit(1)\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr
