"""Stage registry: what each stage is called, what it reads, and where its code lives.

The DAG of one image (DESIGN.md)::

    prep ─┬─► keypoints ─► keypoint_edits ─┐
          └─► field ─┬─► graph ─► topology ◄┘
                     │     │         │
                     └─► extension ─► flow ─► select ─► export

(the graph's arrow goes to the flow, not to the extension).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from functools import lru_cache
from types import ModuleType


@dataclass(frozen=True)
class StageSpec:
    """Declaration of one stage.

    Attributes
    ----------
    name : str
        Stage name; also its config group and the folder of its artifacts.
    module : str
        Import path of the stage's package: ``STAGE_VERSION`` and the config dataclasses, light enough to
        import on every run; ``run`` (and a per-item stage's ``plan_items`` …) load lazily from its code
        (``<module>.stage``, :mod:`stages.lazy`), so a run whose artifacts are all stored imports none of
        the stages' code.
    inputs : tuple of str
        Upstream stages whose artifacts ``run`` receives as keyword arguments.
    persists : str
        What the artifact holds, for ``polyvec-inspect``.
    """

    name: str
    module: str
    inputs: tuple[str, ...]
    persists: str

    def load(self) -> ModuleType:
        """Import the stage's package (its code loads at the first use of ``run`` or another of its names)."""
        return _import(self.module)

    @property
    def version(self) -> str:
        """The stage's ``STAGE_VERSION`` (imports the package, not the code)."""
        return str(self.load().STAGE_VERSION)


STAGES: tuple[StageSpec, ...] = (
    StageSpec("prep", "stages.prep", (), "zarr: grey, mask"),
    StageSpec("keypoints", "stages.keypoints", ("prep",), "zarr: 4 heatmaps; JSON: typed points"),
    StageSpec("keypoint_edits", "stages.keypoint_edits", ("keypoints",),
              "zarr: edited points, types, scores; JSON: typed points and the edit log"),
    StageSpec("field", "stages.field", ("prep",), "zarr: c0, c2, roots, singular cells, smart weights"),
    StageSpec("extension", "stages.extension", ("prep", "field"), "zarr: the field extended beyond the band"),
    StageSpec("graph", "stages.graph", ("prep", "field"), "zarr: vertices, edges, streamlines"),
    StageSpec("topology", "stages.topology", ("prep", "field", "graph", "keypoint_edits"),
              "JSON: candidate paths; zarr: pixel coverage"),
    StageSpec("flow", "stages.flow", ("prep", "extension", "graph", "topology"), "zarr: flowed polylines; JSON: energies"),
    StageSpec("select", "stages.select", ("prep", "topology", "flow"), "JSON: chosen curves"),
    StageSpec("export", "stages.export", ("prep", "topology", "flow", "select"), "SVG + curves JSON"),
)

BY_NAME = {s.name: s for s in STAGES}


@lru_cache(maxsize=None)
def _import(module: str) -> ModuleType:
    return importlib.import_module(module)


class StageUnavailable(RuntimeError):
    """A stage's package or code is missing or lacks ``run``/``STAGE_VERSION``: the install is broken."""


def check_stage(spec: StageSpec, code: bool = False) -> None:
    """Check that a stage's package exposes ``run`` and ``STAGE_VERSION``; with ``code``, import its code too.

    A stage is never silently left out of the DAG: that would let a broken install write artifacts
    and SVGs of a different pipeline. Every run checks the packages (light: ``STAGE_VERSION`` and the
    configs); the engine checks the code (numba, scipy …) of the stages that have work to do
    before it runs any, so a stage that cannot load fails the run once, not each image.

    Raises
    ------
    StageUnavailable
        The package (or, with ``code``, its code) cannot be imported, or lacks ``run`` or ``STAGE_VERSION``.
    """
    try:
        mod = spec.load()
        # dir() lists the lazy names without importing the code; hasattr() imports it.
        missing = [a for a in ("run", "STAGE_VERSION") if not (hasattr(mod, a) if code else a in dir(mod))]
    except ImportError as exc:
        raise StageUnavailable(f"stage {spec.name}: cannot import {spec.module} ({exc}); reinstall polyvec") from None
    if missing:
        raise StageUnavailable(f"stage {spec.name}: {spec.module} has no {' or '.join(missing)}")


def ancestors(name: str) -> set[str]:
    """All stages whose artifacts ``name`` depends on, directly or through others."""
    out: set[str] = set()
    todo = list(BY_NAME[name].inputs)
    while todo:
        s = todo.pop()
        if s not in out:
            out.add(s)
            todo.extend(BY_NAME[s].inputs)
    return out


@lru_cache(maxsize=None)
def height(name: str) -> int:
    """Stages on the longest path from ``name`` to the end of the DAG, ``name`` included (export: 1).

    The engine runs the stages with the most work still behind them first (:func:`pipeline.engine.execute.dask_cluster.priority`).
    """
    below = [s.name for s in STAGES if name in s.inputs]
    return 1 + max((height(b) for b in below), default=0)


def active_stages(until: str | None = None) -> list[StageSpec]:
    """Stages to run, in topological order.

    Every stage up to ``until`` runs (a stage that cannot be loaded is an error, never skipped).

    Parameters
    ----------
    until : str, optional
        Last stage wanted: only it and its ancestors run.

    Raises
    ------
    StageUnavailable
        A wanted stage's module is missing or incomplete.
    """
    wanted = set(BY_NAME)
    if until:
        if until not in BY_NAME:
            raise ValueError(f"unknown stage {until!r}; stages: {', '.join(BY_NAME)}")
        wanted = {until} | ancestors(until)
    out: list[StageSpec] = []
    for spec in STAGES:
        if spec.name in wanted:
            check_stage(spec)
            out.append(spec)
    return out
