"""Batch runner: one dask task per (image, stage), skipping every task whose artifact is stored.

All keys are computed up front in the driver (they depend only on the image bytes and the config),
so cached stages never reach the scheduler. Workers load their inputs from the store, run the stage,
write the artifact and hand back only a small :class:`TaskResult`. A failing image records its error
and its downstream tasks are skipped; the other images carry on.
"""

from __future__ import annotations

import functools
import gc
import json
import os
import resource
import signal
import socket
import sys
import threading
import time
import traceback
from collections import OrderedDict
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

from pipeline import kernels, warmup
from pipeline.launch import THREAD_ENV, take_early
from pipeline.registry import BY_NAME, StageSpec, active_stages, check_stage, height
from pipeline.store import ArtifactStore, adopt_library_versions, artifact_key, hash_bytes, item_keys, library_versions
from stages.errors import InputError


@dataclass(frozen=True)
class Task:
    """One (image, stage) unit of work."""

    image: str
    image_key: str
    stage: str
    version: str
    key: str
    inputs: dict[str, str]
    config: dict
    source: str = ""  # the image as an absolute path: a worker may run in another directory


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


@dataclass
class BatchResult:
    """Outcome of a batch: per image, per stage."""

    results: dict[str, dict[str, TaskResult]] = field(default_factory=dict)
    stages: list[str] = field(default_factory=list)
    outputs: dict[str, list[str]] = field(default_factory=dict)
    #: Image → why its output files could not be written (:func:`write_outputs`).
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


# -- planning ----------------------------------------------------------------------------------
def stage_config(cfg: Any, stage: str) -> dict:
    """The plain-dict config section of a stage (empty when the group has no file)."""
    from omegaconf import DictConfig, OmegaConf

    section = cfg.get(stage) if hasattr(cfg, "get") else None
    if section is None:
        return {}
    if isinstance(section, DictConfig):
        return OmegaConf.to_container(section, resolve=True)
    return dict(section)


def plan(images: Iterable[str | Path], cfg: Any, stages: list[StageSpec]) -> list[list[Task]]:
    """Tasks of every image, in topological order, with their content-addressed keys.

    The ``keypoint_edits`` config is per image: the parsed edits file that applies to it
    (:func:`pipeline.edits.stage_config`).

    Raises
    ------
    pipeline.edits.EditsError
        When an image's keypoint edits file is unreadable or malformed.
    """
    from pipeline import edits

    out = []
    configs = {s.name: stage_config(cfg, s.name) for s in stages}
    for image in images:
        image = str(image)
        if "keypoint_edits" in configs:  # per image: the parsed <stem>.keypoints.json (edits.EditsError)
            configs["keypoint_edits"] = edits.stage_config(image, stage_config(cfg, "keypoint_edits"))
        try:
            image_key = hash_bytes(Path(image).read_bytes())
        except OSError as exc:
            image_key = "unreadable-" + hash_bytes(f"{image}:{exc}".encode())
        keys = {"image": image_key}
        tasks = []
        for s in stages:
            inputs = {"image": image_key} if not s.inputs else {i: keys[i] for i in s.inputs}
            keys[s.name] = artifact_key(s.name, s.version, configs[s.name], inputs)
            tasks.append(Task(image, image_key, s.name, s.version, keys[s.name], inputs, configs[s.name],
                              str(Path(image).absolute())))
        out.append(tasks)
    return out


# -- execution (runs inside workers) -----------------------------------------------------------
_STORES: dict[str, ArtifactStore] = {}


def _store(url: str) -> ArtifactStore:
    if url not in _STORES:
        _STORES[url] = ArtifactStore(url)
    return _STORES[url]


#: Young (generation-1) collections per full one in a process that runs stages; CPython's default is 10.
#: A full collection scans every live object: after hydra's, numba's and the stages' imports (~200,000
#: objects) each took ~0.1 s and found 10–90 unreachable objects. Six of them cost ~0.6 s of the
#: elephant's default run and four ~0.3 s of its λ re-run (stages/DECISIONS.md, engine). Young garbage
#: is still collected as often as before.
FULL_COLLECTION_EVERY = 1000


def quiet_full_collections() -> None:
    """Make full garbage collections rare in this process (:data:`FULL_COLLECTION_EVERY`)."""
    young, middle, _ = gc.get_threshold()
    gc.set_threshold(young, middle, FULL_COLLECTION_EVERY)


