"""Compiled numba kernels shipped with the package, so that a fresh install does not compile them (issue 14).

The graph, topology and flow stages run numba kernels (``@njit(cache=True)``) that numba compiles on
first use and caches on disk: about 40 CPU seconds of a fresh install's first drawing. The package
ships them compiled, as numba's own cache files, in ``pipeline/compiled_kernels/`` (one folder per
kernel module and a ``manifest.json``), built by ``python -m pipeline.kernels`` for the CPU level of
:func:`stages.portable_cpu_target` (x86-64-v3). Before a run computes a stage whose kernels have no
cache yet, :func:`install` copies that stage's shipped files into the folder where numba looks for them
(:func:`cache_dir`), when they fit: built from this very source file (sha256), by this numba and
Python, for the CPU target and platform this process compiles for. numba then loads them, and checks
the same things again itself. Otherwise nothing is copied and the kernels compile as before
(:mod:`pipeline.warmup`). ``runtime.shipped_kernels=false`` turns the copy off.

A developer who changes a kernel module runs ``python -m pipeline.kernels`` again (a test says when).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from importlib.metadata import version
from importlib.util import find_spec
from pathlib import Path

#: The modules with numba kernels that are compiled on first use and cached on disk, per stage.
KERNEL_MODULES = {"graph": ("stages.graph.trace", "stages.graph.cross_section"),
                  "topology": ("stages.topology.constrained_path",), "flow": ("stages.flow.kernel",)}
#: Where the compiled kernels are shipped: ``<module>/<numba's cache files>`` and the manifest.
SHIPPED = Path(__file__).resolve().with_name("compiled_kernels")
#: The manifest's name in such a folder.
MANIFEST = "manifest.json"


def module_file(module: str) -> Path:
    """The source file of a kernel module, as Python names it (so as numba does), without running it."""
    return Path(find_spec(module).origin)


def cache_dir(src: Path, environ=os.environ) -> Path:
    """The folder where numba keeps, and looks for, the cache of ``src``'s kernels.

    numba's locators, in its order: below ``NUMBA_CACHE_DIR`` when set; else the module's
    ``__pycache__`` when it is writable (a source checkout, an editable or a user-writable install);
    else its user-wide cache dir (``~/.cache/numba`` on Linux: a read-only install). Below a cache
    root, the folder is named after the module's folder and the sha1 of its absolute path, as numba's
    ``_CacheLocator.get_suitable_cache_subpath`` names it (a test checks they agree).
    """
    folder = os.path.dirname(os.path.abspath(src))
    subpath = f"{os.path.basename(folder)}_{hashlib.sha1(folder.encode()).hexdigest()}"
    root = environ.get("NUMBA_CACHE_DIR")
    if root:
        return Path(root) / subpath
    in_tree = Path(folder) / "__pycache__"
    if os.access(in_tree if in_tree.is_dir() else folder, os.W_OK):
        return in_tree
    from numba.misc.appdirs import AppDirs

    return Path(AppDirs(appname="numba", appauthor=False).user_cache_dir) / subpath


def is_cached(module: str) -> bool:
    """Whether numba's cache folder holds an index of ``module``'s kernels (``<file>.<kernel>-<line>.py<ver>.nbi``)."""
    src = module_file(module)
    return next(cache_dir(src).glob(f"{src.stem}.*.nbi"), None) is not None


def target(environ=os.environ) -> dict:
    """What a compiled kernel is bound to: numba's version, Python's, the platform and the CPU target."""
    return {"numba": version("numba"), "python": f"py{sys.version_info[0]}{sys.version_info[1]}",
            "platform": f"{sys.platform}-{os.uname().machine}",
            "cpu_name": environ.get("NUMBA_CPU_NAME"), "cpu_features": environ.get("NUMBA_CPU_FEATURES")}


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def install(stages: list[str], shipped: Path | None = None) -> list[str]:
    """Copy the shipped kernels of ``stages`` into numba's cache where it has none yet and they fit.

    A module's files are copied only when the manifest's target is :func:`target` and its sha256 is
    the source file's; each file is written beside its place and renamed into it (data files before
    the index that names them), so that a process that reads the cache meanwhile sees whole files.

    Parameters
    ----------
    stages : list of str
        Stage names (those without kernels are passed over).
    shipped : Path, optional
        A folder :func:`build` wrote; :data:`SHIPPED` by default.

    Returns
    -------
    list of str
        The kernel modules copied.
    """
    shipped = Path(shipped or SHIPPED)
    try:
        manifest = json.loads((shipped / MANIFEST).read_text())
    except (OSError, ValueError):
        return []
    if manifest.get("target") != target():
        return []
    copied = []
    for stage in stages:
        for module in KERNEL_MODULES.get(stage, ()):
            src = module_file(module)
            if manifest["modules"].get(module) != _sha256(src) or is_cached(module):
                continue
            where = cache_dir(src)
            where.mkdir(parents=True, exist_ok=True)
            for name in sorted(manifest["files"][module], key=lambda n: n.endswith(".nbi")):
                tmp = where / f"{name}.tmp.{os.getpid()}"
                shutil.copyfile(shipped / module / name, tmp)
                os.replace(tmp, where / name)
            copied.append(module)
    return copied


def build(out: Path = SHIPPED) -> None:
    """Compile every kernel module for the portable CPU target and write its cache files and manifest to ``out``.

    The kernels are compiled by the stages' warm-ups (:func:`pipeline.warmup.warm`: the stages' own code
    on the bundled example), in :data:`pipeline.warmup.PROCESSES`' two processes at once, into an empty
    ``NUMBA_CACHE_DIR``; ``out`` is replaced by the files that holds.
    """
    import stages
    from pipeline.warmup import PROCESSES

    if not stages.portable_cpu_target():
        raise SystemExit(f"python -m pipeline.kernels: this machine does not compile for {stages.PORTABLE_CPU} "
                         "(an x86-64 Linux CPU with that level, no NUMBA_CPU_NAME of its own): nothing built")
    out = Path(out)
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, NUMBA_CACHE_DIR=tmp, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1")
        procs = [subprocess.Popen([sys.executable, "-m", "pipeline.warmup", *group], env=env) for group in PROCESSES]
        if any(proc.wait() for proc in procs):
            raise SystemExit("python -m pipeline.kernels: a warm-up failed (above): nothing built")
        files, sums = {}, {}
        shutil.rmtree(out, ignore_errors=True)
        for module in sorted(m for ms in KERNEL_MODULES.values() for m in ms):
            src = module_file(module)
            found = sorted(p for p in cache_dir(src, env).glob(f"{src.stem}.*") if p.suffix in (".nbi", ".nbc"))
            if not any(p.suffix == ".nbi" for p in found):
                raise SystemExit(f"python -m pipeline.kernels: the warm-ups compiled nothing of {module}")
            (out / module).mkdir(parents=True)
            for p in found:
                shutil.copyfile(p, out / module / p.name)
            files[module], sums[module] = [p.name for p in found], _sha256(src)
    (out / MANIFEST).write_text(json.dumps({"target": target(), "modules": sums, "files": files}, indent=1)
                                     + "\n")
    size = sum(p.stat().st_size for p in out.rglob("*"))
    print(f"pipeline.kernels: {sum(map(len, files.values()))} files of {len(files)} modules, "
          f"{size / 1e6:.1f} MB, in {out}")


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(prog="python -m pipeline.kernels", description=build.__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=SHIPPED, help=f"where to write them (default {SHIPPED})")
    build(parser.parse_args().out)
