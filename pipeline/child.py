"""The in-process run's child process: the keypoints and the field's extension (:data:`CHILD_STAGES`)
beside this process's field and graph.

This module imports nothing but the standard library, so that ``polyvec`` can start the child
(:func:`start_early`) before it imports its own modules: the child's imports (torch, ~2 s of a
default run) then run on the other core while this process imports the CLI, composes the config
and plans the batch. :func:`pipeline.runner.run_batch` hands it its config sections
(:meth:`ChildTasks.adopt`) or stops it (stages/DECISIONS.md, engine).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from contextlib import contextmanager
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the runner's types; it imports this module
    from pipeline.runner import Task, TaskResult

#: One thread each for the numerical libraries of a process that runs beside another (dask's
#: workers, the child): read by them at import, so set before.
THREAD_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
              "NUMBA_NUM_THREADS": "1", "VECLIB_MAXIMUM_THREADS": "1"}

#: Stages an in-process run computes in its child process (``runtime.keypoints_process``): the
#: keypoints beside the field and graph, then the field's extension, which only the flow reads —
#: off the field → graph path of this process (stages/DECISIONS.md, engine).
CHILD_STAGES = ("keypoints", "extension")


@contextmanager
def sigint_held(tracker: bool = True):
    """Ctrl-C held back while this thread starts worker processes, then raised once.

    SIGINT is blocked in this thread, so that the processes it starts and the threads it starts
    meanwhile (dask's event loop, which starts the nannies) inherit it blocked: the terminal sends
    Ctrl-C to the whole process group, and each worker would print its own tracebacks; the driver
    reports the interrupt once and shuts them down. A Ctrl-C pressed meanwhile (pending, or taken by
    an older thread of this process and recorded by a handler that only notes it) is raised as
    KeyboardInterrupt when the block ends. SIGINT used to be *ignored* here, which the workers
    inherited as well but which dropped a Ctrl-C pressed while a local cluster started: a folder's
    run went on to its end (stages/DECISIONS.md, engine). Elsewhere than the main thread, a no-op.

    ``tracker``: start multiprocessing's resource tracker first (see below); False for a forked
    child, which never starts it.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    if tracker:
        # multiprocessing starts its resource tracker at the first spawn and *unblocks* SIGINT in
        # the spawning thread afterwards: started before the block, it leaves the block alone
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


class ChildTasks:
    """A child process that runs the in-process scheduler's tasks of some stages (:data:`CHILD_STAGES`).

    Why: beside a keypoints thread (torch's import, then the network) the field and graph of the
    same drawing took 1.5× their time alone (the GIL and the interpreter between numpy calls), beside
    a keypoints process hardly more (stages/DECISIONS.md, engine). The child starts with SIGINT
    blocked (Ctrl-C is the driver's to report, as for dask's workers), imports the stages' code and
    preloads what they use (``configs``: each stage's config section, for its ``preload``). Without
    ``configs`` it waits for them after its imports (:meth:`adopt`): the child :func:`start_early`
    starts.

    ``method``: multiprocessing's start method. ``fork`` only from a process that has no threads yet
    (:func:`start_early`); ``spawn`` otherwise.
    """

    def __init__(self, stages: tuple[str, ...], configs: dict[str, dict] | None = None, method: str = "spawn"):
        import multiprocessing

        ctx = multiprocessing.get_context(method)
        self.stages = stages
        self.conn, child = ctx.Pipe()
        self.lock = threading.Lock()
        # A forked child holds a copy of this end too: it closes it, or it would never see this
        # process go (its reads end when every copy of this end is closed).
        ours = self.conn if method == "fork" else None
        self.proc = ctx.Process(target=serve_tasks, args=(child, stages, configs, ours), daemon=True,
                                name="polyvec-" + "-".join(stages))
        try:
            with sigint_held(tracker=method != "fork"):
                self.proc.start()
        except KeyboardInterrupt:   # pressed while it started: nobody else holds it to end it
            self.proc.kill()
            self.proc.join()
            raise
        finally:
            child.close()

    def adopt(self, configs: dict[str, dict]) -> ChildTasks:
        """Give a child started without configs its stages' config sections (it preloads with them)."""
        try:
            self.conn.send(configs)
        except OSError:   # gone already: its first task reports it
            pass
        return self

    def run(self, task: Task, store_url: str, upstream: tuple) -> TaskResult:
        """Run one task in the child; a lost child is this task's failure."""
        from pipeline.runner import TaskResult

        with self.lock:
            try:
                self.conn.send((task, store_url, upstream))
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


def serve_tasks(conn, stages: tuple[str, ...], configs: dict[str, dict] | None, parents=None) -> None:
    """The child of :class:`ChildTasks`: import the stages, preload what their tasks will use (a
    stage's ``preload(section)``, given its config section; ``configs`` None: the first message
    brings them), then run tasks until told to stop. ``parents``: the driver's end of the pipe,
    inherited by a fork, closed here."""
    if parents is not None:
        parents.close()
    os.environ.update(THREAD_ENV)
    from pipeline.runner import BY_NAME, execute, keep_network_memory

    keep_network_memory()
    modules = {name: BY_NAME[name].load() for name in stages}
    try:
        if configs is None:
            configs = conn.recv()
        if configs is not None:
            for name, mod in modules.items():
                if name in configs and "preload" in dir(mod):
                    try:
                        mod.preload(configs[name])
                    except Exception:  # noqa: BLE001 - the task itself will fail with the clear message
                        pass
            while (message := conn.recv()) is not None:
                task, store_url, upstream = message
                conn.send(execute(task, store_url, *upstream))
    except (EOFError, OSError):  # the driver is gone (Ctrl-C): nothing to report to
        pass
    os._exit(0)


_EARLY: list[ChildTasks] = []


def start_early() -> None:
    """Start the child of :data:`CHILD_STAGES` now, before this process imports its own modules;
    :func:`take_early` hands it to the run. Forked on Linux (this process has no threads yet, so
    the fork is safe; a spawned child would first start an interpreter and import the CLI again),
    spawned elsewhere."""
    if not _EARLY:
        _EARLY.append(ChildTasks(CHILD_STAGES, method="fork" if sys.platform == "linux" else "spawn"))


def take_early() -> ChildTasks | None:
    """The child :func:`start_early` started, once (None when there is none or it is gone): the
    caller adopts it or closes it. One left untaken is ended at exit (multiprocessing ends its
    daemonic children)."""
    while _EARLY:
        child = _EARLY.pop()
        if child.proc.is_alive():
            return child
        child.close(kill=True)
    return None
