"""The stage DAG through the store: cache hits, partial recomputation, failures, dask clusters."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time

import pytest

from pipeline.engine.execute import batch as batch_mod
from pipeline.engine.execute import in_process, node, process
from pipeline.engine.execute import child as child_process
from pipeline.engine.execute.base import BatchResult, TaskResult
from pipeline.engine.execute.batch import run_batch
from pipeline.engine.execute.dask_cluster import close_client
from pipeline.engine.plan import Task
from pipeline.engine.registry import active_stages
from stages import synthetic


@pytest.fixture
def images(tmp_path):
    paths = []
    for name, d in (("line", synthetic.line(size=40, width=3)), ("vee", synthetic.vee(size=48, width=3))):
        p = tmp_path / f"{name}.png"
        p.write_bytes(d.png_bytes())
        paths.append(p)
    return paths


def _statuses(batch):
    return {stage: sorted(r.status for per in batch.results.values() for s, r in per.items() if s == stage)
            for stage in batch.stages}


def test_second_identical_run_computes_nothing(tmp_path, images, compose_cfg):
    cfg = compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.cluster=sync", "runtime.until=field")
    first = run_batch(images, cfg)
    assert first.stages == ["prep", "field"]
    assert all(st == ["computed", "computed"] for st in _statuses(first).values())
    second = run_batch(images, cfg)
    assert all(st == ["cached", "cached"] for st in _statuses(second).values())
    assert first.keys(str(images[0])) == second.keys(str(images[0]))


def test_field_parameter_recomputes_field_not_prep(tmp_path, images, compose_cfg):
    store = f"store.path={tmp_path / 'store'}"
    run_batch(images, compose_cfg(store, "runtime.cluster=sync", "runtime.until=field"))
    changed = run_batch(images, compose_cfg(store, "runtime.cluster=sync", "runtime.until=field", "field.beta=12"))
    st = _statuses(changed)
    assert st["prep"] == ["cached", "cached"]
    assert st["field"] == ["computed", "computed"]


def test_bad_image_does_not_stop_the_batch(tmp_path, images, compose_cfg):
    bad = tmp_path / "corrupt.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    cfg = compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.cluster=sync", "runtime.until=field")
    batch = run_batch([images[0], bad, images[1]], cfg)
    assert list(batch.failed_images) == [str(bad)]
    assert batch.results[str(bad)]["field"].status == "skipped"
    assert batch.results[str(images[1])]["field"].status == "computed"


def test_local_dask_cluster(tmp_path, images, compose_cfg):
    cfg = compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.until=field")
    try:
        batch = run_batch(images, cfg)
    finally:
        close_client()
    assert not batch.failed_images
    assert _statuses(batch)["field"] == ["computed", "computed"]


def test_local_cluster_runs_the_stages_with_most_work_behind_them_first(tmp_path, compose_cfg):
    """Dask follows the engine's priorities, root tasks included: on one worker, every image's prep (the
    most stages behind it) runs before any field, where image after image would interleave them."""
    from pipeline.engine.store import ArtifactStore

    paths = []
    for k in range(4):
        p = tmp_path / f"line{k}.png"
        p.write_bytes(synthetic.line(size=40 + 4 * k, width=3).png_bytes())
        paths.append(p)
    cfg = compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.until=field", "runtime.cluster=local",
                      "runtime.workers=1")
    try:
        batch = run_batch(paths, cfg)
    finally:
        close_client()
    assert not batch.failed_images
    store = ArtifactStore(tmp_path / "store")

    def started_at(r):
        m = store.manifest(r.stage, r.key)
        return m["written_at"] - m["duration_s"]

    started = {stage: [started_at(per[stage]) for per in batch.results.values()] for stage in ("prep", "field")}
    assert len(started["prep"]) == len(started["field"]) == 4
    assert max(started["prep"]) < min(started["field"])


def test_batch_priorities_start_images_in_order_and_end_on_short_tasks():
    from pipeline.engine.registry import BY_NAME, height
    from pipeline.engine.execute.dask_cluster import TAIL_IMAGES, priority

    assert height("export") == 1 and height("prep") == max(height(s) for s in BY_NAME)
    assert all(height(s) > height(d) for d in BY_NAME for s in BY_NAME[d].inputs)
    n = 40
    assert priority("prep", 1, n) > priority("export", 0, n)       # the next image starts beside an ending one
    assert priority("export", 0, n) > priority("prep", 10, n)      # ... but a far one waits
    tail = [priority("graph", i, n) for i in range(n - TAIL_IMAGES, n)]
    assert len(set(tail)) == 1                                     # the last images share one place
    assert priority("keypoints", n - 1, n) > priority("flow", n - 2, n)   # the tail runs stage by stage
    assert priority("prep", 0, 3) == priority("prep", 2, 3)               # a small batch is all tail


def test_local_cluster_workers_leave_without_interpreter_teardown(tmp_path, images, compose_cfg):
    """Once the batch is done, a local worker holding the stages' modules exits at once (os._exit after
    the exit handlers): an object that only the interpreter's teardown would collect is never collected.
    And it ran its tasks without dask's profiler."""
    from pipeline.engine.execute.dask_cluster import get_client

    marker_dir = tmp_path / "torn_down"
    marker_dir.mkdir()
    cfg = compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.until=field", "runtime.workers=1")

    def plant(folder=str(marker_dir)):
        import os as _os
        import sys as _sys
        import types

        class Probe:
            def __del__(self, _os=_os, folder=folder):
                _os.close(_os.open(_os.path.join(folder, str(_os.getpid())), _os.O_CREAT | _os.O_WRONLY))

        module = types.ModuleType("polyvec_teardown_probe")
        module.probe = Probe()  # collected only when the interpreter clears its modules
        _sys.modules[module.__name__] = module

    try:
        batch = run_batch(images, cfg)
        client = get_client(cfg.runtime)
        pids = client.run(os.getpid)
        # Nor does a worker run dask's statistical profiler (a stack sample of every thread each 10 ms,
        # for a dashboard page; stages/DECISIONS.md, engine).
        callbacks = client.run(lambda dask_worker: sorted(dask_worker.periodic_callbacks))
        client.run(plant)
    finally:
        close_client()
    assert not batch.failed_images
    assert callbacks and all("heartbeat" in c and "profile" not in c for c in callbacks.values()), callbacks
    for pid in pids.values():  # gone, without a teardown
        for _ in range(100):
            try:
                os.kill(pid, 0)
            except OSError:
                break
            time.sleep(0.05)
    assert list(marker_dir.iterdir()) == []


