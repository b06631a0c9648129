"""The keypoints child forked before ``polyvec`` imports anything of its own (standard library only).

``polyvec``'s launcher (:mod:`pipeline.launch`) calls :func:`start_early` first thing: the fork is
safe while the process has no threads yet, and the child imports torch at once, on the other core,
while the driver imports the CLI, composes the config and plans the batch (~0.4 s). The batch
(:func:`pipeline.engine.execute.batch.run_batch`) adopts it (:func:`take_early`) when it has keypoints
to compute in this process, and ends it otherwise (:func:`end_early`; stages/DECISIONS.md, engine).
Standard library only here, and in the packages above this module: the point is to start before
the imports.
"""

from __future__ import annotations

import os
import signal

from pipeline.engine.execute.process import THREAD_ENV

#: The child :func:`start_early` started: (process, this process's end of its pipe), until taken.
_EARLY: list = []


def start_early() -> None:
    """Fork the keypoints child now (this process has no threads yet); :func:`take_early` hands it
    to the run. SIGINT is blocked in it: Ctrl-C is this process's to report, as for dask's workers."""
    import multiprocessing

    ctx = multiprocessing.get_context("fork")
    ours, theirs = ctx.Pipe()
    proc = ctx.Process(target=_serve_early, args=(theirs, ours), daemon=True, name="polyvec-keypoints-extension")
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        proc.start()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        theirs.close()
    _EARLY.append((proc, ours))


def _serve_early(conn, ours) -> None:
    # The fork holds a copy of this process's end too: closed, or the child would never see this
    # process go (its reads end when every copy of that end is closed).
    ours.close()
    os.environ.update(THREAD_ENV)
    from pipeline.engine.execute.child import CHILD_STAGES, serve_tasks

    serve_tasks(conn, CHILD_STAGES, None)


def take_early():
    """The child :func:`start_early` started, once: ``(process, connection)``, or None (none started,
    or gone). The caller adopts or ends it."""
    while _EARLY:
        proc, conn = _EARLY.pop()
        if proc.is_alive():
            return proc, conn
        conn.close()
    return None


def end_early() -> None:
    """End the keypoints child ``polyvec`` forked before its imports, unless a run adopted it."""
    early = take_early()
    if early is not None:
        proc, conn = early
        proc.kill()
        conn.close()
        proc.join()
