"""A failed image is as cheap as a hit on the next run of the same command (issue 54, item 5): the failure
is stored under its task's key and reported again without running anything; a changed file or config
tries it again."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from pipeline.engine.execute import batch as batch_mod
from pipeline.engine.execute.batch import run_batch
from pipeline.engine.store import ArtifactStore
from stages import synthetic


@pytest.fixture
def folder(tmp_path):
    """A drawing, a junk file named like an image and a blank page."""
    f = tmp_path / "in"
    f.mkdir()
    (f / "line.png").write_bytes(synthetic.line(size=40, width=3).png_bytes())
    (f / "junk.png").write_bytes(np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    Image.fromarray(np.full((60, 60), 255, np.uint8)).save(f / "white.png")
    return f


def _images(folder):
    return [folder / "line.png", folder / "junk.png", folder / "white.png"]


def _no_executor(monkeypatch):
    """Make any work fail the test: a run whose every task is stored or a stored failure starts none."""
    def refuse(*args, **kwargs):
        raise AssertionError("an executor was started")

    monkeypatch.setattr(batch_mod, "InProcessExecutor", refuse)
    monkeypatch.setattr(batch_mod.DaskExecutor, "connect", refuse)


def test_the_next_run_reports_a_stored_failure_without_running_anything(tmp_path, folder, compose_cfg,
                                                                        monkeypatch):
    cfg = compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.cluster=sync", "runtime.until=field")
    first = run_batch(_images(folder), cfg)
    junk, white = str(folder / "junk.png"), str(folder / "white.png")
    assert set(first.failed_images) == {junk, white}
    _no_executor(monkeypatch)
    second = run_batch(_images(folder), cfg)
    assert second.failed_images == first.failed_images   # the same one line for each image
    for image in (junk, white):
        assert second.results[image]["prep"].status == "failed" and second.results[image]["prep"].stored
        assert second.results[image]["field"].status == "skipped"
    assert second.counts()["prep"] == {"cached": 1, "failed": 2}
    assert second.results[str(folder / "line.png")]["field"].status == "cached"


def test_a_changed_file_or_config_is_tried_again(tmp_path, folder, compose_cfg):
    cfg = compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.cluster=sync", "runtime.until=prep")
    junk = folder / "junk.png"
    run_batch([junk], cfg)
    (folder / "junk.png").write_bytes(b"GIF89a other junk")   # still not an image, but other bytes
    again = run_batch([junk], cfg)
    assert again.results[str(junk)]["prep"].status == "failed" and not again.results[str(junk)]["prep"].stored
    assert run_batch([junk], cfg).results[str(junk)]["prep"].stored
    changed = run_batch([junk], compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.cluster=sync",
                                            "runtime.until=prep", "prep.threshold=0.6"))
    assert not changed.results[str(junk)]["prep"].stored
    junk.write_bytes(synthetic.vee(size=48, width=3).png_bytes())   # fixed: an image now
    fixed = run_batch([junk], cfg)
    assert fixed.results[str(junk)]["prep"].status == "computed" and not fixed.failed_images


def test_an_internal_error_is_not_stored(tmp_path, folder, compose_cfg, monkeypatch):
    """Only a failure on the input is stored: an internal error (a bug fixed in place) is tried again."""
    from stages import prep

    def broken(cfg, **inputs):
        raise RuntimeError("a bug")

    monkeypatch.setattr(prep, "run", broken)
    cfg = compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.cluster=sync", "runtime.until=prep")
    line = folder / "line.png"
    first = run_batch([line], cfg)
    assert "internal error" in first.failed_images[str(line)]
    task = batch_mod.plan([line], cfg, batch_mod.validated_stages(cfg))[0][0]
    assert ArtifactStore(tmp_path / "store").failure("prep", task.key) is None
    assert not run_batch([line], cfg).results[str(line)]["prep"].stored


def test_the_command_line_says_it_is_a_stored_failure(tmp_path, folder, cli):
    args = (str(folder), "runtime.until=prep", "runtime.cluster=sync", f"output={tmp_path / 'out'}")
    first = cli(*args, cwd=tmp_path)
    assert first.returncode == 1 and "stored failure" not in first.stderr
    second = cli(*args, cwd=tmp_path)
    assert second.returncode == 1, second.stderr
    lines = [line for line in second.stderr.splitlines() if line.startswith("error")]
    assert len(lines) == 2 and all("stored failure of an earlier run" in line for line in lines), second.stderr
    assert any("junk.png: prep: not an image" in line for line in lines)
