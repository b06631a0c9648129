"""polyvec past one machine: the README's ``## A remote dask cluster`` commands as separate processes.

A real ``dask scheduler`` and two ``dask worker`` commands (two "machines" of one single-threaded
worker each) on loopback; ``polyvec`` on a folder of small drawings against them, one worker killed
with SIGKILL (its nanny too: the machine is gone) once it has stored results and before the batch
ends. The batch still exits 0 and its SVGs are byte-identical to an in-process run. A scheduler
address where nothing listens, or that is not an address, is one line and exit status 2, at once.
"""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import free_port
from test_readme import _command, _lines

from pipeline.engine.execute.process import THREAD_ENV
from stages import synthetic

REPO = Path(__file__).resolve().parents[2]

#: Enough drawings (ten tasks each) that a worker killed after its first results leaves work behind.
DRAWINGS = {"line": synthetic.line(64), "vee": synthetic.vee(64), "tee": synthetic.tee(64),
            "cross": synthetic.cross(64), "wye": synthetic.wye(64), "circle": synthetic.circle(64)}

#: Results a worker stores before it is killed: past its imports, holding results others depend on.
KILL_AFTER = 3


def _env() -> dict[str, str]:
    """The worktree's code and the engine's one-thread pinning, as the local cluster's workers get."""
    return dict(os.environ, **THREAD_ENV, PYTHONUNBUFFERED="1", PYTHONPATH=str(REPO))


@pytest.fixture
def process_groups():
    """Start commands, each in a process group of its own (a worker and the nanny that spawned it);
    every group is ended when the test ends, passed or failed: SIGTERM, then SIGKILL after 20 s."""
    started: list[subprocess.Popen] = []

    def start(args: list[str], cwd: Path) -> subprocess.Popen:
        p = subprocess.Popen(args, cwd=cwd, env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                             start_new_session=True)
        started.append(p)
        return p

    try:
        yield start
    finally:
        for p in started[::-1]:
            _signal_group(p, signal.SIGTERM)
        for p in started[::-1]:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                pass
            _signal_group(p, signal.SIGKILL)  # the group: a nanny's worker may outlive its nanny
            p.wait()


def _signal_group(p: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(p.pid, sig)
    except ProcessLookupError:  # the group has ended already
        pass


def _group_of(pid: int) -> int | None:
    try:
        return os.getpgid(pid)
    except ProcessLookupError:
        return None


@pytest.mark.slow
def test_a_worker_killed_mid_batch_leaves_the_svgs_byte_identical(tmp_path, cli, process_groups):
    """The README's scheduler, its worker command on two "machines" and its ``polyvec`` line; the first
    worker to store :data:`KILL_AFTER` results is killed (SIGKILL, with its nanny) while polyvec runs."""
    from distributed import Client

    scheduler, worker, run = (shlex.split(_command(line)) for line in _lines("A remote dask cluster"))
    assert scheduler[:2] == ["dask", "scheduler"] and worker[:2] == ["dask", "worker"] and run[0] == "polyvec"
    port = free_port()
    address, shared = f"tcp://127.0.0.1:{port}", tmp_path / "shared"

    def adapt(args: list[str]) -> list[str]:
        return [a.replace("HOST:8786", f"127.0.0.1:{port}").replace("/shared/", f"{shared}/") for a in args]

    scheduler = adapt(scheduler) + ["--host", "127.0.0.1", "--port", str(port), "--no-dashboard"]
    worker = adapt(worker) + ["--no-dashboard"]
    worker[worker.index("--nworkers") + 1] = "1"     # each machine here has one core
    run = adapt(run)
    assert f"runtime.scheduler_address={address}" in run
    folder = Path(next(a for a in run[1:] if "=" not in a))
    folder.mkdir(parents=True)
    for name, drawing in DRAWINGS.items():
        (folder / f"{name}.png").write_bytes(drawing.png_bytes())
    store = Path(next(a for a in run if a.startswith("store.path=")).split("=", 1)[1])
    out = tmp_path / next(a for a in run if a.startswith("output=")).split("=", 1)[1]

    machines = tmp_path / "machines"   # the scheduler and workers run in folders of their own
    machines.mkdir()
    process_groups([sys.executable, "-m", "dask", *scheduler[1:]], machines)
    workers = [process_groups([sys.executable, "-m", "dask", *worker[1:]], machines) for _ in range(2)]

    local = cli(str(folder), f"output={tmp_path / 'local'}", f"store.path={tmp_path / 'local-store'}",
                "runtime.cluster=sync", cwd=tmp_path)  # meanwhile the workers import and register
    assert local.returncode == 0, local.stderr[-2000:]
    with Client(address, timeout=60) as client:
        client.wait_for_workers(2, timeout=180)

    remote = subprocess.Popen([sys.executable, "-m", "pipeline.launch", *run[1:]], cwd=tmp_path, env=_env(),
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    groups = {w.pid for w in workers}
    stored_by: dict[int, list[Path]] = {g: [] for g in groups}
    seen: set[Path] = set()
    killed = None
    try:
        deadline = time.monotonic() + 600
        while killed is None and remote.poll() is None and time.monotonic() < deadline:
            for manifest in set(store.glob("*/*/*/manifest.json")) - seen:
                seen.add(manifest)
                group = _group_of(json.loads(manifest.read_text())["pid"])
                if group in stored_by:
                    stored_by[group].append(manifest)
            done = len(list(store.glob("export/*/*/manifest.json")))
            victim = next((g for g, m in stored_by.items() if len(m) >= KILL_AFTER), None)
            if victim is not None and done < len(DRAWINGS) and remote.poll() is None:
                os.killpg(victim, signal.SIGKILL)
                killed = (victim, time.time(), done)
            time.sleep(0.02)
        _, err = remote.communicate(timeout=600)
    finally:
        if remote.poll() is None:
            remote.kill()
            remote.wait()
    assert killed is not None, "no worker was killed while polyvec ran"
    assert remote.returncode == 0, err[-2000:]
    victim, at, done = killed
    assert done < len(DRAWINGS)
    # The surviving worker finished the batch: results it stored after the kill.
    survivor = (groups - {victim}).pop()
    after = [m for m in store.glob("*/*/*/manifest.json") if json.loads(m.read_text())["written_at"] > at]
    assert after and {_group_of(json.loads(m.read_text())["pid"]) for m in after} == {survivor}
    names = sorted(f"{name}.svg" for name in DRAWINGS)
    assert sorted(p.name for p in out.glob("*.svg")) == names
    assert {n: (out / n).read_bytes() for n in names} == {n: (tmp_path / "local" / n).read_bytes() for n in names}


@pytest.mark.parametrize("address, why", [("tcp://127.0.0.1:{port}", "nothing listens there"),
                                          ("127.0.0.1", "is not a dask scheduler address")])
def test_a_scheduler_that_is_not_there_is_one_line_at_once(tmp_path, cli, address, why):
    """Nothing listening at the address (or no address at all): exit status 2 and one line, well within
    the connect timeout (dask's client retries a refused connection until it), no store left behind."""
    (tmp_path / "line.png").write_bytes(synthetic.line(size=40).png_bytes())
    address = address.format(port=free_port())
    start = time.monotonic()
    proc = cli("line.png", f"runtime.scheduler_address={address}", "runtime.connect_timeout_s=60", cwd=tmp_path)
    elapsed = time.monotonic() - start
    assert elapsed < 30, f"{elapsed:.0f} s: the connect timeout (60 s) was waited out"
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("polyvec: error: ") and why in lines[0], proc.stderr[-2000:]
    assert address in lines[0]
    assert not (tmp_path / "artifacts").exists()