#: glibc's malloc serves a request of this many bytes or more with a fresh ``mmap`` and unmaps it on
#: ``free``, so the next array of that size is faulted in again page by page (the kernel zeroing
#: each page). Its threshold adapts from 128 KiB up to 32 MiB — unless a trim threshold is set, as dask
#: does in its workers (``MALLOC_TRIM_THRESHOLD_=65536``), which freezes it at 128 KiB: a 2-worker batch
#: of 8 drawings spent 3.5–4.8 of each worker's 13–14 CPU seconds in the kernel, 0.7–1.2 with this
#: (stages/DECISIONS.md, engine). 32 MiB, the largest glibc accepts on 64-bit, keeps a 2-Mpx
#: drawing's float64 arrays (16 MiB) in the heap.
HEAP_MMAP_BYTES = 32 * 2**20
#: Free memory at the top of the heap kept for the next array instead of given back: as much as the
#: largest array the heap serves (a worker's peak RSS on 24 drawings 707–728 → 823–872 MB; 256 MiB
#: gave 910 MB for no measurable time).
HEAP_TRIM_BYTES = 32 * 2**20
#: The keypoints child's trim threshold (:func:`keep_network_memory`): more than the network's
#: activations freed at once in one pass of a drawing of ``keypoints.single_pass_max`` px.
NETWORK_TRIM_BYTES = 2**30
_HEAP_TUNED = False
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -3, -4      # glibc's <malloc.h>


@functools.lru_cache(maxsize=1)
def _mallopt():
    """glibc's ``mallopt`` (None where the C library has none: not glibc); looked up once."""
    import ctypes

    try:  # the symbols already loaded into this process, the C library's among them
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):  # no mallopt (macOS), no CDLL(None) (Windows)
        return None
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    return mallopt


def reuse_freed_memory() -> None:
    """Make glibc's malloc keep freed arrays' memory for the next ones (:data:`HEAP_MMAP_BYTES`,
    :data:`HEAP_TRIM_BYTES`) in this process. Once per process; nothing where the C library has no
    ``mallopt`` (not glibc)."""
    global _HEAP_TUNED
    if _HEAP_TUNED:
        return
    _HEAP_TUNED = True
    if (mallopt := _mallopt()) is not None:
        mallopt(_M_MMAP_THRESHOLD, HEAP_MMAP_BYTES)
        mallopt(_M_TRIM_THRESHOLD, HEAP_TRIM_BYTES)


def keep_network_memory() -> None:
    """Serve every allocation of this process from the heap and keep up to :data:`NETWORK_TRIM_BYTES`
    of freed memory: for the keypoints child, whose network frees and allocates full-resolution
    activations layer after layer. At 704² a 32-channel map is 63 MB, above the 32-MiB ceiling of
    glibc's mmap threshold, so each was a fresh mapping faulted in page by page (54–139 k faults a
    pass; stages/DECISIONS.md, engine). A process's first pass faults its peak in either way; the
    passes after it (a multi-drawing run, a large drawing's tiles) reuse it. The child's memory stays
    at its peak until it exits."""
    reuse_freed_memory()
    if (mallopt := _mallopt()) is not None:
        mallopt(_M_MMAP_MAX, 0)
        mallopt(_M_TRIM_THRESHOLD, NETWORK_TRIM_BYTES)


def _pin_threads(alone: bool = False) -> None:
    """One thread per task for torch and numba (worker processes also get THREAD_ENV at spawn).

    ``alone``: the task is the only one running (in-process): the flow may share its paths among
    ``numba.get_num_threads()`` threads (its results do not depend on their number); torch
    stays at one (the keypoints stage sets its own ``torch_threads``). NUMBA_NUM_THREADS is never
    changed in a running process: numba re-reads its environment when it compiles and refuses a
    value that differs from the thread pool it already launched.
    """
    # getattr: in-process, another task's thread may be importing torch or numba right now (the module
    # is in sys.modules before it is initialised); that task pins its own threads when it runs.
    set_torch = getattr(sys.modules.get("torch"), "set_num_threads", None)
    if set_torch is not None:
        set_torch(1)
    numba = sys.modules.get("numba")
    set_numba, config = getattr(numba, "set_num_threads", None), getattr(numba, "config", None)
    if set_numba is not None and config is not None:
        set_numba(config.NUMBA_NUM_THREADS if alone else 1)