def _page_faults_of_fresh_arrays(n: int = 40) -> int:
    """Minor page faults while this process makes and drops ``n`` 1-MiB arrays, one after another
    (after one such array, so that a heap that must first grow does not count). 1 MiB: over the
    128 KiB that dask's setting freezes, under a transparent huge page (2 MiB), so 256 faults each."""
    import resource

    import numpy as np

    np.ones(1 << 17).sum()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(n):
        np.ones(1 << 17).sum()
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


_GLIBC = pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc",
                            reason="glibc's malloc only")


@_GLIBC
def test_a_process_that_runs_stages_reuses_freed_arrays_memory():
    """Under dask's MALLOC_TRIM_THRESHOLD_ (which freezes glibc's mmap threshold at 128 KiB) every 1-MiB
    array is a fresh mapping, faulted in page by page; after ``reuse_freed_memory`` it comes from the heap."""
    import inspect

    child = inspect.getsource(_page_faults_of_fresh_arrays) + (
        "import sys\nfrom pipeline.engine.execute.process import reuse_freed_memory\n"
        "if sys.argv[1] == 'tuned':\n    reuse_freed_memory()\nprint(_page_faults_of_fresh_arrays())\n")
    faults = {}
    for mode in ("default", "tuned"):
        out = subprocess.run([sys.executable, "-c", child, mode], capture_output=True, text=True, check=True,
                             env=dict(os.environ, MALLOC_TRIM_THRESHOLD_="65536"))
        faults[mode] = int(out.stdout.split()[-1])
    assert faults["default"] > 40 * 200      # 256 pages an array
    assert faults["tuned"] < 40 * 10


@_GLIBC
def test_the_keypoints_child_keeps_arrays_over_the_mmap_ceiling_in_its_heap():
    """Arrays over glibc's largest mmap threshold (32 MiB; the network's 63-MB activations at 704²)
    are fresh mappings even after ``reuse_freed_memory``; ``keep_network_memory`` serves them from the heap."""
    child = (
        "import resource, sys\nimport torch\nfrom pipeline.engine.execute import process\n"
        # one thread: intra-op threads allocate in arenas of their own, a growth this test does not measure
        "torch.set_num_threads(1)\n"
        "process.keep_network_memory() if sys.argv[1] == 'network' else process.reuse_freed_memory()\n"
        # the heap grows until a free run fits torch's aligned request (memalign pads it, and small
        # allocations between two arrays split the freed ones): at most 6 arrays here, by 40 runs
        "for _ in range(8):\n    torch.ones(5 << 20, dtype=torch.float64).sum()\n"
        "before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
        # torch's tensors, not numpy's: numpy asks for transparent huge pages (512 times fewer faults)
        "for _ in range(16):\n    torch.ones(5 << 20, dtype=torch.float64).sum()\n"   # 40 MiB each: 10,240 pages
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)\n")
    faults = {mode: int(subprocess.run([sys.executable, "-c", child, mode], capture_output=True, text=True,
                                       check=True).stdout.split()[-1]) for mode in ("stages", "network")}
    assert faults["stages"] > 16 * 8000
    # the heap may still grow a few times (glibc's bins; 30,720 and 40,960 faults seen on a busy machine),
    # still well under the fresh mappings' 16 × 10,240
    assert faults["network"] < faults["stages"] // 3


def test_the_keypoints_child_sets_its_heap_before_its_stages_load():
    """The child (``_serve_tasks``) keeps its network's memory from its first task on."""
    import inspect

    from pipeline.engine.execute.child import serve_tasks as _serve_tasks

    body = inspect.getsource(_serve_tasks)
    assert body.index("keep_network_memory()") < body.index("BY_NAME[name].load()")


@_GLIBC
def test_local_cluster_workers_reuse_freed_arrays_memory(tmp_path, images, compose_cfg):
    """A local worker that has run a task keeps freed arrays' memory for the next ones (dask's own
    setting gave it back and faulted it in again: a quarter of a 2-worker batch's CPU seconds)."""
    from pipeline.engine.execute.dask_cluster import get_client

    cfg = compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.until=prep", "runtime.workers=1",
                      "runtime.cluster=local")
    try:
        batch = run_batch(images, cfg)
        counts = get_client(cfg.runtime).run(_page_faults_of_fresh_arrays)
    finally:
        close_client()
    assert not batch.failed_images
    assert counts and all(c < 40 * 10 for c in counts.values())


