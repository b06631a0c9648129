"""First-run kernel compiles moved off the critical path (issue 14).

The graph and flow stages run numba kernels that are compiled on first use and cached on disk
(``@njit(cache=True)``): about 11 s and 10 s of a fresh install's first image, one after the other,
while the other core idles. When a single-process run (``runtime.cluster`` sync or auto with one
image) is about to compute those stages and their kernels have no cache yet, :func:`start` launches
one background process per stage (``python -m pipeline.warmup STAGE``) that compiles the kernels by
running the stage's code on a tiny drawing, while the main process works on prep, keypoints and the
field. Before the engine computes graph or flow it waits for that stage's warm-up (:func:`wait`), so
a kernel is never compiled twice at once; it then loads the kernels from the cache. A warm-up that
fails or takes too long only costs the time it took: the stage then compiles what it still lacks.
The warm-ups run in their own session (Ctrl-C in the terminal reaches only polyvec, which stops
them) and are stopped when the batch ends.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from pipeline.registry import default_config

#: Modules whose numba kernels are compiled on first use and cached on disk, per stage.
KERNEL_MODULES = {"graph": ("stages/graph/trace.py", "stages/graph/cross_section.py"),
                  "topology": ("stages/topology/constrained_path.py",), "flow": ("stages/flow/kernel.py",)}
#: Stages whose kernels a background process compiles (topology's one kernel compiles in ~1 s).
WARMED = ("graph", "flow")
#: Longest wait for a warm-up before the stage compiles on its own (s).
WAIT_LIMIT_S = 180.0

_ROOT = Path(__file__).resolve().parents[1]
_RUNNING: dict[str, subprocess.Popen] = {}


def _numba_cache_dir(src: Path) -> tuple[Path, bool]:
    """Where numba keeps the cache of ``src``'s kernels and whether it is a tree to search.

    numba's locators, in its order: below ``NUMBA_CACHE_DIR`` when set; else the module's
    ``__pycache__`` when it is writable (a source checkout, an editable or a user-writable install);
    else its user-wide cache dir (``~/.cache/numba/<folder>_<hash>`` on Linux: a read-only install).
    """
    cache_dir = os.environ.get("NUMBA_CACHE_DIR")
    if cache_dir:
        return Path(cache_dir), True
    in_tree = src.parent / "__pycache__"
    if os.access(in_tree if in_tree.is_dir() else src.parent, os.W_OK):
        return in_tree, False
    from numba.core.caching import UserWideCacheLocator
    from numba.misc.appdirs import AppDirs

    user = Path(AppDirs(appname="numba", appauthor=False).user_cache_dir)
    return user / UserWideCacheLocator.get_suitable_cache_subpath(str(src)), False


def uncompiled(stages: list[str]) -> list[str]:
    """The stages of ``stages`` with numba kernels that have no on-disk cache yet.

    numba keeps its cache index (``<module>.<function>-<line>.py<ver>.nbi``) where
    :func:`_numba_cache_dir` says.
    """
    out = []
    for stage in stages:
        for module in KERNEL_MODULES.get(stage, ()):
            src = _ROOT / module
            where, tree = _numba_cache_dir(src)
            pattern = f"{src.stem}.*.nbi"
            found = where.rglob(pattern) if tree else where.glob(pattern)
            if next(iter(found), None) is None:
                out.append(stage)
                break
    return out


def start(stages: list[str]) -> list[str]:
    """Start a background warm-up for each stage of :data:`WARMED` in ``stages`` whose kernels are uncompiled.

    Returns
    -------
    list of str
        The stages now warming up.
    """
    started = []
    for stage in uncompiled([s for s in stages if s in WARMED]):
        if stage in _RUNNING and _RUNNING[stage].poll() is None:
            continue
        env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
                   NUMBA_NUM_THREADS="1")
        _RUNNING[stage] = subprocess.Popen([sys.executable, "-m", "pipeline.warmup", stage], cwd=str(_ROOT),
                                           env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                           stderr=subprocess.DEVNULL, start_new_session=True)
        started.append(stage)
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
        ``graph`` (prep → field → graph) or ``flow`` (:func:`stages.flow.polyvector_flow` on one
        straight path over a uniform field: the kernel's types do not depend on the drawing).
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
    else:
        raise SystemExit(f"pipeline.warmup: no warm-up for stage {stage!r} (known: {', '.join(WARMED)})")


if __name__ == "__main__":
    warm(sys.argv[1])
