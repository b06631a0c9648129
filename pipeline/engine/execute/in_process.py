"""The in-process executor: a batch's tasks on two threads of this process and the keypoints child.

Chosen for one drawing, a λ or time-step re-run and a few drawings (``runtime.cluster``,
:func:`~.batch.cluster_mode`), where worker processes would cost more start-up than they save.
"""

from __future__ import annotations

from typing import Callable

from pipeline.engine.execute.base import BatchResult, TaskResult
from pipeline.engine.execute.child import EITHER_STAGES, ChildTasks
from pipeline.engine.execute.node import execute, store_at
from pipeline.engine.kernels import warmup
from pipeline.engine.plan import Task
from pipeline.engine.registry import BY_NAME, height


#: Tasks the in-process scheduler runs at once (threads): an image's keypoints beside its field and
#: graph, which need only prep (torch, scipy and the graph kernels release the GIL in their work).
SYNC_THREADS = 2
#: ... for drawings of at most this many (prep) pixels; a larger one runs a task at a time in this
#: process, so that its peak memory stays that of its largest stage (a 6 Mpx scan: graph ≈ 3.4 GB, +
#: keypoints on a thread 4.0 GB); the keypoints child (``runtime.keypoints_process``) still runs beside it.
SYNC_PARALLEL_MAX_PIXELS = 4_000_000


class InProcessExecutor:
    """Runs the pending tasks in this process, at most :data:`SYNC_THREADS` at once, in DAG order
    (the :class:`~.base.Executor` of one drawing, a re-run, a few drawings).

    Parameters
    ----------
    in_child : tuple of str
        Stages whose tasks run in the keypoints child (:data:`~.child.CHILD_STAGES`, or none).
    child : ChildTasks, optional
        The child :func:`~.batch.run_batch` started early; else one is started here when such a task
        is pending.
    """

    def __init__(self, in_child: tuple[str, ...] = (), child: ChildTasks | None = None):
        self.in_child = in_child
        self.child = child

    def run(self, pending: list[list[Task]], store_url: str, batch: BatchResult,
            report: Callable[[TaskResult], None]) -> None:
        """Run the pending tasks in this process, at most :data:`SYNC_THREADS` at once, in DAG order.

        A task starts when the tasks of its image that it reads have finished; earlier images first. A
        task that starts with nothing else running or ready runs ``alone`` (numba may use its whole pool:
        the flow). Tasks of the stages ``in_child`` run in one child process (:class:`~.child.ChildTasks`):
        ``child`` when given (:func:`~.batch.run_batch` starts it early), else one started here when such a task
        is pending; those of :data:`EITHER_STAGES` run here instead while the child is busy and this
        process has nothing else to start, or when there is no child. On Ctrl-C no new task starts; the
        running ones finish (each writes its artifact whole) and the child is killed.
        """
        from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

        in_child, child = self.in_child, self.child
        waiting = [(i, t) for i, tasks in enumerate(pending) for t in tasks]
        left_in_child = sum(t.stage in in_child for _, t in waiting)
        if child is None and any(t.stage in in_child and t.stage not in EITHER_STAGES for _, t in waiting):
            child = ChildTasks(in_child)
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


def _needed(t: Task, done: dict[str, TaskResult]) -> list[TaskResult]:
    spec = BY_NAME[t.stage]
    return [done[i] for i in spec.inputs if i in done and done[i].status != "cached"]


def _prep_pixels(store_url: str, key: str) -> int | None:
    """Pixels of a stored prep artifact's grey (from its manifest), None when it cannot be read."""
    try:
        shape = store_at(store_url).manifest("prep", key)["arrays"]["grey"]["shape"]
        return int(shape[0]) * int(shape[1])
    except Exception:  # noqa: BLE001 - no such artifact (prep failed): the caller runs one task at a time
        return None
