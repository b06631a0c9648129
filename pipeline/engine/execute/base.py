"""What the executors share: the records a task hands back, a batch's outcome, and the executor interface.

An executor runs a batch's pending tasks (those whose artifacts are not stored) in DAG order and
records each :class:`TaskResult` in the :class:`BatchResult`; the artifacts themselves go to the store
(:func:`pipeline.engine.execute.node.execute`). Two implement it: :class:`~.in_process.InProcessExecutor`
(threads of this process and the keypoints child) and :class:`~.dask_cluster.DaskExecutor`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Protocol

if TYPE_CHECKING:   # annotations only: the keypoints child imports this module and needs no config schemas
    from pipeline.engine.plan import Task



@dataclass
class TaskResult:
    """What a worker hands back: status and key, never the artifact itself."""

    image: str
    stage: str
    key: str
    status: str  # computed | cached | failed | skipped
    error: str | None = None
    detail: str | None = None
    duration_s: float = 0.0
    warnings: tuple[str, ...] = ()  # the artifact's guard notes (computed now; a cached one keeps them in its manifest)
    items: tuple[int, int] | None = None  # a per-item stage computed now: (items reused from the store, items)
    stored: bool = False  # a failure an earlier run recorded for this key (store.failure): not run again


@dataclass
class BatchResult:
    """Outcome of a batch: per image, per stage."""

    results: dict[str, dict[str, TaskResult]] = field(default_factory=dict)
    stages: list[str] = field(default_factory=list)
    outputs: dict[str, list[str]] = field(default_factory=dict)
    #: Image → why its output files could not be written (:func:`pipeline.engine.execute.outputs.write_outputs`).
    output_errors: dict[str, str] = field(default_factory=dict)
    wall_s: float = 0.0

    @property
    def failed_images(self) -> dict[str, str]:
        """Image → first error line, for images with a failed stage or output."""
        out = {}
        for image, per_stage in self.results.items():
            for stage in self.stages:
                r = per_stage.get(stage)
                if r is not None and r.status == "failed":
                    out[image] = f"{stage}: {r.error}"
                    break
            else:
                if image in self.output_errors:
                    out[image] = f"output: {self.output_errors[image]}"
        return out

    def counts(self) -> dict[str, dict[str, int]]:
        """Stage → status → count."""
        table: dict[str, dict[str, int]] = {s: {} for s in self.stages}
        for per_stage in self.results.values():
            for stage, r in per_stage.items():
                table[stage][r.status] = table[stage].get(r.status, 0) + 1
        return table

    def keys(self, image: str) -> dict[str, str]:
        """Stage → key of the stored artifacts of one image."""
        return {s: r.key for s, r in self.results.get(image, {}).items() if r.status in ("computed", "cached")}


class Executor(Protocol):
    """Runs the pending tasks of a batch (:func:`pipeline.engine.execute.batch.run_batch` picks one)."""

    def run(self, pending: list[list[Task]], store_url: str, batch: BatchResult,
            report: Callable[[TaskResult], None]) -> None:
        """Run every task of ``pending`` (one list per image, in DAG order) against the store at
        ``store_url``, record each result in ``batch.results[image][stage]`` and pass it to ``report``
        as it arrives. A failed task's downstream tasks are skipped; other images carry on."""
