"""Shared test fixtures: config composition and the location of ../shared."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.engine.kernels import shipped as kernels, warmup  # (kernels imports stages: numba's CPU target is set before a test imports numba)

# Tests call the stages directly too: start from the shipped kernels, as an installed polyvec's first run does
# (where they fit this machine), not from compiling them in each test worker.
kernels.install(list(warmup.WARMED))

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def shared_path(*parts: str) -> Path:
    """A path under ../shared, skipping the test when it is absent."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"{p} not available (../shared is absent)")
    return p


def train_configs() -> tuple:
    """The ``generator`` and ``labels`` sections of conf/train/default.yaml as their dataclasses."""
    import yaml

    from stages.config import from_section
    from stages.keypoints.training.generator import GeneratorConfig
    from stages.keypoints.training.labels import LabelRules

    train = yaml.safe_load((REPO / "conf" / "train" / "default.yaml").read_text())
    return (from_section(GeneratorConfig, train["generator"], "train.generator"),
            from_section(LabelRules, train["labels"], "train.labels"))


def run_cli(*args: str, cwd: Path, module: str = "pipeline.launch") -> subprocess.CompletedProcess:
    """Run a polyvec command line (``python -m module args``) in a subprocess, as a user would; the
    default module is what the ``polyvec`` command runs."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, capture_output=True, text=True,
                          env=env, timeout=900)


@pytest.fixture(scope="module")
def one_torch_thread():
    """torch on one thread for a module's tests: small tensors gain nothing from a second OpenMP
    thread, and on a busy 2-core machine every op then waits for a descheduled thread (seen: 30x slower)."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on (for a dask scheduler, or an address without one)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_dask_worker(address: str, timeout_s: float = 60.0) -> None:
    """Wait until the dask scheduler at ``address`` has a worker; fail the test after ``timeout_s``."""
    import time

    from distributed import Client

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with Client(address, timeout=5) as c:
                if c.scheduler_info()["workers"]:
                    return
        except OSError:
            pass
        if time.monotonic() > deadline:
            pytest.fail("dask scheduler/worker did not come up")
        time.sleep(0.5)


@pytest.fixture
def cli():
    """The :func:`run_cli` helper."""
    return run_cli


@pytest.fixture
def compose_cfg():
    """Compose the polyvec Hydra config with overrides, as the CLI would."""
    from hydra import compose, initialize_config_module

    def _compose(*overrides: str):
        with initialize_config_module(config_module="conf", version_base=None):
            return compose(config_name="config", overrides=list(overrides))

    return _compose
