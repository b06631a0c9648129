"""The dask executor: a local cluster of single-threaded worker processes, or a remote scheduler.

Chosen for a batch of more than a few drawings, more workers, and always with
``runtime.scheduler_address`` (:func:`~.batch.cluster_mode`). Every (image, stage) task is one dask
task running :func:`~.node.execute`, its upstream tasks its dependencies, ranked by
:func:`priority`; workers read and write the store themselves, so it must be reachable from each
(:func:`check_store_reachable`). The client is kept for the life of the process: a sweep's jobs share
one cluster.
"""

from __future__ import annotations

import os
import socket
import sys
from typing import Any, Callable

from pipeline.engine.execute.base import BatchResult, TaskResult
from pipeline.engine.execute.node import execute
from pipeline.engine.execute.process import THREAD_ENV, sigint_held
from pipeline.engine.kernels import shipped as kernels
from pipeline.engine.plan import Task
from pipeline.engine.registry import BY_NAME, height
from pipeline.engine.store import ArtifactStore


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


def check_scheduler_listening(address: str, timeout_s: float) -> None:
    """Refuse, at once, a TCP scheduler address where nothing listens or whose host is unknown.

    dask's ``Client`` retries a refused connection until its timeout (``runtime.connect_timeout_s``,
    30 s by default) and then names no cause; one plain connection tells a scheduler that is not
    there (refused: immediately) from one that is slow to answer (``timeout_s``). The scheduler
    logs this connection as closed before its handshake, one INFO line per run.

    Raises
    ------
    ClusterError
        ``address`` is malformed, nothing listens there, its host is unknown, or it does not answer
        within ``timeout_s``.
    """
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, location = parse_address(address)
        if scheme not in ("tcp", "tls"):  # inproc://, ucx://: dask's own connect decides
            return
        host, port = parse_host_port(location)
    except ValueError:
        raise ClusterError(f"{address!r} is not a dask scheduler address (tcp://HOST:PORT)") from None
    why = None
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except ConnectionRefusedError:
        why = "nothing listens there: start it with `dask scheduler`"
    except socket.gaierror:
        why = f"unknown host {host}"
    except TimeoutError:
        why = f"no answer within {timeout_s:g} s"
    except OSError as exc:
        why = exc.strerror or type(exc).__name__
    if why:
        raise ClusterError(f"cannot reach the dask scheduler at {address}: {why}")


_CLIENT: Any = None
_CLIENT_SPEC: tuple | None = None


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
        check_scheduler_listening(address, runtime["connect_timeout_s"])
        try:
            client = Client(address, timeout=runtime["connect_timeout_s"])
        except (OSError, TimeoutError) as exc:
            raise ClusterError(f"cannot reach the dask scheduler at {address} ({type(exc).__name__})") from None
        _CLIENT, _CLIENT_SPEC = client, spec
        return client
    # The workers leave Ctrl-C to the driver; one pressed meanwhile is raised once the client is
    # registered, so that the usual clean-up (close_client) ends this cluster too.
    with sigint_held():
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


#: The batch's last images whose tasks are run stage-first, all of them together (:func:`priority`).
TAIL_IMAGES = 8


def priority(stage: str, i: int, n: int) -> int:
    """Scheduling priority (higher first) of image ``i``'s ``stage`` task in a batch of ``n`` images.

    A task ranks by the stages still behind it (:func:`pipeline.engine.registry.height`) less its image's
    place in the batch: images start in order and overlap, but each image's long branches
    (keypoints, field, graph) go before earlier images' short ends (select, export). Run image by
    image, the batch ended on one image's chain with the other worker idle; the last
    :data:`TAIL_IMAGES` images share one place, so the batch ends on short tasks of several
    (stages/DECISIONS.md, engine).
    """
    return height(stage) - min(i, max(0, n - TAIL_IMAGES))


class DaskExecutor:
    """The :class:`~.base.Executor` of a dask.distributed cluster (:meth:`connect` makes one)."""

    def __init__(self, client):
        self.client = client

    @classmethod
    def connect(cls, runtime: dict, store: ArtifactStore, stages: list[str]) -> "DaskExecutor":
        """The executor of ``runtime``'s cluster (:func:`get_client`); a remote one's workers are checked
        to reach the store and get the shipped kernels of ``stages`` in their own numba caches.

        Raises
        ------
        ClusterError
            The scheduler cannot be reached, or its workers cannot reach the store.
        """
        client = get_client(runtime)
        if runtime["scheduler_address"]:
            check_store_reachable(client, store)
            if runtime["shipped_kernels"]:  # the workers' machines have numba caches of their own
                client.run(kernels.install, stages)
        return cls(client)

    def run(self, pending: list[list[Task]], store_url: str, batch: BatchResult,
            report: Callable[[TaskResult], None]) -> None:
        """Submit every task with its upstream futures and record the results as they complete; a
        lost worker (segfault, OOM kill) is its task's failure."""
        client = self.client
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