@pytest.mark.slow
def test_existing_scheduler_and_worker_processes(tmp_path, images, compose_cfg):
    """runtime.scheduler_address joins a dask scheduler and worker started as separate processes."""
    from conftest import free_port

    port = free_port()
    addr = f"tcp://127.0.0.1:{port}"
    bin_dir = [sys.executable, "-m"]
    sched = subprocess.Popen(bin_dir + ["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port",
                                        str(port), "--no-dashboard"], stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
    # The worker as on another machine: a numba cache of its own, empty, and no CPU target set by us.
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_CPU_")}
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "worker numba cache")
    worker = subprocess.Popen(bin_dir + ["distributed.cli.dask_worker", addr, "--nthreads", "1", "--no-dashboard",
                                         "--name", "polyvec-test-worker"], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, env=env)
    try:
        cfg = compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.until=graph",
                          f"runtime.scheduler_address={addr}")
        from conftest import wait_for_dask_worker

        wait_for_dask_worker(addr)
        batch = run_batch(images, cfg)
        assert not batch.failed_images
        assert _statuses(batch)["graph"] == ["computed", "computed"]
        from pipeline.engine.store import ArtifactStore

        manifest = ArtifactStore(tmp_path / "store").manifest("field", batch.keys(str(images[0]))["field"])
        assert manifest["pid"] != os.getpid()  # computed by the external worker
        # The package's compiled kernels were copied into the worker's cache: it compiled none.
        from pipeline.engine.kernels.shipped import SHIPPED, MANIFEST

        if json.loads((SHIPPED / MANIFEST).read_text())["target"]["cpu_name"] == os.environ.get("NUMBA_CPU_NAME"):
            from distributed import Client

            def graph_kernel_stats() -> dict:  # in the worker (a nested function: dask sends it by value)
                import gc

                from numba.core.dispatcher import Dispatcher

                return {o.py_func.__name__: (sum(o.stats.cache_hits.values()), sum(o.stats.cache_misses.values()))
                        for o in gc.get_objects()
                        if isinstance(o, Dispatcher) and o.py_func.__module__.startswith("stages.graph")}

            with Client(addr, timeout=30) as client:
                (stats,) = client.run(graph_kernel_stats).values()
            assert stats["_trace_all"][0] >= 1 and not any(miss for _, miss in stats.values()), stats
    finally:
        close_client()
        worker.terminate()
        sched.terminate()
        worker.wait(20)
        sched.wait(20)


def test_until_and_unknown_stage():
    assert [s.name for s in active_stages("field")] == ["prep", "field"]
    with pytest.raises(ValueError, match="unknown stage"):
        active_stages("nonsense")


def test_auto_cluster_runs_a_few_images_in_process_and_more_on_dask():
    from types import SimpleNamespace

    from pipeline.engine.execute.batch import SYNC_MAX_IMAGES, cluster_mode

    def tasks(*stages):
        return [SimpleNamespace(stage=s) for s in stages]

    auto = {"cluster": "auto", "scheduler_address": None, "workers": 2}
    # A λ re-run of one image: flow → select → export is a chain, nothing can run side by side.
    assert cluster_mode(auto, [tasks("flow", "select", "export")]) == "sync"
    # A first run of one image: keypoints and field could run side by side, but starting the workers
    # costs more than that gains.
    assert cluster_mode(auto, [tasks("prep", "keypoints", "field", "graph")]) == "sync"
    # A few drawings: the workers' start and imports cost more than they gain (2-4 drawings 12-37 %
    # slower on two workers); more: dask's two processes run them faster.
    assert SYNC_MAX_IMAGES == 4
    assert cluster_mode(auto, [tasks("prep", "keypoints")] * 4) == "sync"
    assert cluster_mode(auto, [tasks("prep", "keypoints")] * 5) == "local"
    # ... unless more workers are asked for than the in-process scheduler's two threads
    assert cluster_mode(auto | {"workers": 4}, [tasks("flow"), tasks("flow")]) == "local"
    assert cluster_mode(auto | {"workers": 4}, [tasks("flow")]) == "sync"
    assert cluster_mode(auto | {"scheduler_address": "tcp://h:1"}, [tasks("flow")]) == "local"
    assert cluster_mode({"cluster": "sync"}, [tasks("prep", "keypoints", "field")]) == "sync"
    assert cluster_mode({"cluster": "local"}, [tasks("flow")]) == "local"


