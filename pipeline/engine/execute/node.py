"""One task in isolation: load its inputs, run its stage, store its artifact (any process, any machine).

:func:`execute` is the only function that runs a stage; both executors call it, in this process, in
the keypoints child or in a dask worker. It reads the task's inputs from the store through a small
in-process memo of recent artifacts (:func:`load_artifact`), reuses a per-item stage's stored items
(:func:`run_per_item`: the flow's unchanged paths after a keypoint edit) and hands back only a small
:class:`~.base.TaskResult`: a failing image records its error and the batch carries on.
"""

from __future__ import annotations

import os
import resource
import socket
import sys
import threading
import time
import traceback
from collections import OrderedDict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.engine.execute.base import TaskResult
from pipeline.engine.execute.process import (pin_threads, quiet_full_collections, return_freed_memory,
                                             reuse_freed_memory)
from pipeline.engine.kernels import shipped as kernels
from pipeline.engine.registry import BY_NAME
from pipeline.engine.store import ArtifactStore, item_keys, library_versions
from stages.errors import InputError

if TYPE_CHECKING:   # annotations only: the keypoints child imports this module and needs no config schemas
    from pipeline.engine.plan import Task


_STORES: dict[str, ArtifactStore] = {}


def store_at(url: str) -> ArtifactStore:
    """This process's :class:`ArtifactStore` of ``url`` (one per URL and process)."""
    if url not in _STORES:
        _STORES[url] = ArtifactStore(url)
    return _STORES[url]


# Artifacts recently loaded or written by this process, by (stage, key). They are immutable (a key
# names its content), so a chain of stages in one process — a λ re-run in-process, or a worker that
# gets an image's next stage — reuses them instead of reading zarr and re-parsing JSON (topology's
# paths are megabytes of JSON read by flow, select and export). Arrays are made read-only so that a
# stage that modified its input in place would fail loudly instead of corrupting the next stage's.
# Bounded by count and by array bytes, so a batch of large scans cannot pile up gigabytes per worker.
_MEMO: "OrderedDict[tuple[str, str], Any]" = OrderedDict()
_MEMO_LOCK = threading.Lock()  # the in-process scheduler runs two tasks at once (threads)
# 48, not 12: a batch runs several images' stages side by side (:func:`~.dask_cluster.priority`), and with 12 their
# inputs were read back from zarr (stage seconds +3 %, stages/DECISIONS.md). 48 artifacts of 512-px
# drawings hold ~200 MB of arrays (~33 MB per image), under the byte bound, which binds for larger ones.
MEMO_SIZE = 48
MEMO_BYTES = 256 * 2**20


def _remember(stage: str, key: str, artifact) -> None:
    for a in artifact.arrays.values():
        if hasattr(a, "flags"):
            a.flags.writeable = False
    if artifact.nbytes() > MEMO_BYTES:
        return
    with _MEMO_LOCK:
        _MEMO[(stage, key)] = artifact
        _MEMO.move_to_end((stage, key))
        total = sum(a.nbytes() for a in _MEMO.values())
        while len(_MEMO) > MEMO_SIZE or total > MEMO_BYTES:
            total -= _MEMO.popitem(last=False)[1].nbytes()


def load_artifact(store: ArtifactStore, stage: str, key: str):
    """``store.load`` through this process's memo of recent artifacts."""
    with _MEMO_LOCK:
        hit = _MEMO.get((stage, key))
        if hit is not None:
            _MEMO.move_to_end((stage, key))
            return hit
    artifact = store.load(stage, key)
    _remember(stage, key, artifact)
    return artifact


def run_per_item(module, task: Task, store: ArtifactStore, inputs: dict) -> tuple[Any, tuple[int, int]]:
    """Run a per-item stage (:class:`stages.artifact.ItemPlan`), reusing the items stored by earlier runs.

    After a keypoint correction most of the flow's paths are unchanged: their flowed curves are read
    back instead of flowed again. An item's key hashes its own arrays, the plan's context and the keys
    of the stage's ``ITEM_INPUTS``, so a reused result is the one the stage would compute, and the
    artifact is the one ``module.run`` gives, byte for byte (the stage's items are independent:
    tested). A missing or unreadable item is computed again.

    Parameters
    ----------
    module : module
        The stage, exposing ``ITEM_INPUTS``, ``plan_items``, ``run_items`` and ``assemble``.
    task : Task
    store : ArtifactStore
    inputs : dict
        The loaded input artifacts.

    Returns
    -------
    artifact : stages.artifact.Artifact
    items : tuple of int
        (items reused, items).
    """
    plan = module.plan_items(dict(task.config), **inputs)
    keys = item_keys(task.stage, task.version, plan.context, {i: task.inputs[i] for i in module.ITEM_INPUTS},
                     plan.items)
    results = store.load_items(task.stage, task.image_key, keys)
    missing = [i for i, r in enumerate(results) if r is None]
    if missing:
        fresh = dict(zip(missing, module.run_items(plan, missing)))
        store.save_items(task.stage, task.image_key, [(keys[i], r) for i, r in fresh.items()])
        results = [fresh.get(i, r) for i, r in enumerate(results)]
    return module.assemble(plan, results), (len(keys) - len(missing), len(keys))


