"""The shipped model files travel with a (non-editable) install."""

from __future__ import annotations

import fnmatch
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_package_data_covers_the_shipped_weights():
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["*"]
    shipped = sorted(p.name for p in (ROOT / "stages" / "keypoints" / "weights").iterdir() if p.is_file())
    assert {"keypoints.pt", "keypoints_procedural.pt", "type_classifier.npz"} <= set(shipped)
    missing = [n for n in shipped if not any(fnmatch.fnmatch(n, pat) for pat in patterns)]
    assert missing == [], f"not in [tool.setuptools.package-data]: {missing}"
