"""Benchmark: 40 drawings on a ``dask scheduler`` and 2 ``dask worker`` processes vs the local cluster (not a test).

The README's ``## A remote dask cluster`` commands on this machine: one scheduler and two ``dask worker
… --nworkers 1 --nthreads 1`` commands (two one-core "machines"), started before the batches as a
cluster's are, and ``polyvec FOLDER runtime.scheduler_address=…``; against it ``runtime.cluster=local
runtime.workers=2`` (the local cluster, which starts its two workers inside the command). Each row is
the whole command's wall seconds (:func:`bench_speed.polyvec`), on a fresh store.

Drawings: the drawings of ``../shared/data/drawings`` turned 0°, 90°, 180° and 270° (distinct images,
so none is a store hit of another), each fitted into 512×512 on white (:func:`bench_speed.fitted_512`),
the first 40. Rows, in this order: the cluster's first batch (its workers import the stages and load
the detector), the local cluster, with ``--warm`` the cluster again (warm workers), and with ``--kill``
the cluster with one worker killed (SIGKILL, with its nanny) once a quarter of the SVGs' exports are stored. Every
row's SVGs are compared with the local cluster's.

Usage::

    python tests/benchmarks/bench_cluster.py [--drawings 40] [--kill] [--warm] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_speed import SHARED, fitted_512, polyvec

from pipeline.engine.execute.process import THREAD_ENV

REPO = Path(__file__).resolve().parents[2]


def drawings(n: int, folder: Path) -> Path:
    """``n`` distinct 512² drawings (the shared drawings in four orientations) in ``folder/batch``."""
    from PIL import Image

    turned = []
    for deg in (0, 90, 180, 270):
        (folder / f"r{deg}").mkdir(parents=True)
        for src in sorted(SHARED.glob("*/*.png")):
            path = folder / f"r{deg}" / f"{src.parent.name}_{src.stem}.png"
            Image.open(src).convert("L").rotate(deg, expand=True, fillcolor=255).save(path)
            turned.append(path)
    batch = folder / "batch"
    batch.mkdir()
    fitted_512(turned[:n], batch)
    return batch


class Cluster:
    """A ``dask scheduler`` and ``dask worker`` processes on loopback, each in a process group of its own."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.env = dict(os.environ, **THREAD_ENV, PYTHONPATH=str(REPO))
        self.procs: list[subprocess.Popen] = []
        self.workers: list[subprocess.Popen] = []
        # Port 0: a free one, which the scheduler writes to its scheduler file with its address.
        file = folder / "scheduler.json"
        self._start("scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard", "--scheduler-file", str(file))
        deadline = time.monotonic() + 120
        while not file.is_file() or not file.read_text().strip():
            if time.monotonic() > deadline or self.procs[0].poll() is not None:
                raise SystemExit("the dask scheduler did not start")
            time.sleep(0.2)
        self.address = json.loads(file.read_text())["address"]

    def _start(self, *args: str) -> subprocess.Popen:
        p = subprocess.Popen([sys.executable, "-m", "dask", *args], cwd=self.folder, env=self.env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        self.procs.append(p)
        return p

    def add_workers(self, n: int) -> None:
        """Start ``n`` one-core workers (each ``dask worker`` command as on a machine of its own) and
        wait until the scheduler has them all."""
        from distributed import Client

        for _ in range(n):
            self.workers.append(self._start("worker", self.address, "--nworkers", "1", "--nthreads", "1",
                                            "--no-dashboard"))
        alive = [w for w in self.workers if w.poll() is None]
        with Client(self.address, timeout=60) as client:
            client.wait_for_workers(len(alive), timeout=300)

    def kill_worker(self) -> None:
        """SIGKILL the first live worker command and its worker process (a machine lost)."""
        victim = next(w for w in self.workers if w.poll() is None)
        os.killpg(victim.pid, signal.SIGKILL)
        victim.wait()

    def close(self) -> None:
        for p in self.procs[::-1]:
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        for p in self.procs[::-1]:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                pass
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            p.wait()


def killed_run(batch: Path, out: Path, store: Path, cluster: Cluster, n: int) -> float:
    """The cluster's command with one worker killed once ``n // 4`` exports are stored; wall seconds."""
    exe = str(Path(sys.executable).with_name("polyvec"))
    started = time.monotonic()
    proc = subprocess.Popen([exe, str(batch), f"output={out}", f"store.path={store}",
                             f"runtime.scheduler_address={cluster.address}"], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    while proc.poll() is None and len(list(store.glob("export/*/*/manifest.json"))) < n // 4:
        time.sleep(0.05)
    if proc.poll() is None:
        cluster.kill_worker()
    _, err = proc.communicate()
    if proc.returncode:
        raise SystemExit(f"the run with a worker killed failed ({proc.returncode}):\n{err[-2000:]}")
    return time.monotonic() - started


def same_svgs(a: Path, b: Path) -> str:
    names = sorted(p.name for p in a.glob("*.svg"))
    same = sum((a / n).read_bytes() == (b / n).read_bytes() for n in names if (b / n).is_file())
    return f"{same}/{len(names)} SVGs byte-identical to the local cluster's"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drawings", type=int, default=40)
    ap.add_argument("--kill", action="store_true", help="also a run with one worker killed a quarter of the way")
    ap.add_argument("--warm", action="store_true", help="also the cluster's second batch (warm workers)")
    ap.add_argument("--keep", type=Path, help="work in this folder and keep it (default: a temporary one)")
    args = ap.parse_args()
    tmp = args.keep or Path(tempfile.mkdtemp(prefix="bench_cluster-"))
    tmp.mkdir(parents=True, exist_ok=True)
    batch = drawings(args.drawings, tmp)
    (tmp / "cluster").mkdir()
    cluster = Cluster(tmp / "cluster")
    try:
        cluster.add_workers(2)
        remote = ["runtime.progress=false", f"runtime.scheduler_address={cluster.address}"]
        rows = [("scheduler + 2 workers, first batch", "remote1", remote),
                ("local cluster, 2 workers", "local", ["runtime.progress=false", "runtime.cluster=local",
                                                       "runtime.workers=2"]),
                ("scheduler + 2 workers, warm", "remote2", remote)][:3 if args.warm else 2]
        for name, tag, overrides in rows:
            r = polyvec([str(batch)], str(tmp / f"out-{tag}"), str(tmp / f"store-{tag}"), *overrides)
            print(f"{args.drawings} drawings 512², {name:<38}{r['wall_s']:>8.1f} s", flush=True)
        for tag in ("remote1", "remote2")[:2 if args.warm else 1]:
            print(f"  {tag}: {same_svgs(tmp / f'out-{tag}', tmp / 'out-local')}")
        if args.kill:
            wall = killed_run(batch, tmp / "out-killed", tmp / "store-killed", cluster, args.drawings)
            print(f"{args.drawings} drawings 512², {'scheduler + 2 workers, one killed':<38}{wall:>8.1f} s"
                  f"   ({same_svgs(tmp / 'out-killed', tmp / 'out-local')})", flush=True)
    finally:
        cluster.close()


if __name__ == "__main__":
    main()
