"""A batch: plan every (image, stage) task, skip the stored ones, run the rest on an executor.

All keys are computed up front in the driver (they depend only on the image bytes and the config,
:mod:`pipeline.engine.plan`), so cached stages never reach an executor. The executor — in-process
(:class:`~.in_process.InProcessExecutor`) or dask (:class:`~.dask_cluster.DaskExecutor`), chosen by
:func:`cluster_mode` — runs each task through :func:`~.node.execute`, which loads its inputs from the
store, runs the stage, writes the artifact and hands back only a small :class:`~.base.TaskResult`. A
failing image records its error and its downstream tasks are skipped; the other images carry on. A
task that failed on its input before (a junk file, a blank page: :meth:`~pipeline.engine.store.ArtifactStore.failure`)
is that failure again, found like a hit: nothing runs for its image.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

from pipeline.engine.config import stage_config, validate
from pipeline.engine.execute.base import BatchResult, Executor, TaskResult
from pipeline.engine.execute.child import CHILD_STAGES, EITHER_STAGES, ChildTasks
from pipeline.engine.execute.dask_cluster import DaskExecutor
from pipeline.engine.execute.early_child import end_early, take_early
from pipeline.engine.execute.in_process import SYNC_THREADS, InProcessExecutor
from pipeline.engine.kernels import shipped as kernels
from pipeline.engine.kernels import warmup
from pipeline.engine.plan import Task, plan
from pipeline.engine.registry import BY_NAME, active_stages, check_stage
from pipeline.engine.store import ArtifactStore


def validated_stages(cfg) -> list:
    """The stages a run computes (``runtime.until``), after checking the config of each and of ``runtime``.

    Raises
    ------
    stages.errors.InputError
        A missing, unknown or ill-typed key, or a value out of its range.
    """
    validate(cfg, ["runtime"])
    stages = active_stages(stage_config(cfg, "runtime")["until"])
    validate(cfg, [s.name for s in stages])  # every key present, none unknown, values in range
    return stages


def run_batch(images: list[str | Path], cfg: Any, on_result: Callable[[TaskResult], None] | None = None,
              store: ArtifactStore | None = None, on_compile: Callable[[str], None] | None = None) -> BatchResult:
    """Run the stage DAG over images through the content-addressed store.

    Parameters
    ----------
    images : list of path
        Image files.
    cfg : DictConfig or dict
        The full config (stage sections, ``store.path``, ``runtime``).
    on_result : callable, optional
        Called in the driver with every :class:`TaskResult` as it arrives (progress display).
    store : ArtifactStore, optional
        Defaults to ``ArtifactStore(cfg.store.path)``.
    on_compile : callable, optional
        Called once, before any work, when a stage with work to do has numba kernels that are not
        compiled yet and no shipped ones fit this machine (:mod:`pipeline.engine.kernels.shipped`): a
        first run that takes longer. Its argument says why, in words.

    Returns
    -------
    BatchResult
    """
    stages = validated_stages(cfg)
    runtime = stage_config(cfg, "runtime")
    store = store or ArtifactStore(cfg["store"]["path"])
    store.sweep_tmp()
    t0 = time.perf_counter()
    batch = BatchResult(stages=[s.name for s in stages])
    plans = plan(images, cfg, stages)
    report = on_result or (lambda r: None)

    pending: list[list[Task]] = []
    for tasks in plans:
        image = tasks[0].image if tasks else None
        per = batch.results.setdefault(image, {})
        todo_final = []
        for t in tasks:
            # A stored artifact is a hit even when an upstream one was evicted from the store.
            if store.exists(t.stage, t.key):
                per[t.stage] = TaskResult(t.image, t.stage, t.key, "cached")
            elif (up := next((i for i in BY_NAME[t.stage].inputs
                              if i in per and per[i].status in ("failed", "skipped")), None)) is not None:
                per[t.stage] = TaskResult(t.image, t.stage, t.key, "skipped", error=f"upstream {up} failed")
            elif (all(per.get(i) is not None for i in BY_NAME[t.stage].inputs)
                  and (failure := store.failure(t.stage, t.key)) is not None):
                # failed on this very input and config before (store.save_failure): reported as a hit
                # is, no process started or stage imported for it. Looked up only where every input is
                # stored, as a failure needs them: a first run asks once per image, not once per task.
                per[t.stage] = TaskResult(t.image, t.stage, t.key, "failed", error=failure["error"], stored=True)
            else:
                todo_final.append(t)
                continue
            report(per[t.stage])
        if todo_final:
            pending.append(todo_final)

    if pending:
        todo = {t.stage for tasks in pending for t in tasks}
        sync = cluster_mode(runtime, pending) == "sync"
        # Every kernel in numba's cache (each run but a first): no copy and no second look here.
        cold = warmup.uncompiled(sorted(todo))
        if cold and kernels.forget_stale(cold):  # indexes of kernels an edit moved: not a cache, not cold
            cold = warmup.uncompiled(cold)
        if cold and runtime["shipped_kernels"]:
            kernels.install(cold)
            cold = warmup.uncompiled(cold)
        if on_compile is not None and cold:
            on_compile(kernels.why_compiled(cold) if runtime["shipped_kernels"] else "runtime.shipped_kernels=false")
        if sync:
            # One image in-process leaves a core idle: its graph and flow kernels (first run only)
            # compile there meanwhile. Started before the code check below (~0.7 s of imports): the
            # graph's warm-up is the first run's critical path.
            warmup.start(sorted(todo))
        in_child = CHILD_STAGES if sync and runtime["keypoints_process"] else ()
        # The child starts before the code check below, so that its own imports (torch) and the
        # networks' weights load on the other core meanwhile; the one `polyvec` forked before its
        # own imports is adopted (stages/DECISIONS.md, engine).
        child = None
        if todo & (set(in_child) - set(EITHER_STAGES)):
            configs = {name: stage_config(cfg, name) for name in in_child}
            child = ChildTasks(in_child, configs, early=take_early())
        end_early()   # not adopted: nothing for it in this process
        try:
            # Only now the code of the stages with work to do is imported (a stored artifact needs none).
            for spec in stages:
                if spec.name in todo:
                    check_stage(spec, code=True)
            executor: Executor = (InProcessExecutor(in_child, child) if sync
                                  else DaskExecutor.connect(runtime, store, sorted(todo)))
            executor.run(pending, store.url, batch, report)
        finally:
            if child is not None and child.proc.is_alive():  # a failed code check: the executor never ran
                child.close(kill=True)
                child.join()
            warmup.stop()  # nothing to stop unless in-process warm-ups were started
    else:
        end_early()   # every artifact stored
    batch.wall_s = time.perf_counter() - t0
    return batch


#: ``runtime.cluster: auto`` runs a batch in-process when at most this many images have work left
#: (and ``runtime.workers`` is at most :data:`SYNC_THREADS`): two to four 512² drawings 7.0–15.9 s
#: in-process against 11.0–17.4 s on two local workers, four scanned ones 20.9 s against 24.6–26.1 s;
#: six to eight about even, twelve 5 % slower (stages/DECISIONS.md, engine).
SYNC_MAX_IMAGES = 4


def cluster_mode(runtime: dict, pending: list[list[Task]]) -> str:
    """``sync`` or ``local`` (dask) for this batch's pending tasks.

    ``runtime.cluster: auto`` runs in-process when at most :data:`SYNC_MAX_IMAGES` images have work
    left — one drawing, a λ / time-step re-run (flow → select → export), a few drawings — and
    ``runtime.workers`` asks for no more processes than the in-process scheduler's threads: worker
    processes each import torch, numba and the stages (~4 CPU-s apiece) and hand tasks over through
    dask, which a few drawings do not repay; the in-process scheduler already runs two tasks at once
    beside its keypoints child (:class:`~.in_process.InProcessExecutor`). With more images, more
    workers, and always with a ``scheduler_address``, it uses dask.
    """
    mode = runtime["cluster"]
    if mode != "auto":
        return mode
    if runtime.get("scheduler_address"):
        return "local"
    if len(pending) <= 1 or (len(pending) <= SYNC_MAX_IMAGES and int(runtime["workers"]) <= SYNC_THREADS):
        return "sync"
    return "local"
