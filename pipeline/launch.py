"""``polyvec``'s console entry point: the keypoints child first, then the CLI (:mod:`pipeline.cli`).

Before this process imports anything of its own it forks the child that an in-process run computes
its keypoints in (:class:`pipeline.runner._ChildTasks`), and the child imports torch at once, on the
other core, while this process imports the CLI, composes the config and plans the batch (~0.4 s).
:func:`pipeline.runner.run_batch` adopts it (:func:`take_early`) when the batch has keypoints to
compute in this process, and ends it otherwise (stages/DECISIONS.md, engine).

Standard library only, here: the fork is safe while this process has no threads, and the point is
to start before the imports.
"""

from __future__ import annotations

import os
import signal
import sys

#: One thread each for the numerical libraries of a process that runs beside another (dask's
#: workers, the keypoints child): read by them at import, so set before.
THREAD_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
              "NUMBA_NUM_THREADS": "1", "VECLIB_MAXIMUM_THREADS": "1"}

#: Arguments with which ``polyvec`` runs no drawing: no child for them.
NO_RUN_FLAGS = frozenset({"-h", "--help", "-c", "--cfg", "--info", "--hydra-help", "--version",
                          "--shell-completion", "-sc"})

#: The child :func:`start_early` started: (process, this process's end of its pipe), until taken.
_EARLY: list = []


def main() -> None:
    """Console entry point of ``polyvec`` (see :func:`pipeline.cli.main`)."""
    if sys.platform == "linux" and not NO_RUN_FLAGS.intersection(sys.argv[1:]):
        start_early()
    from pipeline.cli import main as cli_main

    cli_main()


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
    from pipeline.runner import CHILD_STAGES, _serve_tasks

    _serve_tasks(conn, CHILD_STAGES, None)


def take_early():
    """The child :func:`start_early` started, once: ``(process, connection)``, or None (none started,
    or gone). The caller adopts or ends it."""
    while _EARLY:
        proc, conn = _EARLY.pop()
        if proc.is_alive():
            return proc, conn
        conn.close()
    return None


if __name__ == "__main__":   # python -m pipeline.launch: the run must find the child in the imported module
    from pipeline.launch import main as imported_main

    imported_main()
