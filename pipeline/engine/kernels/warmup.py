"""First-run kernel compiles moved off the critical path (issue 14).

The graph, topology and flow stages run numba kernels that are compiled on first use and cached on
disk (``@njit(cache=True)``): about 11 s, 1 s and 10 s of a first image, one after the other, while
the other core idles, where the package's compiled kernels (:mod:`pipeline.engine.kernels.shipped`) do not fit the
machine. When a single-process run (``runtime.cluster`` sync or auto
with one image) is about to compute those stages and their kernels have no cache yet, :func:`start`
launches two background processes (``python -m pipeline.engine.kernels.warmup STAGE ...``: the graph's; topology's
then the flow's) that compile the kernels by running the stages' code on tiny inputs, while the main
process works on prep, keypoints and the field. Before the engine computes one of these stages it
waits for that stage's warm-up (:func:`wait`), so
a kernel is never compiled twice at once; it then loads the kernels from the cache. A warm-up that
fails or takes too long only costs the time it took: the stage then compiles what it still lacks.
The warm-ups run in their own session (Ctrl-C in the terminal reaches only polyvec, which stops
them) and are stopped when the batch ends. The field's three small kernels (~0.6 s) are not warmed:
the field runs right after prep, before a warm-up could be done, and compiles them itself (the graph's
warm-up, which runs the field on its way, compiles them too).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from pipeline.engine.config import default_config
from pipeline.engine.kernels import shipped

#: Stages whose kernels a background process compiles.
WARMED = ("graph", "topology", "flow")
#: The stages one background process warms, in order: topology's one kernel (~1 s) is compiled by
#: the flow's process before the flow's (~5 s): topology runs first, after the graph (the critical
#: path of a first run), while the flow's own warm-up has seconds to spare.
PROCESSES = (("graph",), ("topology", "flow"))
#: Longest wait for a warm-up before the stage compiles on its own (s).
WAIT_LIMIT_S = 180.0

_ROOT = Path(__file__).resolve().parents[3]
_RUNNING: dict[str, subprocess.Popen] = {}


def uncompiled(stages: list[str]) -> list[str]:
    """The stages of ``stages`` with numba kernels that have no on-disk cache yet
    (:func:`pipeline.engine.kernels.shipped.is_cached`)."""
    return [s for s in stages if shipped.uncached_modules([s])]


def start(stages: list[str]) -> list[str]:
    """Start a background warm-up for each stage of :data:`WARMED` in ``stages`` whose kernels are uncompiled.

    Returns
    -------
    list of str
        The stages now warming up.
    """
    cold = set(uncompiled([s for s in stages if s in WARMED]))
    started = []
    for group in PROCESSES:
        todo = [s for s in group if s in cold and not (s in _RUNNING and _RUNNING[s].poll() is None)]
        if not todo:
            continue
        env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
                   NUMBA_NUM_THREADS="1")
        proc = subprocess.Popen([sys.executable, "-m", "pipeline.engine.kernels.warmup", *todo], cwd=str(_ROOT),
                                env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True)
        for stage in todo:
            _RUNNING[stage] = proc
        started += todo
    return started


def wait(stage: str, limit_s: float = WAIT_LIMIT_S) -> None:
    """Wait (at most ``limit_s``) for the warm-up of ``stage`` if one is running; stop it past the limit."""
    proc = _RUNNING.get(stage)  # not popped before it ends: tasks of two images may wait on it at once
    if proc is None:
        return
    try:
        proc.wait(timeout=limit_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    _RUNNING.pop(stage, None)


def stop() -> None:
    """Stop every warm-up still running (the batch is over or was interrupted)."""
    while _RUNNING:
        _, proc = _RUNNING.popitem()
        if proc.poll() is None:
            proc.kill()
        proc.wait()


def warm(stage: str) -> None:
    """Compile ``stage``'s kernels by running its code on the bundled example drawing (defaults).

    Parameters
    ----------
    stage : str
        ``graph`` (prep → field → graph), ``topology`` (its constrained-walk search on a three-vertex
        path) or ``flow`` (:func:`stages.flow.polyvector_flow` on one straight path over a uniform
        field). The kernels' types do not depend on the drawing.
    """
    import numpy as np

    if stage == "graph":
        from stages import graph, prep
        from stages.field import run as field_run
        from stages.synthetic import example_drawing

        png = example_drawing().png_bytes()
        p = prep.run(default_config("prep"), image_bytes=png, image_name="example.png")
        f = field_run(default_config("field"), prep=p)
        graph.run(default_config("graph"), prep=p, field=f)
    elif stage == "flow":
        from stages.config import from_section
        from stages.flow import FlowConfig, polyvector_flow

        params = from_section(FlowConfig, dict(default_config("flow"), iterations=3), "flow")
        c0 = np.full((16, 16), 0.1 + 0j)
        c2 = np.full((16, 16), -0.5 + 0j)
        xy = np.stack([np.linspace(2.0, 13.0, 12), np.linspace(3.0, 12.0, 12)], axis=1)
        polyvector_flow(c0, c2, [xy], [np.full(12, 3.0)], [np.linspace(0.0, 11.0, 12)], params)
    elif stage == "topology":
        from stages.topology.constrained_path import _search

        # The path 0 - 1 - 2 (arcs 0→1, 1→0, 1→2, 2→1), from vertex 0 to vertex 2 through 1.
        i64 = np.int64
        _search(np.array([0, 1, 3, 4], i64), np.array([1, 0, 2, 1], i64), np.ones(4), np.array([1, 0, 3, 2], i64),
                np.array([0, 2, 3, 4, 6], i64), np.ones(6, bool), 0, 3, np.array([0, 1, 0], i64),
                np.array([True, False, False]), np.array([False, False, True]), 1)
    else:
        raise SystemExit(f"pipeline.engine.kernels.warmup: no warm-up for stage {stage!r} (known: {', '.join(WARMED)})")


if __name__ == "__main__":
    for name in sys.argv[1:]:
        warm(name)
