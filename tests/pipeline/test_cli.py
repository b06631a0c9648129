"""The command lines as a user runs them, in subprocesses."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from stages import synthetic


def polyvec(*args: str, cwd: Path, module: str = "pipeline.cli") -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, capture_output=True, text=True,
                          env=env, timeout=600)


def test_default_run_on_the_bundled_example(tmp_path):
    """`polyvec` with no input vectorises the generated example drawing; a rerun is all cache hits."""
    proc = polyvec(cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "out" / "polyvec-example.png").exists()
    assert (tmp_path / "artifacts" / "prep").is_dir()
    assert "computed" in proc.stderr
    if (tmp_path / "artifacts" / "export").is_dir():
        assert (tmp_path / "out" / "polyvec-example.svg").exists()
    again = polyvec(cwd=tmp_path)
    assert again.returncode == 0
    table = [line for line in again.stderr.splitlines() if line.startswith("│")]
    assert table and all(line.split("│")[2].strip() == "0" for line in table), again.stderr


def test_batch_with_a_corrupt_file_finishes_and_exits_nonzero(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    (folder / "a.png").write_bytes(synthetic.line(size=40).png_bytes())
    (folder / "b.png").write_bytes(b"GIF89a broken")
    (folder / "c.png").write_bytes(synthetic.vee(size=48).png_bytes())
    proc = polyvec(f"input={folder}", "runtime.until=field", "runtime.cluster=sync", cwd=tmp_path)
    assert proc.returncode == 1
    assert "b.png: prep:" in proc.stderr
    assert "Traceback" not in proc.stderr
    # the two good images went all the way
    assert len(list((tmp_path / "artifacts" / "field").glob("*/*"))) == 2


def test_missing_input_is_one_line(tmp_path):
    proc = polyvec("input=does/not/exist.png", cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.strip() == "polyvec: error: input not found: does/not/exist.png"


def test_multirun_shares_one_store(tmp_path):
    img = tmp_path / "line.png"
    img.write_bytes(synthetic.line(size=40).png_bytes())
    proc = polyvec("-m", f"input={img}", "field.beta=9,11", "runtime.until=field", "runtime.cluster=sync",
                   cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert len(list((tmp_path / "artifacts" / "prep").glob("*/*"))) == 1
    assert len(list((tmp_path / "artifacts" / "field").glob("*/*"))) == 2


def test_inspect_list_show_render(tmp_path):
    img = tmp_path / "vee.png"
    img.write_bytes(synthetic.vee(size=48).png_bytes())
    assert polyvec(f"input={img}", "runtime.until=field", "runtime.cluster=sync", cwd=tmp_path).returncode == 0
    listed = polyvec("list", str(img), cwd=tmp_path, module="pipeline.inspect")
    assert listed.returncode == 0 and "field" in listed.stdout and "prep" in listed.stdout
    shown = polyvec("show", "field", "--image", str(img), cwd=tmp_path, module="pipeline.inspect")
    assert shown.returncode == 0
    manifest = json.loads(shown.stdout[: shown.stdout.index("\n}\n") + 2])
    assert manifest["stage"] == "field" and "beta" in manifest["config"]
    for stage in ("prep", "field"):
        out = tmp_path / f"{stage}.png"
        r = polyvec("render", str(img), stage, "-o", str(out), cwd=tmp_path, module="pipeline.inspect")
        assert r.returncode == 0, r.stderr
        from PIL import Image

        assert Image.open(out).size[0] >= 48
    missing = polyvec("show", "graph", "ffff", cwd=tmp_path, module="pipeline.inspect")
    assert missing.returncode == 2 and "no graph artifact" in missing.stderr
