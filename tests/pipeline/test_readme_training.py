"""The README's keypoint-detector and polyvec-bench commands, each run as written but on tiny data.

Long runs are made small by overriding the keys that set their size (``train.steps`` and friends) and
by pointing folders at a few generated cases; every command of both blocks runs.
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]

# Keys whose value the README gives at full size, and the value that keeps a test fast.
TINY = {"train.steps": "2", "train.type_classifier.drawings": "2", "train.type_classifier.val_drawings": "1",
        "train.type_classifier.epochs": "5", "train.type_classifier.vector_drawings": "2"}
TINY_EXTRA = {"polyvec-train": ["train.batch_size=2", "train.num_workers=0", "train.val.count=1",
                                "train.val.vector_count=0", "train.crop_schedule=[[0,48]]",
                                "train.network.level_channels=[4,8,8,8]", "train.network.stem_mid=4",
                                "train.network.bottleneck_blocks=1"]}


def _block(section: str) -> list[str]:
    readme = (REPO / "README.md").read_text()
    text = readme.split(f"## {section}", 1)[1].split("\n## ", 1)[0]
    block = text.split("```bash", 1)[1].split("```", 1)[0]
    return [ln.split("  #", 1)[0].strip() for ln in block.splitlines() if ln.split("  #", 1)[0].strip()]


def _ndjson(folder: Path, names: list[str]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        with open(folder / f"{name}.ndjson", "w") as f:
            for i in range(2):
                f.write(json.dumps({"word": name, "drawing": [[[0, 100 + 40 * i], [0, 0]],
                                                              [[50, 50], [0, 120]]]}) + "\n")


def _adapt(cmd: str, work: Path) -> list[str]:
    """The command as argv, made small: tiny sizes, the local tiny data instead of ../shared."""
    argv = shlex.split(cmd)
    out = []
    for a in argv:
        key = a.split("=", 1)[0]
        if key in TINY:
            a = f"{key}={TINY[key]}"
        a = a.replace("../shared/data/realvec_dev,../shared/data/drawings", str(work / "cases"))
        out.append(a)
    if out[0] == "polyvec-train" or out[:3] == ["python", "-m", "pipeline.train"]:
        out += TINY_EXTRA["polyvec-train"] + [f"train.vector.files=[{work / 'qd' / '*.ndjson'}]",
                                              "train.vector.holdout=1", "train.vector.stroke3=[]"]
        if "--type-classifier" in out:
            out += [f"{k}={v}" for k, v in TINY.items() if k.startswith("train.type_classifier")
                    and f"{k}={v}" not in out]
    if "--min-strokes" in out:  # the tiny drawings have two strokes
        out[out.index("--min-strokes") + 1] = "2"
    if out[:3] == ["python", "-m", "pipeline.validation_cases"]:
        out += [f"train.vector.files=[{work / 'qd' / '*.ndjson'}]", "train.vector.holdout=2",
                "train.vector.stroke3=[]", "--stroke3", "0"]
    if out[0].startswith("python"):
        out[0] = sys.executable
        if out[1].startswith("tests/"):  # a script of the repository, run from the working folder
            out[1] = str(REPO / out[1])
    return out


@pytest.mark.slow
def test_readme_detector_and_bench_commands_run(tmp_path):
    _ndjson(tmp_path / "qd", [f"thing{i}" for i in range(4)])
    # a few realvec-style cases for the commands that read a case folder
    from pipeline.validation_cases import write_cases
    from pipeline.train import compose_plain

    cfg = compose_plain(REPO / "conf", [f"train.vector.files=[{tmp_path / 'qd' / '*.ndjson'}]",
                                        "train.vector.holdout=1", "train.vector.stroke3=[]"])
    write_cases(cfg, tmp_path / "cases", per_category=1, stroke3=0)
    (tmp_path / "conf").symlink_to(REPO / "conf")  # `--type-classifier conf` names the repo's conf folder
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    commands = _block("Keypoint detector: training and evaluation") + _block("Evaluation: `polyvec-bench`")
    assert any(c.startswith("polyvec-train") for c in commands) and any(c.startswith("polyvec-bench") for c in commands)
    for cmd in commands:
        argv = _adapt(cmd, tmp_path)
        if argv[0] in ("polyvec-train", "polyvec-bench"):
            argv = [sys.executable, "-m", {"polyvec-train": "pipeline.train", "polyvec-bench": "pipeline.bench"}[argv[0]]] + argv[1:]
        argv = [a.replace("outputs/valsplit", str(tmp_path / "cases")) if "valsplit" in a and "validation_cases" not in cmd
                else a for a in argv]
        r = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        assert r.returncode in (0, 1), f"{cmd}\n{r.stderr[-2000:]}"  # 1: polyvec-bench with a failed case
        assert "Traceback" not in r.stderr, f"{cmd}\n{r.stderr[-2000:]}"
    assert np.any([p.name == "type_classifier.npz" for p in (tmp_path / "outputs").rglob("*")])


@pytest.mark.slow
@pytest.mark.parametrize("sweep", [False, True])
def test_polyvec_train_names_its_weights_and_leaves_the_folder_clean(tmp_path, sweep):
    """Issue 18 items 10 and 14: no ``outputs/<date>/<time>/.hydra/`` (nor a sweep's
    ``multirun.yaml``) in the working folder, and one line that says where the weights went."""
    _ndjson(tmp_path / "qd", ["thing0", "thing1"])
    work, out = tmp_path / "cwd", tmp_path / "weights"
    work.mkdir()
    argv = _adapt(f"polyvec-train {'-m ' if sweep else ''}train.steps=1 train.out_dir={out}", tmp_path)
    argv = [sys.executable, "-m", "pipeline.train"] + argv[1:]
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    r = subprocess.run(argv, cwd=work, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(p.name for p in work.rglob("*")) == []                 # nothing left in the user's folder
    said = [ln for ln in r.stdout.splitlines() if "weights written to" in ln]
    assert len(said) == 1 and str((out / "keypoints.pt").resolve()) in said[0], r.stdout[-2000:]
    assert (out / "keypoints.pt").is_file()