def execute(task: Task, store_url: str, *upstream: TaskResult, alone: bool = False) -> TaskResult:
    """Run one task in a worker: load inputs, run the stage, store the artifact.

    ``alone``: no other task runs beside this one (the in-process scheduler), see :func:`~.process.pin_threads`.
    """
    for up in upstream:
        if up.status in ("failed", "skipped"):
            return TaskResult(task.image, task.stage, task.key, "skipped", error=f"upstream {up.stage} failed")
    store = store_at(store_url)
    if store.exists(task.stage, task.key):
        return TaskResult(task.image, task.stage, task.key, "cached")
    pin_threads(alone)
    quiet_full_collections()      # a dask worker or the keypoints child: this process runs stages
    reuse_freed_memory()
    try:
        return _run_task(task, store, source=Path(task.source or task.image))
    finally:
        return_freed_memory()     # the next task, maybe on another thread (arena), does not sit on it


def _run_task(task: Task, store: ArtifactStore, source: Path) -> TaskResult:
    """:func:`execute`'s work once the task is known to run: load, run, store; its result."""
    t0 = time.perf_counter()
    try:
        spec = BY_NAME[task.stage]
        module = spec.load()
        kernels.load_without_registries(task.stage)
        if task.stage == "prep":
            try:
                data = source.read_bytes()
            except IsADirectoryError:
                raise InputError("is a directory, not an image") from None
            except OSError as exc:
                if source.is_symlink() and not source.exists():
                    raise InputError(f"broken symbolic link (to {os.readlink(source)})") from None
                raise InputError(f"cannot read file ({exc.strerror or exc})") from None
            kwargs = {"image_bytes": data, "image_name": Path(task.image).name}
        else:
            kwargs = {name: load_artifact(store, name, key) for name, key in task.inputs.items()}
        items = None
        if hasattr(module, "plan_items"):
            artifact, items = run_per_item(module, task, store, kwargs)
        else:
            artifact = module.run(dict(task.config), **kwargs)
        duration = time.perf_counter() - t0
        manifest = {
            "stage": task.stage, "version": task.version, "key": task.key, "config": task.config,
            "inputs": task.inputs, "image": task.image_key, "image_name": Path(task.image).name,
            "image_path": str(source.resolve()), "duration_s": round(duration, 4),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
            "host": socket.gethostname(), "pid": os.getpid(), "libraries": library_versions(),
            "python": sys.version.split()[0],
        }
        if artifact.notes:
            manifest["warnings"] = list(artifact.notes)
        if items is not None:
            manifest["items"] = {"reused": items[0], "total": items[1]}
        store.save(task.stage, task.key, artifact, manifest)
        _remember(task.stage, task.key, artifact)
        return TaskResult(task.image, task.stage, task.key, "computed", duration_s=duration,
                          warnings=tuple(artifact.notes), items=items)
    except InputError as exc:
        _record_failure(store, task, str(exc))
        return TaskResult(task.image, task.stage, task.key, "failed", error=str(exc),
                          duration_s=time.perf_counter() - t0)
    except MemoryError:
        return TaskResult(task.image, task.stage, task.key, "failed", error="out of memory",
                          duration_s=time.perf_counter() - t0)
    except Exception as exc:  # noqa: BLE001 - one bad image must not sink the batch
        return TaskResult(task.image, task.stage, task.key, "failed",
                          error=f"internal error in stage {task.stage}: {type(exc).__name__}: {exc}",
                          detail=traceback.format_exc(), duration_s=time.perf_counter() - t0)


def _record_failure(store: ArtifactStore, task: Task, error: str) -> None:
    """File an input's failure under the task's key (:meth:`ArtifactStore.save_failure`): the same file
    and config fail the same way, so the next run reports it without running anything for the image.
    Only :class:`InputError` is recorded: an internal error may be a bug fixed in place, and memory or a
    lost worker may do better next time. A store that cannot take it costs the record, not the run."""
    try:
        store.save_failure(task.stage, task.key, {
            "stage": task.stage, "version": task.version, "key": task.key, "config": task.config,
            "inputs": task.inputs, "image": task.image_key, "image_name": Path(task.image).name,
            "error": error, "written_at": time.time()})
    except OSError:
        pass
