"""Compiled numba kernels shipped with the package, so that a fresh install does not compile them (issue 14).

The field, graph, topology and flow stages run numba kernels (``@njit(cache=True)``) that numba compiles
on first use and caches on disk: about 40 CPU seconds of a fresh install's first drawing. The package
ships them compiled, as numba's own cache files, in ``pipeline/engine/kernels/compiled/`` (one folder per
kernel module and a ``manifest.json``), built by ``python -m pipeline.engine.kernels.build`` for the CPU level of
:func:`stages.portable_cpu_target` (x86-64-v3). Before a run computes a stage whose kernels have no
cache yet, :func:`install` copies that stage's shipped files into the folder where numba looks for them
(:func:`cache_dir`), when they fit: built from this very source file (sha256), by this numba and
Python, for the CPU target and platform this process compiles for (on a cluster joined by
``runtime.scheduler_address``, each worker copies them into its own machine's cache before its first
task). numba then loads them, and checks the same things again itself. Otherwise nothing is copied and the kernels compile as before
(:mod:`pipeline.engine.kernels.warmup`). ``runtime.shipped_kernels=false`` turns the copy off. A task loads its
stage's cached kernels without numba's registries (:func:`load_without_registries`).

A developer who changes a kernel module runs ``python -m pipeline.engine.kernels.build`` again (a test says when).
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import os
import pickletools
import shutil
import sys
from importlib.util import find_spec
from pathlib import Path

import stages  # noqa: F401  (sets numba's CPU target, stages.portable_cpu_target, which target() reads)

#: The modules with numba kernels that are compiled on first use and cached on disk, per stage.
KERNEL_MODULES = {"field": ("stages.field.kernel",), "graph": ("stages.graph.trace", "stages.graph.cross_section"),
                  "topology": ("stages.topology.constrained_path",), "flow": ("stages.flow.kernel",)}
#: Where the compiled kernels are shipped: ``<module>/<numba's cache files>`` and the manifest.
SHIPPED = Path(__file__).resolve().with_name("compiled")
#: The manifest's name in such a folder.
MANIFEST = "manifest.json"


_QUICK_LOADS: set[str] = set()


def load_without_registries(stage: str) -> None:
    """Let the cached kernels of ``stage`` load without numba's registries (once per module and process).

    Before it loads a cached kernel, numba refreshes its CPU target: it imports the implementations
    of everything it could compile (~330 modules in a bare process, scipy.linalg among them), which
    only compiling needs: ~0.35 s of a λ re-run's flow and of the graph's first call in a default run
    (stages/DECISIONS.md, engine). Loaded machine code needs numba's runtime (NRT) and the symbols
    numba puts in LLVM's table: at import (its C helpers, in ``BaseContext``), when the target is
    made (C math), when a parallel kernel is loaded (its ``reload_init``), and, of the registry
    modules, only ``numba.cpython.hashing`` (the hash secrets), imported here. So each cached
    dispatcher of the stage's kernel modules (:data:`KERNEL_MODULES`) gets a ``load_overload`` that
    initialises NRT and loads; a kernel not in the cache compiles as before (numba's compiler
    refreshes the target itself). It replaces a method of numba's private ``Cache`` class, so only
    with the numba the shipped kernels were built by (the pinned one, which the tests load them with);
    another numba loads its own way.
    """
    modules = [m for m in KERNEL_MODULES.get(stage, ()) if m not in _QUICK_LOADS]
    if not modules:
        return
    import importlib

    import numba
    from numba.core.caching import Cache
    from numba.core.dispatcher import Dispatcher

    _QUICK_LOADS.update(modules)
    if numba.__version__ != _shipped_numba():
        return
    for module in modules:
        for obj in vars(importlib.import_module(module)).values():
            if isinstance(obj, Dispatcher) and isinstance(obj._cache, Cache):
                obj._cache.load_overload = functools.partial(_load_overload, obj._cache)


def _load_overload(cache, sig, target_context):
    """numba's ``Cache.load_overload`` without ``target_context.refresh()`` (:func:`load_without_registries`)."""
    import numba.cpython.hashing  # noqa: F401 - puts the hash secrets' symbols into LLVM's table
    from numba.core.runtime import rtsys

    rtsys.initialize(target_context)
    with cache._guard_against_spurious_io_errors():
        return cache._load_overload(sig, target_context)


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