def test_artifact_memo_reuses_and_protects_loaded_artifacts(tmp_path):
    import numpy as np
    from pipeline.engine.store import ArtifactStore
    from stages.artifact import Artifact

    store = ArtifactStore(tmp_path / "store")
    store.save("prep", "k" * 64, Artifact(arrays={"grey": np.ones((4, 4), np.float32)}, data={"n": 1}), {})
    node._MEMO.clear()
    a = node.load_artifact(store, "prep", "k" * 64)
    assert node.load_artifact(store, "prep", "k" * 64) is a  # the second read comes from the memo
    with pytest.raises(ValueError):
        a["grey"][0, 0] = 0.0  # a stage must not modify its inputs: the next stage shares them
    for i in range(node.MEMO_SIZE + 1):  # bounded: old artifacts are dropped
        node._remember("x", str(i), Artifact(arrays={}, data={}))
    assert ("prep", "k" * 64) not in node._MEMO and len(node._MEMO) == node.MEMO_SIZE
    big = Artifact(arrays={"a": np.zeros(node.MEMO_BYTES // 8 + 1)}, data={})
    node._remember("big", "b", big)  # larger than the byte budget: not kept
    assert ("big", "b") not in node._MEMO
    node._MEMO.clear()


def test_a_stage_whose_module_is_missing_fails_the_run(monkeypatch):
    """A broken install (a stage package gone) is an error, never a shorter DAG."""
    import pipeline.engine.registry as registry

    broken = tuple(registry.StageSpec(s.name, "stages.no_such_module", s.inputs, s.persists) if s.name == "graph"
                   else s for s in registry.STAGES)
    monkeypatch.setattr(registry, "STAGES", broken)
    with pytest.raises(registry.StageUnavailable, match="stage graph: cannot import stages.no_such_module"):
        registry.active_stages()
    assert [s.name for s in registry.active_stages("field")] == ["prep", "field"]


def test_a_stage_imports_its_code_only_when_it_computes(tmp_path, images, compose_cfg, monkeypatch):
    """A run imports a stage's package (STAGE_VERSION, configs); its code loads only when the stage has work,
    and code that cannot load (a broken install) stops the run once, before any work (issue 14)."""
    import pipeline.engine.registry as registry

    pkg = tmp_path / "fake_field"
    pkg.mkdir()
    (pkg / "__init__.py").write_text('from stages.lazy import lazy_names\n\nSTAGE_VERSION = "1"\n'
                                     '__getattr__, __dir__ = lazy_names(__name__, {"fake_field.stage": ("run",)})\n')
    (pkg / "stage.py").write_text("from stages.artifact import Artifact\n\n\ndef run(cfg, prep):\n"
                                  "    return Artifact(arrays={}, data={'ink': prep.data['ink_fraction']})\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    fake = registry.StageSpec("field", "fake_field", ("prep",), "")
    monkeypatch.setattr(registry, "STAGES", tuple(fake if s.name == "field" else s for s in registry.STAGES))
    monkeypatch.setitem(registry.BY_NAME, "field", fake)
    store = f"store.path={tmp_path / 'store'}"
    cfg = compose_cfg(store, "runtime.cluster=sync", "runtime.until=field")
    assert _statuses(run_batch(images, cfg))["field"] == ["computed", "computed"]
    (pkg / "stage.py").write_text("import no_such_library\n")   # the code breaks ...
    monkeypatch.delitem(sys.modules, "fake_field.stage")
    assert _statuses(run_batch(images, cfg))["field"] == ["cached", "cached"]   # ... and a cached run never sees it
    assert "fake_field.stage" not in sys.modules
    with pytest.raises(registry.StageUnavailable, match="stage field: cannot import fake_field .*no_such_library"):
        run_batch(images, compose_cfg(store, "runtime.cluster=sync", "runtime.until=field", "field.beta=12"))
    assert len(list((tmp_path / "store" / "field").glob("*/*"))) == 2   # nothing ran


# -- the per-path memo of the flow (a per-item stage) ---------------------------------------------
def _example(folder):
    folder.mkdir()
    img = folder / "drawing.png"
    img.write_bytes(synthetic.example_drawing().png_bytes())
    return img


def _add_junction(img):
    import json

    img.with_name(img.stem + ".keypoints.json").write_text(json.dumps(
        {"format": "polyvec-keypoint-edits", "version": 1, "added": [{"x": 40.0, "y": 150.0, "type": "junction"}]}))


def _same_artifact(a, b):
    assert a.data == b.data
    assert set(a.arrays) == set(b.arrays)
    for name in a.arrays:
        assert a.arrays[name].dtype == b.arrays[name].dtype and a.arrays[name].tobytes() == b.arrays[name].tobytes()


def test_a_keypoint_edit_reruns_the_flow_on_the_changed_paths_only(tmp_path, compose_cfg):
    """After a keypoint correction the flow reuses the unchanged paths' stored results, and the flow
    artifact and SVG are byte-identical to those of a run with the same edits on an empty store."""
    from pipeline.engine.store import ArtifactStore

    img = _example(tmp_path / "in")
    cfg = compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.cluster=sync")
    first = run_batch([img], cfg).results[str(img)]
    assert first["flow"].items[0] == 0 and first["flow"].items[1] > 5
    _add_junction(img)
    edited = run_batch([img], cfg).results[str(img)]
    assert edited["topology"].status == "computed" and edited["flow"].status == "computed"
    reused, total = edited["flow"].items
    assert 0 < reused < total
    assert ArtifactStore(tmp_path / "store").manifest("flow", edited["flow"].key)["items"] == {
        "reused": reused, "total": total}
    fresh = run_batch([img], compose_cfg(f"store.path={tmp_path / 'fresh'}", "runtime.cluster=sync"))
    fresh = fresh.results[str(img)]
    assert fresh["flow"].items == (0, total) and fresh["flow"].key == edited["flow"].key
    for stage in ("flow", "export"):
        _same_artifact(ArtifactStore(tmp_path / "store").load(stage, edited[stage].key),
                       ArtifactStore(tmp_path / "fresh").load(stage, fresh[stage].key))


def test_a_corrupted_or_missing_stored_path_is_flowed_again(tmp_path, compose_cfg):
    """The paths one flow computed are stored as one pack; a result in it that is corrupted (its
    digest) or torn (a truncated pack) is flowed again, the rest reused, and the new results stored."""
    import json
    import shutil

    from pipeline.engine.store import PACK_MAGIC, ArtifactStore

    img = _example(tmp_path / "in")
    cfg = compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.cluster=sync", "runtime.until=flow")
    store = ArtifactStore(tmp_path / "store")
    first = run_batch([img], cfg).results[str(img)]["flow"]
    reference = store.load("flow", first.key)
    packs = sorted((tmp_path / "store" / ".items" / "flow").rglob("*.pack"))
    assert len(packs) == 1                                               # one file, not one per path
    raw = bytearray(packs[0].read_bytes())
    at = len(PACK_MAGIC) + 4
    end = at + int.from_bytes(raw[len(PACK_MAGIC):at], "little")
    index = json.loads(raw[at:end])
    assert len(index) == first.items[1]
    raw[end + index[0][1] + index[1][1] // 2] ^= 0xFF                    # one flipped byte in the second result
    packs[0].write_bytes(bytes(raw[:-10]))                               # and the last one torn
    shutil.rmtree(store.path_for("flow", first.key))
    again = run_batch([img], cfg).results[str(img)]["flow"]
    assert again.status == "computed" and again.items == (first.items[1] - 2, first.items[1])
    _same_artifact(store.load("flow", again.key), reference)
    scope = packs[0].parent.name
    assert all(r is not None for r in store.load_items("flow", scope, [index[1][0], index[-1][0]]))  # written again
    assert len(sorted((tmp_path / "store" / ".items" / "flow").rglob("*.pack"))) == 2


def test_stored_paths_are_not_reused_under_another_iteration_count(tmp_path, compose_cfg):
    """The max_vertices guard lowers the iterations of every path: paths flowed under it are keyed
    apart; a max_vertices that does not bind changes nothing a path depends on."""
    from pipeline.engine.store import ArtifactStore

    img = _example(tmp_path / "in")
    store = f"store.path={tmp_path / 'store'}"
    total = run_batch([img], compose_cfg(store, "runtime.cluster=sync", "runtime.until=flow")
                      ).results[str(img)]["flow"].items[1]
    loose = run_batch([img], compose_cfg(store, "runtime.cluster=sync", "runtime.until=flow",
                                         "flow.max_vertices=1000000")).results[str(img)]["flow"]
    assert loose.status == "computed" and loose.items == (total, total)
    tight = compose_cfg(store, "runtime.cluster=sync", "runtime.until=flow", "flow.max_vertices=500")
    guarded = run_batch([img], tight).results[str(img)]["flow"]
    assert guarded.warnings and guarded.items == (0, total)
    fresh = run_batch([img], compose_cfg(f"store.path={tmp_path / 'fresh'}", "runtime.cluster=sync",
                                         "runtime.until=flow", "flow.max_vertices=500")).results[str(img)]["flow"]
    _same_artifact(ArtifactStore(tmp_path / "store").load("flow", guarded.key),
                   ArtifactStore(tmp_path / "fresh").load("flow", fresh.key))


def test_an_in_process_run_lets_numba_use_its_pool_and_workers_stay_on_one_thread(tmp_path, compose_cfg,
                                                                                   monkeypatch):
    """The flow's paths run in parallel when the task runs alone (their results do not depend on the
    thread count); a worker beside another keeps one thread."""
    import numba

    calls = []
    monkeypatch.setattr(numba, "set_num_threads", calls.append)
    image = tmp_path / "line.png"
    image.write_bytes(synthetic.line(size=40, width=3).png_bytes())
    run_batch([image], compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.cluster=sync",
                                   "runtime.until=field"))
    assert calls and set(calls) == {numba.config.NUMBA_NUM_THREADS}
    calls.clear()
    process.pin_threads()
    assert calls == [1]


def test_in_process_scheduler_runs_the_keypoints_beside_the_field_and_keeps_dag_order(monkeypatch):
    """The in-process executor: two tasks at once where the DAG allows (keypoints ‖ field → graph), never a task
    before its inputs, and one image's failure skips only what reads it."""
    import threading
    import time
    from pipeline.engine.registry import STAGES

    log, lock = [], threading.Lock()

    def fake_execute(task, store_url, *upstream, alone=False):
        with lock:
            log.append(("start", task.stage, time.perf_counter()))
        time.sleep(0.15)
        status = "failed" if task.stage == "keypoint_edits" else "computed"
        if any(u.status in ("failed", "skipped") for u in upstream):
            status = "skipped"
        with lock:
            log.append(("end", task.stage, time.perf_counter()))
        return TaskResult(task.image, task.stage, task.key, status)

    monkeypatch.setattr(in_process, "execute", fake_execute)
    tasks = [Task("a.png", "k", s.name, "1", s.name, {i: i for i in s.inputs}, {}) for s in STAGES]

    def run(pixels):
        monkeypatch.setattr(in_process, "_prep_pixels", lambda url, key: pixels)
        log.clear()
        batch = BatchResult(stages=[s.name for s in STAGES])
        batch.results["a.png"] = {}
        reported = []
        in_process.InProcessExecutor().run([tasks], "unused", batch, reported.append)
        return {(kind, stage): t for kind, stage, t in log}, reported

    # a large drawing: one task at a time (peak memory of its largest stage)
    when, _ = run(in_process.SYNC_PARALLEL_MAX_PIXELS + 1)
    assert when[("start", "field")] >= when[("end", "keypoints")] or when[("start", "keypoints")] >= when[("end", "field")]
    when, reported = run(700 * 700)
    # the keypoints and the field ran at once
    assert when[("start", "field")] < when[("end", "keypoints")] and when[("start", "keypoints")] < when[("end", "field")]
    for s in STAGES:          # no task before its inputs ended
        for i in s.inputs:
            assert when[("start", s.name)] >= when[("end", i)]
    status = {r.stage: r.status for r in reported}
    assert status["graph"] == "computed" and status["keypoint_edits"] == "failed"
    assert status["topology"] == status["flow"] == status["export"] == "skipped"


def _logged_scheduler(monkeypatch, pixels, cost=None, images=("a.png",)):
    """The in-process scheduler with its tasks replaced by sleeps (``cost[stage]`` s, else 0.15 s) that
    log their start and end, and a child that runs its tasks one at a time on the calling thread.

    Returns ``run(in_child) -> {("start"|"end", name): time, ("where", name): "child"|"here"}`` over
    every stage of ``images``; a name is the stage's for the first image, ``"b.field"`` for the others.
    """
    import threading
    import time
    from pipeline.engine.registry import STAGES

    log, lock = [], threading.Lock()

    def logged(task, where="here"):
        name = task.stage if task.image == images[0] else f"{task.image.split('.')[0]}.{task.stage}"
        with lock:
            log.append(("start", name, time.perf_counter()))
            log.append(("where", name, where))
        time.sleep((cost or {}).get(task.stage, 0.15))
        with lock:
            log.append(("end", name, time.perf_counter()))
        return TaskResult(task.image, task.stage, task.key, "computed")

    class FakeChild:   # the child's interface
        def __init__(self, stages):
            self.busy = threading.Lock()

        def run(self, task, store_url, upstream):
            with self.busy:
                return logged(task, "child")

        def close(self, kill=False):
            pass

        def join(self, timeout_s=5.0):
            pass

    monkeypatch.setattr(in_process, "execute", lambda task, store_url, *up, alone=False: logged(task))
    monkeypatch.setattr(in_process, "ChildTasks", FakeChild)
    monkeypatch.setattr(in_process, "_prep_pixels", lambda url, key: pixels)
    pending = [[Task(image, image, s.name, "1", s.name, {i: i for i in s.inputs}, {}) for s in STAGES]
               for image in images]

    def run(in_child):
        log.clear()
        batch = BatchResult(stages=[s.name for s in STAGES])
        for image in images:
            batch.results[image] = {}
        in_process.InProcessExecutor(in_child).run(pending, "unused", batch, lambda r: None)
        assert all(r.status == "computed" for image in images for r in batch.results[image].values())
        return {(kind, name): t for kind, name, t in log}

    return run


def test_a_large_drawing_still_runs_its_keypoints_child_beside_this_process(monkeypatch):
    """Over ``SYNC_PARALLEL_MAX_PIXELS`` this process runs a task at a time, but the keypoints child
    (its own memory) still runs beside it: a 300-dpi A4 page took the sum of the two (42 s, 32 s now)."""
    from pipeline.engine.registry import STAGES

    run = _logged_scheduler(monkeypatch, in_process.SYNC_PARALLEL_MAX_PIXELS + 1)
    when = run(child_process.CHILD_STAGES)
    assert when[("start", "field")] < when[("end", "keypoints")] and when[("start", "keypoints")] < when[("end", "field")]
    # never two tasks at once in this process: each task of this process starts after the previous ended
    mine = sorted((when[("start", s.name)], when[("end", s.name)]) for s in STAGES if when[("where", s.name)] == "here")
    assert all(b[0] >= a[1] for a, b in zip(mine, mine[1:]))
    when = run(())   # the keypoints on a thread of this process: one task at a time, as before
    assert when[("start", "field")] >= when[("end", "keypoints")] or when[("start", "keypoints")] >= when[("end", "field")]


def test_the_child_runs_one_task_at_a_time_and_never_holds_up_this_process(monkeypatch):
    """While the child computes the keypoints, the graph and then the extension (it needs no torch) run
    on this process's free thread, the graph first, instead of queueing behind the keypoints; with the
    child idle when the extension is ready, the extension runs there, beside the graph."""

    run = _logged_scheduler(monkeypatch, 700 * 700, cost={"keypoints": 0.6, "field": 0.05, "graph": 0.1})
    when = run(child_process.CHILD_STAGES)
    assert set(child_process.CHILD_STAGES) == {"keypoints", "extension"}
    assert when[("where", "keypoints")] == "child" and when[("where", "extension")] == "here"
    assert when[("start", "graph")] < when[("end", "keypoints")]     # not queued behind the child
    assert when[("end", "graph")] <= when[("start", "extension")] < when[("end", "keypoints")]
    # a drawing whose keypoints end first: its extension goes to the child, beside the graph here
    when = _logged_scheduler(monkeypatch, 700 * 700, cost={"keypoints": 0.1, "field": 0.05, "graph": 0.6})(
        child_process.CHILD_STAGES)
    assert when[("where", "extension")] == "child"
    assert when[("start", "extension")] >= when[("end", "keypoints")]
    assert when[("start", "extension")] < when[("end", "graph")]


def test_with_stages_of_its_own_to_run_this_process_leaves_the_extension_to_the_child(monkeypatch):
    """Two drawings: while the child computes keypoints, this process runs the other drawing's field and
    graph before it takes an extension (the child would compute it later beside them)."""

    when = _logged_scheduler(monkeypatch, 700 * 700, images=("a.png", "b.png"),
                             cost={"keypoints": 0.5, "prep": 0.05, "field": 0.05, "graph": 0.1})(child_process.CHILD_STAGES)
    assert when[("start", "b.field")] < when[("end", "keypoints")]   # the child busy meanwhile
    assert when[("start", "graph")] < when[("start", "b.field")] < when[("start", "extension")]
    assert when[("start", "b.graph")] < when[("start", "extension")]


def test_an_extension_without_keypoints_to_compute_starts_no_child(monkeypatch):
    """A run whose keypoints are stored (a field setting changed) computes the extension here: no child
    process, with its imports, is started for it."""
    from pipeline.engine.registry import STAGES

    started = []
    monkeypatch.setattr(in_process, "ChildTasks", lambda *a, **k: started.append(a))
    monkeypatch.setattr(in_process, "execute", lambda task, store_url, *up, alone=False:
                        TaskResult(task.image, task.stage, task.key, "computed"))
    monkeypatch.setattr(in_process, "_prep_pixels", lambda url, key: 700 * 700)
    todo = [s for s in STAGES if s.name in ("extension", "flow", "select", "export")]
    tasks = [Task("a.png", "k", s.name, "1", s.name, {i: i for i in s.inputs}, {}) for s in todo]
    batch = BatchResult(stages=[s.name for s in STAGES])
    batch.results["a.png"] = {}
    in_process.InProcessExecutor(child_process.CHILD_STAGES).run([tasks], "unused", batch, lambda r: None)
    assert [r.status for r in batch.results["a.png"].values()] == ["computed"] * 4
    assert not started


def test_in_process_runs_compute_the_keypoints_in_a_child_process(tmp_path, compose_cfg, monkeypatch):
    """``runtime.keypoints_process``: an in-process run computes the keypoints, then the field's
    extension, in a child process (beside the field and graph on this process's threads, free of the
    GIL) with the same artifacts; the child is gone when the run returns."""
    import json
    import multiprocessing

    import numpy as np

    image = tmp_path / "vee.png"
    image.write_bytes(synthetic.vee(size=48, width=3).png_bytes())
    pids, keys = {}, {}
    for flag in ("true", "false"):
        store = tmp_path / f"store-{flag}"
        batch = run_batch([image], compose_cfg(f"store.path={store}", "runtime.cluster=sync",
                                               f"runtime.keypoints_process={flag}"))
        assert all(r.status == "computed" for r in batch.results[str(image)].values())
        keys[flag] = batch.results[str(image)]["keypoints"].key
        manifests = {p.parent.parent.parent.name: json.loads(p.read_text()) for p in store.glob("*/*/*/manifest.json")}
        pids[flag] = {stage: m["pid"] for stage, m in manifests.items()}
        assert not [c for c in multiprocessing.active_children() if c.name.startswith("polyvec-")]
    assert pids["true"]["keypoints"] != os.getpid() and pids["true"]["prep"] == os.getpid()
    # the field's extension (only the flow reads it) runs in the child after the keypoints, or here
    # while the child is busy
    assert pids["true"]["extension"] in (pids["true"]["keypoints"], os.getpid()) and pids["true"]["graph"] == os.getpid()
    assert pids["false"]["keypoints"] == pids["false"]["extension"] == os.getpid()
    assert keys["true"] == keys["false"]
    # a field setting changed: the keypoints are stored, the extension is computed here, and no child starts

    started, child = [], in_process.ChildTasks
    for module in (batch_mod, in_process):   # the batch starts the child early; the executor would otherwise
        monkeypatch.setattr(module, "ChildTasks", lambda *a, **k: started.append(a) or child(*a, **k))
    batch = run_batch([image], compose_cfg(f"store.path={tmp_path / 'store-true'}", "runtime.cluster=sync",
                                           "field.alpha=0.2"))
    status = {stage: r.status for stage, r in batch.results[str(image)].items()}
    assert status["keypoints"] == "cached" and status["extension"] == "computed"
    manifest = json.loads(next((tmp_path / "store-true").glob(
        f"extension/*/{batch.results[str(image)]['extension'].key}/manifest.json")).read_text())
    assert manifest["pid"] == os.getpid() and not started
    from pipeline.engine.store import ArtifactStore
    a = ArtifactStore(str(tmp_path / "store-true")).load("keypoints", keys["true"])
    b = ArtifactStore(str(tmp_path / "store-false")).load("keypoints", keys["false"])
    assert np.array_equal(a["points"], b["points"]) and np.array_equal(a["heatmaps"], b["heatmaps"])


def test_the_keypoints_child_preloads_torch_and_the_networks_before_its_first_task(monkeypatch):
    """The child imports torch and loads the keypoints' weights and typing as soon as it starts (its
    first task used to pay ~1.1 s for them); a config its preload refuses is left to the task to report."""
    from pipeline.engine.config import default_config
    from stages.keypoints import stage as kp

    class Conn:                # no task: the child is told to stop at once
        def recv(self):
            return None

    class Exit(Exception):
        pass

    def leave(code):
        raise Exit(code)

    monkeypatch.setattr(child_process.os, "_exit", leave)
    monkeypatch.setattr(child_process, "THREAD_ENV", {})       # this process's environment stays as it is
    monkeypatch.setattr(kp, "_MODELS", {})
    monkeypatch.setattr(kp, "_TYPE_CLASSIFIERS", {})
    with pytest.raises(Exit):
        child_process.serve_tasks(Conn(), ("keypoints", "extension"), {"keypoints": default_config("keypoints")})
    assert len(kp._MODELS) == 1 and len(kp._TYPE_CLASSIFIERS) == 1 and "torch" in sys.modules
    kp._MODELS.clear()
    with pytest.raises(Exit):                              # an unknown key: no preload, no error here
        child_process.serve_tasks(Conn(), ("keypoints",), {"keypoints": {**default_config("keypoints"), "bogus": 1}})
    assert not kp._MODELS


def test_a_failed_code_check_leaves_no_keypoints_child(tmp_path, images, compose_cfg, monkeypatch):
    """The keypoints child starts before the stages' code is checked; a check that fails stops it."""
    import multiprocessing

    import pipeline.engine.registry as registry

    def broken(spec, code=False):
        if code and spec.name == "graph":
            raise registry.StageUnavailable("stage graph: broken on purpose")

    monkeypatch.setattr(batch_mod, "check_stage", broken)
    with pytest.raises(registry.StageUnavailable, match="broken on purpose"):
        run_batch(images[:1], compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.cluster=sync"))
    assert not [c for c in multiprocessing.active_children() if c.name.startswith("polyvec-")]


def test_the_keypoints_child_and_its_tasks_need_no_config_schemas():
    """The child's module and the Task it unpickles leave out the config schemas (every stage's package,
    the bench's and training's dataclasses: 30-50 ms of imports on the child's critical path)."""
    script = ("import sys\nimport pipeline.engine.execute.child, pipeline.engine.plan\n"
              "print(sorted(m for m in sys.modules if m in ('pipeline.engine.config', 'stages.evaluate', "
              "'stages.prep', 'stages.keypoints.training.config')))\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_the_keypoints_child_imports_no_more_than_its_stages_need():
    """The keypoints child's start is a small drawing's critical path: what it imports — the CLI
    module again (a spawned child re-imports the console script's ``pipeline.cli``), its stages' code
    and what their ``preload`` loads — pulls in no skimage, scipy.spatial, omegaconf, Hydra, dask or
    numba (0.1–0.3 s each that the child used to pay; stages/DECISIONS.md, engine)."""
    script = (
        "import sys, yaml\n"
        "import pipeline.cli\n"
        "from pipeline.engine.config import CONF_DIR\n"
        "from pipeline.engine.execute.child import CHILD_STAGES\n"
        "from pipeline.engine.registry import BY_NAME\n"
        "for name in CHILD_STAGES:\n"
        "    mod = BY_NAME[name].load()\n"
        "    mod.run\n"
        "    if 'preload' in dir(mod):\n"
        "        mod.preload(yaml.safe_load((CONF_DIR / name / 'default.yaml').read_text()))\n"
        "print(' '.join(m for m in ('skimage', 'scipy.spatial', 'omegaconf', 'hydra', 'dask', 'numba')\n"
        "               if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == []


# `polyvec` as its console entry runs it (pipeline.launch), with the early child's pid written to
# early.pid and, as the process exits (before multiprocessing ends its children), whether it lives.
_EARLY_CHILD_RUN = """
import atexit, sys
from pipeline.engine.execute import early_child
early_child.start_early()
proc = early_child._EARLY[0][0]
open("early.pid", "w").write(str(proc.pid))
atexit.register(lambda: open("alive.txt", "w").write(str(proc.is_alive())))
sys.argv = ["polyvec", *sys.argv[1:]]
from pipeline.cli import main
main()
"""


def _gone(pid: int, timeout_s: float = 20.0) -> bool:
    """Whether process ``pid`` has ended (or is a zombie nobody reaped) within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            state = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0]
        except (FileNotFoundError, ProcessLookupError):
            return True
        if state in ("Z", "X"):
            return True
        time.sleep(0.1)
    return False


@pytest.mark.skipif(sys.platform != "linux", reason="the early child is forked on Linux only")
def test_polyvec_forks_its_keypoints_child_before_its_imports_and_the_run_adopts_it(tmp_path):
    """The keypoints child starts before ``polyvec`` imports its own code (its torch import then runs
    beside the CLI's imports and planning); the run computes its keypoints in that very process, and a
    run with none to compute (every artifact stored, a λ re-run) ends it: no process outlives a run."""
    (tmp_path / "vee.png").write_bytes(synthetic.vee(size=48, width=3).png_bytes())

    def run(*args):
        out = subprocess.run([sys.executable, "-c", _EARLY_CHILD_RUN, "vee.png", "runtime.cluster=sync", *args],
                             cwd=tmp_path, capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stderr[-2000:]
        return int((tmp_path / "early.pid").read_text()), (tmp_path / "alive.txt").read_text()

    early, alive = run()
    pids = {p.parent.parent.parent.name: json.loads(p.read_text())["pid"]
            for p in tmp_path.glob("artifacts/*/*/*/manifest.json")}
    assert pids["keypoints"] == early != pids["prep"]
    assert alive == "False" and _gone(early)
    for args in ((), ("flow.lam=0.5",)):   # every artifact stored; a λ re-run: no keypoints to compute
        early, alive = run(*args)
        assert alive == "False" and _gone(early)


@pytest.mark.skipif(sys.platform != "linux", reason="the early child is forked on Linux only")
def test_the_early_keypoints_child_leaves_when_polyvec_is_killed(tmp_path):
    """A forked child holds a copy of the driver's end of its pipe: it closes it, so that it sees the
    driver go (killed, or ended by Ctrl-C without its exit handlers) instead of waiting for ever."""
    import signal

    script = ("import time\nfrom pipeline.engine.execute import early_child\nearly_child.start_early()\n"
              "print(early_child._EARLY[0][0].pid, flush=True)\ntime.sleep(600)\n")
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=tmp_path)
    early = int(proc.stdout.readline())
    time.sleep(0.5)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    assert _gone(early, timeout_s=60)
