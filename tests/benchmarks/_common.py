"""Helpers shared by the benchmark scripts (run as scripts: this folder is on sys.path)."""

from __future__ import annotations

import hashlib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def stage_cfg(stage: str) -> dict:
    """A stage's default config section from conf/<stage>/default.yaml."""
    from pipeline.engine.config import default_config

    return default_config(stage)


def source_hash(*paths: Path) -> str:
    """Short hash of the Python sources under ``paths``, to key cached benchmark inputs."""
    h = hashlib.sha1()
    for p in paths:
        for f in sorted(p.rglob("*.py")) if p.is_dir() else [p]:
            h.update(f.read_bytes())
    return h.hexdigest()[:12]
