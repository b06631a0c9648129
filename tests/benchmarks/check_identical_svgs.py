"""Check that a refactoring leaves every SVG byte-identical (issue 16; not a test).

Runs ``polyvec`` into a fresh store (in-process scheduler, so it takes one core) on

1. the bundled example drawing (``polyvec`` with no input), and
2. the 13 drawings of ``../shared/data/drawings`` (when present), and
3. with ``--realvec``, the 106 scored cases of ``../shared/data/realvec_dev`` (about 8 minutes on one core),

then lists the sha256 of every ``.svg`` and ``.json`` written. With ``--ref DIR`` the files are
compared with those of a reference run (made first, from the code before the change, with
``--out DIR``): the exit status is 0 when every SVG is identical, 1 otherwise. JSON files (the curve
data beside each SVG) are compared too and reported, but only SVGs decide the status; the example's
JSON names its input, written into the output folder, so each run's folder is replaced by
``<out>`` before hashing.

Usage::

    python tests/benchmarks/check_identical_svgs.py --out /work/ref16          # the reference
    python tests/benchmarks/check_identical_svgs.py --out /tmp/new16 --ref /work/ref16
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DRAWINGS = REPO.parent / "shared" / "data" / "drawings"
REALVEC = REPO.parent / "shared" / "data" / "realvec_dev"


def _polyvec(args: list[str], store: Path) -> None:
    """Run the ``polyvec`` command in-process-scheduled into ``store``; raise on failure."""
    cmd = [sys.executable, "-m", "pipeline.cli", *args, f"store.path={store}",
           "runtime.cluster=sync", "runtime.progress=false"]
    subprocess.run(cmd, cwd=REPO, check=True)


def _hashes(folder: Path) -> dict[str, str]:
    """sha256 of every SVG and JSON file below ``folder`` (the folder's own path replaced by
    ``<out>``), by path relative to it."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes().replace(str(folder).encode(), b"<out>")).hexdigest()
            for p in sorted(folder.rglob("*")) if p.suffix in (".svg", ".json") and p.is_file() and p.name != "hashes.json"}


def run(out: Path, realvec: bool = False) -> dict[str, str]:
    """Vectorise the example and the drawings (and realvec_dev's cases) into ``out``; write and
    return ``hashes.json``."""
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="pv-identical-") as tmp:
        t0 = time.perf_counter()
        _polyvec([f"output={out / 'example'}"], Path(tmp) / "store")
        if DRAWINGS.is_dir():
            _polyvec([str(DRAWINGS), f"output={out / 'drawings'}"], Path(tmp) / "store")
        if realvec and REALVEC.is_dir():
            _polyvec([str(REALVEC), f"output={out / 'realvec_dev'}"], Path(tmp) / "store")
        print(f"vectorised in {time.perf_counter() - t0:.0f} s")
    hashes = _hashes(out)
    (out / "hashes.json").write_text(json.dumps(hashes, indent=1) + "\n")
    return hashes


def compare(new: dict[str, str], ref: dict[str, str]) -> bool:
    """Print the comparison; True when every SVG of either run is identical in the other."""
    ok = True
    for kind in (".svg", ".json"):
        names = sorted(n for n in set(new) | set(ref) if n.endswith(kind))
        differ = [n for n in names if new.get(n) != ref.get(n)]
        print(f"{kind}: {len(names) - len(differ)} of {len(names)} identical")
        for n in differ:
            state = "missing" if n not in new else "extra" if n not in ref else "differs"
            print(f"  {state}: {n}")
        if kind == ".svg" and (differ or not names):
            ok = False
    return ok


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="folder for this run's SVGs")
    ap.add_argument("--ref", type=Path, help="a reference run's folder to compare with")
    ap.add_argument("--realvec", action="store_true", help="realvec_dev's cases as well")
    a = ap.parse_args()
    new = run(a.out.resolve(), a.realvec)
    if a.ref is not None:
        ref = _hashes(a.ref.resolve())
        sys.exit(0 if compare(new, ref) else 1)


if __name__ == "__main__":
    main()
