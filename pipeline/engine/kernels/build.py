"""``python -m pipeline.engine.kernels.build``: compile the kernels the package ships (:mod:`.shipped`).

Run by a developer after changing a kernel module (``tests/pipeline/test_kernels.py`` says when): the
stages' warm-ups (:mod:`.warmup`) compile every kernel into an empty numba cache, for this Python and
any other given with ``--python``, and their cache files and a manifest replace :data:`.shipped.SHIPPED`.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import stages
from pipeline.engine.kernels.shipped import (KERNEL_MODULES, MANIFEST, SHIPPED, _sha256, cache_dir, module_file,
                                             python_tag, target)
from pipeline.engine.kernels.warmup import PROCESSES


def _interpreter_tag(python: str) -> str:
    """The Python tag of the interpreter ``python``; it must have the numba that built the other kernels."""
    code = "import sys, importlib.metadata as m; print(f'py{sys.version_info[0]}{sys.version_info[1]}', m.version('numba'))"
    try:
        tag, numba = subprocess.run([python, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    except (OSError, subprocess.CalledProcessError, ValueError):
        raise SystemExit(f"python -m pipeline.engine.kernels.build: {python} does not run, or has no numba") from None
    if numba != target()["numba"]:
        raise SystemExit(f"python -m pipeline.engine.kernels.build: {python} has numba {numba}, not {target()['numba']}")
    return tag


def build(out: Path = SHIPPED, pythons: tuple[str, ...] = ()) -> None:
    """Compile every kernel module for the portable CPU target and write its cache files and manifest to ``out``.

    The kernels are compiled by the stages' warm-ups (:func:`pipeline.engine.kernels.warmup.warm`: the stages' own code
    on the bundled example), in :data:`pipeline.engine.kernels.warmup.PROCESSES`' two processes at once, into an empty
    ``NUMBA_CACHE_DIR``; ``out`` is replaced by the files that holds.

    Parameters
    ----------
    out : Path
        The folder to write (:data:`SHIPPED` by default).
    pythons : tuple of str
        Other Python interpreters to compile for as well (their cache files are named by their version);
        each needs the same numba and the stages' dependencies, and runs this source tree.
    """
    if not stages.portable_cpu_target():
        raise SystemExit(f"python -m pipeline.engine.kernels.build: this machine does not compile for {stages.PORTABLE_CPU} "
                         "(an x86-64 Linux CPU with that level, no NUMBA_CPU_NAME of its own): nothing built")
    out = Path(out)
    interpreters = {python_tag(): sys.executable} | {_interpreter_tag(p): p for p in pythons}
    root = str(Path(__file__).resolve().parents[3])
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, NUMBA_CACHE_DIR=tmp, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1",
                   PYTHONPATH=os.pathsep.join(filter(None, (root, os.environ.get("PYTHONPATH")))))
        for python in interpreters.values():
            procs = [subprocess.Popen([python, "-m", "pipeline.engine.kernels.warmup", *group], env=env, cwd=root)
                     for group in PROCESSES]
            if any(proc.wait() for proc in procs):
                raise SystemExit(f"python -m pipeline.engine.kernels.build: a warm-up by {python} failed (above): nothing built")
        files, sums = {}, {}
        shutil.rmtree(out, ignore_errors=True)
        for module in sorted(m for ms in KERNEL_MODULES.values() for m in ms):
            src = module_file(module)
            found = sorted(p for p in cache_dir(src, env).glob(f"{src.stem}.*") if p.suffix in (".nbi", ".nbc"))
            for tag in interpreters:
                if not any(p.suffix == ".nbi" and f".{tag}." in p.name for p in found):
                    raise SystemExit(f"python -m pipeline.engine.kernels.build: the warm-ups compiled nothing of {module} ({tag})")
            (out / module).mkdir(parents=True)
            for p in found:
                shutil.copyfile(p, out / module / p.name)
            files[module], sums[module] = [p.name for p in found], _sha256(src)
    manifest = {"target": target(), "pythons": sorted(interpreters), "modules": sums, "files": files}
    (out / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    size = sum(p.stat().st_size for p in out.rglob("*"))
    print(f"pipeline.engine.kernels.build: {sum(map(len, files.values()))} files of {len(files)} modules for "
          f"{', '.join(sorted(interpreters))}, {size / 1e6:.1f} MB, in {out}")


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(prog="python -m pipeline.engine.kernels.build", description=build.__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=SHIPPED, help=f"where to write them (default {SHIPPED})")
    parser.add_argument("--python", action="append", default=[], metavar="PYTHON",
                        help="another Python interpreter to compile for (repeatable), with the same numba")
    args = parser.parse_args()
    build(args.out, tuple(args.python))