def _indexes(src: Path) -> list[Path]:
    """numba's index files of the kernels of source file ``src`` for this Python, sorted."""
    return sorted(cache_dir(src).glob(f"{src.stem}.*.{python_tag()}.nbi"))


def is_cached(module: str) -> bool:
    """Whether numba's cache folder holds a current index of each of ``module``'s kernels for this Python.

    numba names an index ``<file>.<kernel>-<line>.py<ver>.nbi`` (Pythons of other versions share the
    folder) and writes into it its own version (a pickled str) and the sha256 digest of the module's
    source it compiled, and its kernels' keys hold the CPU they were compiled for: an index from before
    the source changed (a ``git pull``, an upgrade in place) or for another CPU target (a cache from
    before :func:`stages.portable_cpu_target`) is no cache, numba compiles again. Digest and CPU name are
    looked for in the indexes of the shipped kernels' numba, whose format this knows; any other numba's
    index is taken as a cache.
    """
    src = module_file(module)
    indexes = _indexes(src)
    digest, cpu = None, os.environ.get("NUMBA_CPU_NAME", "").encode()
    for index in indexes:
        try:
            data = index.read_bytes()
        except OSError:
            return False
        version = _index_version(data)
        if version is None:  # not numba's index: numba cannot read it either
            return False
        if version != _shipped_numba():
            continue
        digest = digest or hashlib.sha256(src.read_bytes()).digest()
        if digest not in data or cpu not in data:
            return False
    return bool(indexes)


def forget_stale(stages: list[str]) -> list[str]:
    """Remove the cache files of ``stages``' kernel modules that were compiled from an older source.

    numba names an index after its kernel and the kernel's line in the source. When an edit moves a
    kernel (a ``git pull``, an upgrade in place), numba compiles it under the new name and never
    opens the old index again; :func:`is_cached` would still find the old one, with its old source
    digest, and call the module uncompiled at every run (the compile message and the warm-ups each
    time). Only indexes of this Python, in the format of the shipped kernels' numba and without the
    source's current digest are removed, with their data files: numba would refuse them anyway.

    Returns
    -------
    list of str
        The index files removed.
    """
    removed = []
    for module in sorted({m for stage in stages for m in KERNEL_MODULES.get(stage, ())}):
        src = module_file(module)
        folder = cache_dir(src)
        digest = None
        for index in _indexes(src):
            try:
                data = index.read_bytes()
            except OSError:
                continue
            if _index_version(data) != _shipped_numba():
                continue  # another numba's: its own business
            digest = digest or hashlib.sha256(src.read_bytes()).digest()
            if digest in data:
                continue
            stem = index.name[: -len(".nbi")]
            try:
                for data_file in folder.glob(f"{stem}.*.nbc"):
                    if data_file.name[len(stem) + 1: -len(".nbc")].isdigit():
                        data_file.unlink(missing_ok=True)
                index.unlink(missing_ok=True)
            except OSError:  # a folder it cannot write: numba cannot cache there either
                continue
            removed.append(index.name)
    return removed


def _index_version(data: bytes) -> str | None:
    """The numba version an index starts with (a pickled str), read from its opcodes without unpickling
    anything (a cache file is data, not code to run); None when it does not start so."""
    try:
        for op, arg, _ in pickletools.genops(io.BytesIO(data)):
            if op.name in ("SHORT_BINUNICODE", "BINUNICODE", "UNICODE"):
                return arg
            if op.name not in ("PROTO", "FRAME"):
                return None
    except Exception:  # malformed opcodes raise ValueError and others
        return None
    return None


@functools.lru_cache(maxsize=1)
def _shipped_numba() -> str | None:
    """The numba version of the shipped kernels (None without a manifest)."""
    return (_manifest(None) or {}).get("target", {}).get("numba")


@functools.lru_cache(maxsize=1)
def _numba_version() -> str:
    from importlib.metadata import version  # ~20 ms: only when a kernel module has no cache

    return version("numba")


def target(environ=os.environ) -> dict:
    """What a compiled kernel is bound to besides Python's version: numba's version, the platform, the CPU target."""
    import platform

    return {"numba": _numba_version(), "platform": f"{sys.platform}-{platform.machine()}",
            "cpu_name": environ.get("NUMBA_CPU_NAME"), "cpu_features": environ.get("NUMBA_CPU_FEATURES")}


