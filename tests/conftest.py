"""Shared test fixtures: config composition and the location of ../shared."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def shared_path(*parts: str) -> Path:
    """A path under ../shared, skipping the test when it is absent."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"{p} not available (../shared is absent)")
    return p


@pytest.fixture
def compose_cfg():
    """Compose the polyvec Hydra config with overrides, as the CLI would."""
    from hydra import compose, initialize_config_module

    def _compose(*overrides: str):
        with initialize_config_module(config_module="conf", version_base=None):
            return compose(config_name="config", overrides=list(overrides))

    return _compose
