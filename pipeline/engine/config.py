"""Structured configs: every config group is the dataclass its code reads, registered with Hydra.

Each stage declares its parameters as one dataclass (``stages.<stage>.<Stage>Config``, fields without
defaults: the values live in ``conf/<stage>/default.yaml`` only). :func:`register` (called by
``conf/__init__.py``, which Hydra imports before it composes) stores each one in Hydra's ConfigStore
as ``<group>_schema``, and the app configs (``conf/config.yaml``, ``train_app.yaml``) put it first in
the group, so composing the YAML onto it checks every key and type: an unknown key (in a file or an
override) or a value of the wrong type is an error at start-up, and a key the file lacks is reported
by :func:`validate`.

Every start-up imports this module (``conf/__init__.py``, the batch's :func:`validate`), so what it
imports stays light, Hydra only in :func:`register`: a stage's package holds its dataclasses, not its
code (:mod:`stages.lazy`), and the training's and the bench's dataclasses are in light modules too
(:mod:`stages.keypoints.training.config`, :mod:`stages.evaluate`); ``tests/pipeline/test_cli.py``
checks that a cached run imports no numba, scipy or torch, nor Hydra where its config is cached.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stages.config import from_section
from stages.errors import InputError
from stages.evaluate import BenchConfig
from stages.export import ExportConfig
from stages.extension import ExtensionConfig
from stages.field import FieldConfig
from stages.flow import FlowConfig
from stages.graph import GraphConfig
from stages.keypoint_edits import KeypointEditsConfig
from stages.keypoints import KeypointsConfig
from stages.keypoints.training.config import TrainConfig
from stages.prep import PrepConfig
from stages.select import SelectConfig
from stages.topology import TopologyConfig

#: The Hydra config folder: one group per stage (``conf/<stage>/default.yaml``) and the apps.
CONF_DIR = Path(__file__).resolve().parents[2] / "conf"


@dataclass
class RuntimeConfig:
    """The ``runtime`` config group (``conf/runtime/local.yaml``), one field per key: where tasks run."""

    cluster: str
    workers: int
    memory_limit: Any
    scheduler_address: str | None
    connect_timeout_s: float
    until: str | None
    progress: bool
    pages: bool
    debug: bool
    keypoints_process: bool
    shipped_kernels: bool

    def __post_init__(self) -> None:
        if self.cluster not in ("auto", "local", "sync"):
            raise InputError(f"runtime.cluster must be auto, local or sync, not {self.cluster!r}")


#: config group → the dataclass that mirrors it
SCHEMAS: dict[str, type] = {
    "prep": PrepConfig, "keypoints": KeypointsConfig, "keypoint_edits": KeypointEditsConfig,
    "field": FieldConfig, "extension": ExtensionConfig, "graph": GraphConfig, "topology": TopologyConfig, "flow": FlowConfig,
    "select": SelectConfig, "export": ExportConfig, "runtime": RuntimeConfig, "bench": BenchConfig,
    "train": TrainConfig,
}


def default_config(group: str) -> dict:
    """A config group's defaults, ``conf/<group>/default.yaml``, as a plain dict (empty without one)."""
    import yaml

    path = CONF_DIR / group / "default.yaml"
    return (yaml.safe_load(path.read_text()) or {}) if path.is_file() else {}


def stage_config(cfg: Any, stage: str) -> dict:
    """The plain-dict config section of a stage (empty when the group has no file)."""
    from omegaconf import DictConfig, OmegaConf

    section = cfg.get(stage) if hasattr(cfg, "get") else None
    if section is None:
        return {}
    if isinstance(section, DictConfig):
        return OmegaConf.to_container(section, resolve=True)
    return dict(section)


def register() -> None:
    """Store every schema in Hydra's ConfigStore as ``<group>_schema`` (idempotent; ``conf/__init__.py``
    calls it before Hydra composes: :func:`validate` alone needs no Hydra)."""
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    for group, cls in SCHEMAS.items():
        cs.store(name=f"{group}_schema", node=cls)


def validate(cfg: Any, groups: list[str] | None = None) -> None:
    """Build the dataclass of every group present in ``cfg`` (all of :data:`SCHEMAS` by default).

    Raises
    ------
    stages.errors.InputError
        On a missing, unknown or ill-typed key, or a value out of its range.
    """
    for group in groups if groups is not None else list(SCHEMAS):
        section = stage_config(cfg, group)
        if section:
            from_section(SCHEMAS[group], section, group)