def python_tag() -> str:
    """This Python's tag in numba's cache file names (``py311``)."""
    return f"py{sys.version_info[0]}{sys.version_info[1]}"


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _manifest(shipped: Path | None) -> dict | None:
    """The manifest of a folder :func:`build` wrote (:data:`SHIPPED` by default), or None without one."""
    try:
        return json.loads((Path(shipped or SHIPPED) / MANIFEST).read_text())
    except (OSError, ValueError):
        return None


def uncached_modules(stages: list[str]) -> list[str]:
    """The kernel modules of ``stages`` that numba has no cache of (:func:`is_cached`)."""
    return [m for stage in stages for m in KERNEL_MODULES.get(stage, ()) if not is_cached(m)]


def misfit(manifest: dict | None) -> str:
    """Why shipped kernels do not fit this process, in words; ``""`` when they do (see :func:`stale`)."""
    if manifest is None:
        return "none are shipped with this install"
    theirs, mine = manifest.get("target", {}), target()
    if theirs.get("numba") != mine["numba"]:
        return f"the shipped ones are numba {theirs.get('numba')}'s, this is numba {mine['numba']}"
    if theirs.get("platform") != mine["platform"]:
        return f"the shipped ones are for {theirs.get('platform')}, not {mine['platform']}"
    if (theirs.get("cpu_name"), theirs.get("cpu_features")) != (mine["cpu_name"], mine["cpu_features"]):
        if mine["cpu_name"] is None and mine["cpu_features"] is None:
            return f"the shipped ones need an {theirs.get('cpu_name')} CPU (AVX2, FMA), which this one is not"
        return "NUMBA_CPU_NAME / NUMBA_CPU_FEATURES are set in the environment"
    if python_tag() not in manifest.get("pythons", ()):
        return f"none are shipped for Python {sys.version_info[0]}.{sys.version_info[1]}"
    return ""


def stale(manifest: dict, module: str) -> str:
    """``""`` when the shipped kernels of ``module`` were built from its source as it is (sha256), else why not."""
    if manifest["modules"].get(module) != _sha256(module_file(module)):
        return f"{module} changed since they were built (python -m pipeline.engine.kernels.build)"
    return ""


def why_compiled(stages: list[str], shipped: Path | None = None) -> str:
    """Why the uncached kernels of ``stages`` are compiled rather than copied, in words (``""``: all are cached)."""
    modules = uncached_modules(stages)
    if not modules:
        return ""
    manifest = _manifest(shipped)
    return (misfit(manifest) or next(filter(None, (stale(manifest, m) for m in modules)), "")
            or "the shipped ones could not be copied into numba's cache folder")


def install(stages: list[str], shipped: Path | None = None) -> list[str]:
    """Copy the shipped kernels of ``stages`` into numba's cache where it has none yet and they fit.

    A module's files are copied only when neither :func:`misfit` nor :func:`stale` finds anything
    against them (the manifest's target is :func:`target`, this Python is among its versions, the
    module's sha256 is its source file's); each file is written beside its place and renamed into it
    (data files before the index that names them), so that a process that reads the cache meanwhile
    sees whole files.

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
    modules = uncached_modules(stages)
    if not modules:  # the common case: nothing to read
        return []
    shipped = Path(shipped or SHIPPED)
    manifest = _manifest(shipped)
    if misfit(manifest):
        return []
    tag = f".{python_tag()}."
    copied = []
    for module in modules:
        if stale(manifest, module):
            continue
        where = cache_dir(module_file(module))
        names = sorted((n for n in manifest["files"][module] if tag in n), key=lambda n: n.endswith(".nbi"))
        try:
            where.mkdir(parents=True, exist_ok=True)
            for name in names:
                tmp = where / f"{name}.tmp.{os.getpid()}"
                try:
                    shutil.copyfile(shipped / module / name, tmp)
                    os.replace(tmp, where / name)
                finally:
                    tmp.unlink(missing_ok=True)
        except OSError:  # numba cannot cache there either: it compiles in memory, as without them
            continue
        copied.append(module)
    return copied
