"""The keypoints child: a process that runs the in-process executor's keypoints (and extension) tasks.

Beside a keypoints thread (torch's import, then the network) the field and graph of the same drawing
took 1.5× their time alone (the GIL and the interpreter between numpy calls), beside a keypoints
process hardly more (stages/DECISIONS.md, engine). :class:`ChildTasks` is the driver's end (spawned
here, or adopted from :mod:`.early_child`); :func:`serve_tasks` is the child's loop, which runs each
task through :func:`~.node.execute` and sends back its :class:`~.base.TaskResult`.
"""

from __future__ import annotations

import os
import threading
from typing import TYPE_CHECKING

from pipeline.engine.execute.base import TaskResult
from pipeline.engine.execute.node import execute
from pipeline.engine.execute.process import THREAD_ENV, keep_network_memory, sigint_held
from pipeline.engine.registry import BY_NAME
from pipeline.engine.store import adopt_library_versions, library_versions

if TYPE_CHECKING:   # annotations only: the keypoints child imports this module and needs no config schemas
    from pipeline.engine.plan import Task


#: Stages an in-process run computes in its child process (``runtime.keypoints_process``): the
#: keypoints beside the field and graph, then the field's extension, which only the flow reads —
#: off the field → graph path of this process (stages/DECISIONS.md, engine).
CHILD_STAGES = ("keypoints", "extension")
#: Of those, the stages that need no torch: run on a thread of this process that would idle while the
#: child is busy (a small drawing's graph ends before its keypoints, and its extension waited for
#: them), and here alone when no other child stage has work (no child is started for them).
EITHER_STAGES = ("extension",)


class ChildTasks:
    """A child process that runs the in-process scheduler's tasks of some stages (:data:`CHILD_STAGES`).

    Why: beside a keypoints thread (torch's import, then the network) the field and graph of the
    same drawing took 1.5× their time alone (the GIL and the interpreter between numpy calls), beside
    a keypoints process hardly more (stages/DECISIONS.md, engine). The child is spawned at once, with
    SIGINT blocked (Ctrl-C is the driver's to report, as for dask's workers), and imports the
    stages' code and preloads what they use (``configs``: each stage's config section, for its
    ``preload``) while the driver checks the code and runs prep. ``early``: instead, the child that
    ``polyvec`` forked before its own imports (:func:`~.early_child.take_early`), given ``configs``.
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
        self.proc = ctx.Process(target=serve_tasks, args=(child, stages, configs or {}), daemon=True,
                                name="polyvec-" + "-".join(stages))
        try:
            with sigint_held():
                self.proc.start()
        except KeyboardInterrupt:   # pressed while it started: nobody else holds it to end it
            self.proc.kill()
            self.proc.join()
            raise
        finally:
            child.close()

    def run(self, task: Task, store_url: str, upstream: tuple) -> TaskResult:
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


def serve_tasks(conn, stages: tuple[str, ...], configs: dict[str, dict] | None) -> None:
    """The child of :class:`ChildTasks`: import the stages, preload what their tasks will use (a
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