# Artifacts recently loaded or written by this process, by (stage, key). They are immutable (a key
# names its content), so a chain of stages in one process — a λ re-run in-process, or a worker that
# gets an image's next stage — reuses them instead of reading zarr and re-parsing JSON (topology's
# paths are megabytes of JSON read by flow, select and export). Arrays are made read-only so that a
# stage that modified its input in place would fail loudly instead of corrupting the next stage's.
# Bounded by count and by array bytes, so a batch of large scans cannot pile up gigabytes per worker.
_MEMO: "OrderedDict[tuple[str, str], Any]" = OrderedDict()
_MEMO_LOCK = threading.Lock()  # the in-process scheduler runs two tasks at once (threads)
# 48, not 12: a batch runs several images' stages side by side (:func:`priority`), and with 12 their
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

    ``alone``: no other task runs beside this one (the in-process scheduler), see :func:`_pin_threads`.
    """
    from stages.errors import InputError

    for up in upstream:
        if up.status in ("failed", "skipped"):
            return TaskResult(task.image, task.stage, task.key, "skipped", error=f"upstream {up.stage} failed")
    store = _store(store_url)
    if store.exists(task.stage, task.key):
        return TaskResult(task.image, task.stage, task.key, "cached")
    _pin_threads(alone)
    quiet_full_collections()      # a dask worker or the keypoints child: this process runs stages
    reuse_freed_memory()
    t0 = time.perf_counter()
    try:
        spec = BY_NAME[task.stage]
        module = spec.load()
        kernels.load_without_registries(task.stage)
        source = Path(task.source or task.image)
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
        return TaskResult(task.image, task.stage, task.key, "failed", error=str(exc),
                          duration_s=time.perf_counter() - t0)
    except MemoryError:
        return TaskResult(task.image, task.stage, task.key, "failed", error="out of memory",
                          duration_s=time.perf_counter() - t0)
    except Exception as exc:  # noqa: BLE001 - one bad image must not sink the batch
        return TaskResult(task.image, task.stage, task.key, "failed",
                          error=f"internal error in stage {task.stage}: {type(exc).__name__}: {exc}",
                          detail=traceback.format_exc(), duration_s=time.perf_counter() - t0)


# -- schedulers --------------------------------------------------------------------------------
class ClusterError(RuntimeError):
    """The dask scheduler cannot be reached, or its workers cannot reach the store (before any work)."""


def check_store_reachable(client, store: ArtifactStore) -> None:
    """Refuse a store the cluster's workers cannot see: a marker written here must exist for each worker.

    Raises
    ------
    ClusterError
        A worker does not see the marker (a local path on another machine, a ``memory://`` store).
    """
    import uuid

    marker = f".reach-{uuid.uuid4().hex}"
    with store.fs.open(store._join(marker), "wb") as f:
        f.write(b"polyvec")
    try:
        seen = client.run(_sees_marker, store.url, marker)
    finally:
        store.fs.rm(store._join(marker))
    blind = sorted(w for w, ok in seen.items() if not ok)
    if blind:
        raise ClusterError(f"store {store.url} is not reachable from {len(blind)} of {len(seen)} dask workers "
                           f"(e.g. {blind[0]}): put store.path on a shared file system or an fsspec URL")


def _sees_marker(url: str, marker: str) -> bool:
    import fsspec

    try:
        fs, root = fsspec.core.url_to_fs(url)
        return bool(fs.exists(os.path.join(root, marker) if fs.protocol in ("file", ("file", "local"))
                              else f"{root.rstrip('/')}/{marker}"))
    except Exception:  # noqa: BLE001 - a worker that cannot even open the URL does not see it
        return False


_CLIENT: Any = None
_CLIENT_SPEC: tuple | None = None


@contextmanager
def _sigint_held():
    """Ctrl-C held back while this thread starts worker processes, then raised once.

    SIGINT is blocked in this thread, so that the processes it starts and the threads it starts
    meanwhile (dask's event loop, which starts the nannies) inherit it blocked: the terminal sends
    Ctrl-C to the whole process group, and each worker would print its own tracebacks; the driver
    reports the interrupt once and shuts them down. A Ctrl-C pressed meanwhile (pending, or taken by
    an older thread of this process and recorded by a handler that only notes it) is raised as
    KeyboardInterrupt when the block ends. SIGINT used to be *ignored* here, which the workers
    inherited as well but which dropped a Ctrl-C pressed while a local cluster started: a folder's
    run went on to its end (stages/DECISIONS.md, engine). Elsewhere than the main thread, a no-op.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    # multiprocessing starts its resource tracker at the first spawn and *unblocks* SIGINT in the
    # spawning thread afterwards: started before the block, it leaves the block alone
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    pressed = []
    handler = signal.signal(signal.SIGINT, lambda signum, frame: pressed.append(signum))
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        if signal.SIGINT in signal.sigpending():
            signal.sigwait({signal.SIGINT})
            pressed.append(signal.SIGINT)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        # None: a handler not set from Python (embedding); Python's own is the sensible one back
        signal.signal(signal.SIGINT, handler if handler is not None else signal.default_int_handler)
    if pressed and handler is not signal.SIG_IGN:
        raise KeyboardInterrupt


def get_client(runtime: dict):
    """A dask.distributed client: a local cluster of single-threaded processes, or a remote scheduler.

    The client is kept for the life of the process, so Hydra multirun jobs share one cluster.
    """
    global _CLIENT, _CLIENT_SPEC
    import dask
    from distributed import Client, LocalCluster

    address = runtime["scheduler_address"]
    spec = (address, runtime["workers"], runtime["memory_limit"])
    if _CLIENT is not None and _CLIENT_SPEC == spec and _CLIENT.status == "running":
        return _CLIENT
    close_client()
    if address:
        try:
            client = Client(address, timeout=runtime["connect_timeout_s"])
        except (OSError, TimeoutError) as exc:
            raise ClusterError(f"cannot reach the dask scheduler at {address} ({type(exc).__name__})") from None
        _CLIENT, _CLIENT_SPEC = client, spec
        return client
    # The workers leave Ctrl-C to the driver; one pressed meanwhile is raised once the client is
    # registered, so that the usual clean-up (close_client) ends this cluster too.
    with _sigint_held():
        # dashboard_address=":0": a free port. None means dask's default 8787, with a warning whenever
        # another dask runs on the machine.
        # Saturation inf: every task goes to a worker once it is ready, so that the workers run the
        # engine's priorities (:func:`priority`); dask's default queues root tasks (prep) on the
        # scheduler and releases them only when a worker runs out of work. Our tasks return small
        # records (the artifacts go to the store), so the queue's memory guard is not needed.
        # No statistical profiler in the workers: it samples every thread's stack each 10 ms, under
        # the GIL the task needs, for a dashboard page no one opens here (a worker's event-loop
        # thread 0.9 -> 0.65 CPU-s in an 8-drawing batch; stages/DECISIONS.md, engine).
        with dask.config.set({"distributed.scheduler.worker-saturation": float("inf"),
                              "distributed.worker.profile.enabled": False}):
            cluster = LocalCluster(n_workers=int(runtime["workers"]), threads_per_worker=1, processes=True,
                                   dashboard_address=":0", memory_limit=runtime["memory_limit"],
                                   env=dict(THREAD_ENV), silence_logs=50)
        client = Client(cluster)
        # Our own worker processes only: a remote scheduler's workers are not ours to end this way.
        client.run(exit_without_teardown_at_exit)
        _CLIENT, _CLIENT_SPEC = client, spec
    return client


def exit_without_teardown_at_exit() -> None:
    """Make this (local-cluster worker) process leave without the interpreter's teardown.

    A worker that ran the stages holds torch, numba and scipy; when the cluster closes, Python's
    finalisation of those modules took about 1 s (a 2-worker batch of 8 drawings: ``cluster.close()``
    1.03 s of its 15.5 s), spent after every task was done and every artifact written. Registered
    when the cluster starts, before any task imports a stage, the hook runs after the exit handlers
    those imports add (they run last-registered first) and before the modules are torn down: it
    flushes the standard streams and ends the process with status 0 once the worker has closed.
    """
    import atexit

    atexit.register(_exit_now)


def _exit_now() -> None:
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more can reach it
            pass
    os._exit(0)


def close_client() -> None:
    """Shut the cached client (and its local cluster) down."""
    global _CLIENT, _CLIENT_SPEC
    if _CLIENT is not None:
        cluster = getattr(_CLIENT, "cluster", None)
        try:
            _CLIENT.close()
            if cluster is not None:
                cluster.close()
        except Exception:  # noqa: BLE001 - best effort at shutdown
            pass
    _CLIENT, _CLIENT_SPEC = None, None


def validated_stages(cfg) -> list:
    """The stages a run computes (``runtime.until``), after checking the config of each and of ``runtime``.

    Raises
    ------
    stages.errors.InputError
        A missing, unknown or ill-typed key, or a value out of its range.
    """
    from pipeline.schema import validate  # it imports this module

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
        compiled yet and no shipped ones fit this machine (:mod:`pipeline.kernels`): a first run that
        takes longer. Its argument says why, in words.

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
                report(per[t.stage])
            else:
                todo_final.append(t)
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
            child = _ChildTasks(in_child, configs, early=take_early())
        _end_early()   # not adopted: nothing for it in this process
        try:
            # Only now the code of the stages with work to do is imported (a stored artifact needs none).
            for spec in stages:
                if spec.name in todo:
                    check_stage(spec, code=True)
            if sync:
                _run_sync(pending, store.url, batch, report, in_child=in_child, child=child)
            else:
                client = get_client(runtime)
                if runtime["scheduler_address"]:
                    check_store_reachable(client, store)
                    if runtime["shipped_kernels"]:  # the workers' machines have numba caches of their own
                        client.run(kernels.install, sorted(todo))
                _run_dask(pending, store.url, batch, report, client)
        finally:
            if child is not None and child.proc.is_alive():  # a failed code check: _run_sync never ran
                child.close(kill=True)
                child.join()
            warmup.stop()  # nothing to stop unless in-process warm-ups were started
    else:
        _end_early()   # every artifact stored
    batch.wall_s = time.perf_counter() - t0
    return batch


def _end_early() -> None:
    """End the keypoints child ``polyvec`` forked before its imports, unless a run adopted it."""
    early = take_early()
    if early is not None:
        proc, conn = early
        proc.kill()
        conn.close()
        proc.join()


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
    beside its keypoints child (:func:`_run_sync`). With more images, more workers, and always with a
    ``scheduler_address``, it uses dask.
    """
    mode = runtime["cluster"]
    if mode != "auto":
        return mode
    if runtime.get("scheduler_address"):
        return "local"
    if len(pending) <= 1 or (len(pending) <= SYNC_MAX_IMAGES and int(runtime["workers"]) <= SYNC_THREADS):
        return "sync"
    return "local"


def _needed(t: Task, done: dict[str, TaskResult]) -> list[TaskResult]:
    spec = BY_NAME[t.stage]
    return [done[i] for i in spec.inputs if i in done and done[i].status != "cached"]


def _prep_pixels(store_url: str, key: str) -> int | None:
    """Pixels of a stored prep artifact's grey (from its manifest), None when it cannot be read."""
    try:
        shape = _store(store_url).manifest("prep", key)["arrays"]["grey"]["shape"]
        return int(shape[0]) * int(shape[1])
    except Exception:  # noqa: BLE001 - no such artifact (prep failed): the caller runs one task at a time
        return None


#: Stages an in-process run computes in its child process (``runtime.keypoints_process``): the
#: keypoints beside the field and graph, then the field's extension, which only the flow reads —
#: off the field → graph path of this process (stages/DECISIONS.md, engine).
CHILD_STAGES = ("keypoints", "extension")
#: Of those, the stages that need no torch: run on a thread of this process that would idle while the
#: child is busy (a small drawing's graph ends before its keypoints, and its extension waited for
#: them), and here alone when no other child stage has work (no child is started for them).
EITHER_STAGES = ("extension",)

#: Tasks the in-process scheduler runs at once (threads): an image's keypoints beside its field and
#: graph, which need only prep (torch, scipy and the graph kernels release the GIL in their work).
SYNC_THREADS = 2
#: ... for drawings of at most this many (prep) pixels; a larger one runs a task at a time in this
#: process, so that its peak memory stays that of its largest stage (a 6 Mpx scan: graph ≈ 3.4 GB, +
#: keypoints on a thread 4.0 GB); the keypoints child (``runtime.keypoints_process``) still runs beside it.
SYNC_PARALLEL_MAX_PIXELS = 4_000_000


class _ChildTasks:
    """A child process that runs the in-process scheduler's tasks of some stages (:data:`CHILD_STAGES`).

    Why: beside a keypoints thread (torch's import, then the network) the field and graph of the
    same drawing took 1.5× their time alone (the GIL and the interpreter between numpy calls), beside
    a keypoints process hardly more (stages/DECISIONS.md, engine). The child is spawned at once, with
    SIGINT blocked (Ctrl-C is the driver's to report, as for dask's workers), and imports the
    stages' code and preloads what they use (``configs``: each stage's config section, for its
    ``preload``) while the driver checks the code and runs prep. ``early``: instead, the child that
    ``polyvec`` forked before its own imports (:func:`pipeline.launch.take_early`), given ``configs``.
    """

    def __init__(self, stages: tuple[str, ...], configs: dict[str, dict] | None = None, early: tuple | None = None):
        import multiprocessing

        self.lock = threading.Lock()
        if early is not None:
            self.proc, self.conn = early
            try:
                self.conn.send(configs or {})
            except OSError:   # gone already: its first task reports it
                pass
            return
        ctx = multiprocessing.get_context("spawn")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_serve_tasks, args=(child, stages, configs or {}), daemon=True,
                                name="polyvec-" + "-".join(stages))
        try:
            with _sigint_held():
                self.proc.start()
        except KeyboardInterrupt:   # pressed while it started: nobody else holds it to end it
            self.proc.kill()
            self.proc.join()
            raise
        finally:
            child.close()

    def run(self, task: "Task", store_url: str, upstream: tuple) -> "TaskResult":
        """Run one task in the child; a lost child is this task's failure."""
        with self.lock:
            try:
                # the driver's library versions (its first task looked them up): the child's manifests
                # need the same, and it is spared the lookup on its critical path
                self.conn.send((task, store_url, upstream, library_versions()))
                return self.conn.recv()
            except (EOFError, OSError) as exc:
                return TaskResult(task.image, task.stage, task.key, "failed",
                                  error=f"worker lost: {type(exc).__name__}: {exc}")

    def close(self, kill: bool = False) -> None:
        """Let the child leave (it skips its interpreter's teardown), or kill it; does not wait."""
        if kill:
            self.proc.kill()
        else:
            try:
                self.conn.send(None)
            except OSError:
                pass
        self.conn.close()

    def join(self, timeout_s: float = 5.0) -> None:
        """Wait for the closed child to be gone (killed past ``timeout_s``): no process outlives the run."""
        self.proc.join(timeout_s)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join()


def _preload(modules: dict, configs: dict) -> None:
    """Each stage's ``preload(section)`` for the stages ``configs`` names (see :func:`_serve_tasks`)."""
    for name, mod in modules.items():
        if name in configs and "preload" in dir(mod):
            try:
                mod.preload(configs[name])
            except Exception:  # noqa: BLE001 - the task itself will fail with the clear message
                pass


def _serve_tasks(conn, stages: tuple[str, ...], configs: dict[str, dict] | None) -> None:
    """The child of :class:`_ChildTasks`: import the stages, preload what their tasks will use (a
    stage's ``preload(section)``, given its config section), then run tasks until told to stop.
    ``configs`` None (the child forked before the run was planned): a stage's ``preload(None)``
    imports what every config needs, then the first message brings the sections, or None to stop."""
    os.environ.update(THREAD_ENV)
    keep_network_memory()
    modules = {name: BY_NAME[name].load() for name in stages}
    try:
        if configs is None:
            _preload(modules, dict.fromkeys(modules))
            configs = conn.recv()
        if configs is not None:   # None: told to leave before any task
            _preload(modules, configs)
            while (message := conn.recv()) is not None:
                task, store_url, upstream, versions = message
                adopt_library_versions(versions)
                conn.send(execute(task, store_url, *upstream))
    except (EOFError, OSError):  # the driver is gone (Ctrl-C): nothing to report to
        pass
    os._exit(0)


def _run_sync(pending, store_url, batch, report, in_child: tuple[str, ...] = (),
              child: "_ChildTasks | None" = None) -> None:
    """Run the pending tasks in this process, at most :data:`SYNC_THREADS` at once, in DAG order.

    A task starts when the tasks of its image that it reads have finished; earlier images first. A
    task that starts with nothing else running or ready runs ``alone`` (numba may use its whole pool:
    the flow). Tasks of the stages ``in_child`` run in one child process (:class:`_ChildTasks`):
    ``child`` when given (:func:`run_batch` starts it early), else one started here when such a task
    is pending; those of :data:`EITHER_STAGES` run here instead while the child is busy and this
    process has nothing else to start, or when there is no child. On Ctrl-C no new task starts; the
    running ones finish (each writes its artifact whole) and the child is killed.
    """
    from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

    waiting = [(i, t) for i, tasks in enumerate(pending) for t in tasks]
    left_in_child = sum(t.stage in in_child for _, t in waiting)
    if child is None and any(t.stage in in_child and t.stage not in EITHER_STAGES for _, t in waiting):
        child = _ChildTasks(in_child)
    results = [batch.results[tasks[0].image] for tasks in pending]
    stages_of = [{t.stage for t in tasks} for tasks in pending]
    running: dict = {}

    def ready(i: int, t: Task) -> bool:
        return all(s in results[i] for s in BY_NAME[t.stage].inputs if s in stages_of[i])

    sizes: dict[int, int] = {}

    def parallel(i: int) -> bool:
        """Whether image i may run two tasks at once (its prep size is known once prep is done)."""
        if i not in sizes:
            pixels = _prep_pixels(store_url, results[i]["prep"].key) if "prep" in results[i] else None
            if pixels is None:
                return False
            sizes[i] = pixels
        return sizes[i] <= SYNC_PARALLEL_MAX_PIXELS

    def apart(there: bool) -> bool:
        """Whether a task run in the child (``there``) or here and every running task run in different
        processes: their memories do not add up in one process, so the size rule does not apply
        (stages/DECISIONS.md)."""
        return all(there != o_there for _, _, o_there in running.values())

    def work(i: int, t: Task, alone: bool, there: bool) -> TaskResult:
        if there:
            return child.run(t, store_url, _needed(t, results[i]))
        warmup.wait(t.stage)
        return execute(t, store_url, *_needed(t, results[i]), alone=alone)

    pool = ThreadPoolExecutor(max_workers=SYNC_THREADS, thread_name_prefix="polyvec-task")
    finished_cleanly = False
    try:
        while waiting or running:
            # earlier images first; of one image, the task with the most stages behind it (the graph
            # before an extension that would run on this process's free thread)
            startable = sorted(((i, t) for i, t in waiting if ready(i, t)),
                               key=lambda it: (it[0], -height(it[1].stage)))
            for pos, (i, t) in enumerate(startable):
                if len(running) >= SYNC_THREADS:
                    break
                child_busy = any(o_there for _, _, o_there in running.values())
                there = t.stage in in_child and child is not None
                if there and child_busy and t.stage in EITHER_STAGES:
                    # this process's own tasks before it in the order have started (or the loop broke)
                    if any(u.stage not in in_child for _, u in startable[pos + 1:]):
                        continue   # this process has its own stages to run: the child computes it later
                    there = False  # this thread would idle until the child is free
                if there and child_busy:
                    continue   # the child runs one task at a time: a thread waiting on it would idle
                if running and not (apart(there) or all(parallel(j) for j, _, _ in [*running.values(), (i, t, there)])):
                    break
                waiting.remove((i, t))
                alone = not running and len(startable) == 1
                running[pool.submit(work, i, t, alone, there)] = (i, t, there)
            finished, _ = wait(list(running), return_when=FIRST_COMPLETED)
            for fut in finished:
                i, t, _ = running.pop(fut)
                r = fut.result()
                results[i][t.stage] = r
                report(r)
                if t.stage in in_child:
                    left_in_child -= 1
                    if not left_in_child and child is not None:  # its memory (torch's) is not needed any more
                        child.close()
        finished_cleanly = True
    finally:
        # Interrupted: return at once (the running tasks end in their threads, each writing its
        # artifact whole, before the process exits); else every thread is idle already.
        pool.shutdown(wait=finished_cleanly, cancel_futures=True)
        if child is not None:
            if left_in_child:  # interrupted with keypoints tasks left
                child.close(kill=True)
            # The child leaves on its own soon after close(); the run returns once it is gone (a
            # test under load saw it still alive when run_batch returned).
            child.join()


#: The batch's last images whose tasks are run stage-first, all of them together (:func:`priority`).
TAIL_IMAGES = 8


def priority(stage: str, i: int, n: int) -> int:
    """Scheduling priority (higher first) of image ``i``'s ``stage`` task in a batch of ``n`` images.

    A task ranks by the stages still behind it (:func:`pipeline.registry.height`) less its image's
    place in the batch: images start in order and overlap, but each image's long branches
    (keypoints, field, graph) go before earlier images' short ends (select, export). Run image by
    image, the batch ended on one image's chain with the other worker idle; the last
    :data:`TAIL_IMAGES` images share one place, so the batch ends on short tasks of several
    (stages/DECISIONS.md, engine).
    """
    return height(stage) - min(i, max(0, n - TAIL_IMAGES))


def _run_dask(pending, store_url, batch, report, client) -> None:
    from distributed import as_completed

    futures = {}
    for i, tasks in enumerate(pending):
        per_future: dict[str, Any] = {}
        for t in tasks:
            deps = [per_future[s] for s in BY_NAME[t.stage].inputs if s in per_future]
            fut = client.submit(execute, t, store_url, *deps, key=f"{t.stage}-{i}-{t.key[:16]}", pure=False,
                                retries=0, priority=priority(t.stage, i, len(pending)))
            per_future[t.stage] = fut
            futures[fut] = t
    for fut in as_completed(list(futures)):
        t = futures[fut]
        try:
            r = fut.result()
        except Exception as exc:  # a worker died (segfault, OOM kill): record and carry on
            r = TaskResult(t.image, t.stage, t.key, "failed", error=f"worker lost: {type(exc).__name__}: {exc}")
        batch.results[t.image][t.stage] = r
        report(r)


# -- outputs -----------------------------------------------------------------------------------
def write_outputs(batch: BatchResult, store: ArtifactStore, output_dir: str | Path,
                  names: dict[str, str | Path] | None = None) -> dict[str, list[str]]:
    """Write ``<name>.svg``, ``<name>.json`` (and ``<name>.bezier.svg``) of every exported image.

    Parameters
    ----------
    batch : BatchResult
    store : ArtifactStore
    output_dir : path
    names : dict, optional
        Image → output path relative to ``output_dir`` without suffix (the CLI mirrors the input
        tree); by default the image's stem. A name is a function of its image alone, never of which
        other images failed.

    Returns
    -------
    dict
        Image → files written. An image whose files cannot be written is left out, its reason in
        ``batch.output_errors``.

    Raises
    ------
    ValueError
        When two images of the batch have the same name.
    """
    output_dir = Path(output_dir)
    names = {image: Path(names[image]) if names and image in names else Path(Path(image).stem)
             for image in batch.results}
    if len(set(names.values())) != len(names):
        raise ValueError("two images of the batch have the same output name")
    written: dict[str, list[str]] = {}
    for image, per in batch.results.items():
        r = per.get("export")
        if r is None or r.status not in ("computed", "cached"):
            continue
        art = load_artifact(store, "export", r.key)
        name = str(names[image])
        payload = {k: v for k, v in art.data.items() if k not in ("svg", "bezier_svg")}
        payload.update(source=str(image), artifact=r.key)
        texts = {output_dir / f"{name}.svg": art.data["svg"], output_dir / f"{name}.json": curves_json(payload)}
        if art.data.get("bezier_svg"):
            texts[output_dir / f"{name}.bezier.svg"] = art.data["bezier_svg"]
        where = (output_dir / name).parent
        try:
            where.mkdir(parents=True, exist_ok=True)
            for where, text in texts.items():
                _atomic_write(where, text)
        except OSError as exc:
            # one image's files (a sub-folder's name taken by a file, a full disk): its error line,
            # the other images' files still written; what it wrote stays (whole files only)
            batch.output_errors[image] = f"cannot write {where} ({exc.strerror or exc})"
            continue
        written[image] = [str(p) for p in texts]
    batch.outputs = written
    return written


def curves_json(payload: dict) -> str:
    """The curves JSON written beside each SVG: one top-level key per line, one list item per line.

    ``json.dumps(indent=…)`` streams through the pure-Python encoder (~0.1 s for the elephant's 93
    curves, a fifteenth of its λ re-run) and put every coordinate on a line of its own; here each line
    is one call of the C encoder, and a curve reads as one line.
    """
    lines = []
    for k, v in payload.items():
        if isinstance(v, list) and v:
            items = ",\n".join("  " + json.dumps(x) for x in v)
            lines.append(f" {json.dumps(k)}: [\n{items}\n ]")
        else:
            lines.append(f" {json.dumps(k)}: {json.dumps(v)}")
    return "{\n" + ",\n".join(lines) + "\n}\n"


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
