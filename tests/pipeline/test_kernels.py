"""The compiled kernels shipped with the package (pipeline/engine/kernels/, stages.portable_cpu_target; issue 14)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest

import stages
from pipeline.engine.kernels import shipped as kernels, warmup
from stages import synthetic

REPO = Path(__file__).resolve().parents[2]
MODULES = sorted(m for ms in kernels.KERNEL_MODULES.values() for m in ms)

# The real stages on another drawing than the warm-up's, in a fresh process: which numba kernels of
# graph and flow were loaded from the cache (hits) and which had to be compiled (misses).
_CHECK = r"""
import gc, json, sys
import stages  # first, as polyvec's commands do: it sets numba's CPU target before numba reads it
import numpy as np
from pipeline.engine.kernels import shipped as kernels
for stage in kernels.KERNEL_MODULES:   # as the engine's tasks do
    kernels.load_without_registries(stage)
from numba.core.dispatcher import Dispatcher
from pipeline.engine.config import default_config as cfg
from stages import graph, prep, synthetic
from stages.config import from_section
from stages.field import run as field_run
from stages.flow import FlowConfig, polyvector_flow

p = prep.run(cfg("prep"), image_bytes=synthetic.tee(size=64).png_bytes(), image_name="tee.png")
f = field_run(cfg("field"), prep=p)
g = graph.run(cfg("graph"), prep=p, field=f)
xy = np.asarray(g["vertex_xy"], np.float64)[:6]
params = from_section(FlowConfig, cfg("flow"), "flow")
polyvector_flow(np.asarray(f["c0"]), np.asarray(f["c2"]), [xy], [np.full(len(xy), 3.0)],
                [np.arange(len(xy), dtype=np.float64)], params)
import stages.topology.stage as topology
from pipeline.engine.registry import BY_NAME
# The tee needs no constrained walk; the example drawing does (the topology warm-up uses neither).
p = prep.run(cfg("prep"), image_bytes=synthetic.example_drawing().png_bytes(), image_name="example.png")
f = field_run(cfg("field"), prep=p)
g = graph.run(cfg("graph"), prep=p, field=f)
kp = BY_NAME["keypoints"].load().run(cfg("keypoints"), prep=p)
edits = BY_NAME["keypoint_edits"].load().run(cfg("keypoint_edits"), keypoints=kp)
topology.run(cfg("topology"), prep=p, keypoint_edits=edits, field=f, graph=g)
out = {}
for o in gc.get_objects():
    if isinstance(o, Dispatcher) and o.py_func.__module__.split(".")[1] in ("field", "graph", "topology", "flow"):
        s = o.stats
        out[o.py_func.__name__] = [sum(s.cache_hits.values()), sum(s.cache_misses.values())]
print(json.dumps(out))
print(json.dumps({"registries": "numba.np.polynomial.polynomial_core" in sys.modules}))
"""


def _shipped_fit() -> None:
    """Skip unless this machine can load the shipped kernels (an x86-64-v3 Linux CPU, a Python they were built
    by); where it can, this process must compile for their target."""
    manifest = json.loads((kernels.SHIPPED / kernels.MANIFEST).read_text())
    if not (sys.platform.startswith("linux") and os.uname().machine == "x86_64"
            and stages._PORTABLE_CPU_FLAGS <= stages._cpu_flags()) or kernels.python_tag() not in manifest["pythons"]:
        pytest.skip(f"the shipped kernels are for {manifest['target']} and {manifest['pythons']}, "
                    "which this machine cannot run")
    assert kernels.target() == manifest["target"]


def _ours(names: list) -> list:
    """The names of this Python's cache files among ``names``."""
    return sorted(n for n in names if f".{kernels.python_tag()}." in n)


def test_the_shipped_kernels_are_built_from_the_current_sources():
    """Every kernel module's shipped cache was compiled from its source as it is now, by the pinned numba.

    numba rejects a cache whose source file changed (any byte of it): after editing one of these
    modules, run ``python -m pipeline.engine.kernels.build`` and commit ``pipeline/engine/kernels/compiled``."""
    manifest = json.loads((kernels.SHIPPED / kernels.MANIFEST).read_text())
    assert sorted(manifest["modules"]) == MODULES
    for module in MODULES:
        src = kernels.module_file(module)
        assert manifest["modules"][module] == hashlib.sha256(src.read_bytes()).hexdigest(), \
            f"{module} changed since its kernels were compiled: run python -m pipeline.engine.kernels.build"
        names = manifest["files"][module]
        for tag in manifest["pythons"]:
            assert any(n.endswith(f".{tag}.nbi") for n in names) and any(f".{tag}." in n and n.endswith(".nbc")
                                                                          for n in names), (module, tag)
        assert all((kernels.SHIPPED / module / n).is_file() for n in names)
    assert manifest["target"]["numba"] == version("numba"), "pyproject.toml pins the numba that built them"
    assert "py311" in manifest["pythons"]  # CI's Python
    assert manifest["target"]["cpu_name"] == stages.PORTABLE_CPU and manifest["target"]["cpu_features"] == ""
    pin = [d for d in (REPO / "pyproject.toml").read_text().splitlines() if d.strip().startswith('"numba')]
    assert pin and f'"numba=={manifest["target"]["numba"]}"' in pin[0]


def _load_check(tmp_path: Path, shipped: Path) -> None:
    """Copy the kernels of ``shipped`` into an empty numba cache; the stages then load every kernel they call
    from it (hits) and compile none (misses)."""
    # A user's shell: no CPU target of numba's set (the pytest process set it; children inherit it).
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_CPU_")}
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "numba-cache")
    code = f"from pipeline.engine.kernels import shipped as kernels; print(kernels.install(list(kernels.KERNEL_MODULES), {str(shipped)!r}))"
    copied = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True,
                            check=True).stdout
    assert sorted(eval(copied)) == MODULES
    proc = subprocess.run([sys.executable, "-c", _CHECK], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr
    *_, counts, loaded = map(json.loads, proc.stdout.strip().splitlines())
    assert not loaded["registries"]   # every kernel loaded without numba's registries
    # The entry kernels of the field's solve, tracing, cross-sections, the constrained walk and the flow;
    # their helpers are compiled into them.
    for name in ("sparse_product", "step_solution", "next_direction", "_trace_all", "_build_sections", "_search",
                 "_flow_kernel"):
        assert counts[name][0] >= 1, (name, counts)
    assert not {k: v for k, v in counts.items() if v[1]}, counts


@pytest.mark.slow
def test_the_shipped_kernels_load_without_a_compile(tmp_path):
    _shipped_fit()
    _load_check(tmp_path, kernels.SHIPPED)


@pytest.mark.slow
def test_the_build_command_compiles_every_kernel_the_stages_then_load(tmp_path):
    """The ``python -m pipeline.engine.kernels.build`` of docs/ARCHITECTURE.md (into another folder, with ``--python``): the warm-ups
    compile exactly the kernels the stages load on other drawings, and the same files as the shipped ones."""
    _shipped_fit()
    # --python: another interpreter (here this one again: the same Python's files, built once)
    subprocess.run([sys.executable, "-m", "pipeline.engine.kernels.build", "--out", str(tmp_path / "built"), "--python",
                    sys.executable], cwd=REPO, check=True, capture_output=True, timeout=600)
    built = json.loads((tmp_path / "built" / kernels.MANIFEST).read_text())
    shipped = json.loads((kernels.SHIPPED / kernels.MANIFEST).read_text())
    assert built["target"] == shipped["target"] and built["modules"] == shipped["modules"]
    assert built["pythons"] == [kernels.python_tag()]
    assert {m: _ours(n) for m, n in built["files"].items()} == {m: _ours(n) for m, n in shipped["files"].items()}
    _load_check(tmp_path, tmp_path / "built")


def test_cache_dir_is_the_folder_numba_caches_in(tmp_path):
    """:func:`kernels.cache_dir` names numba's own folder, with and without ``NUMBA_CACHE_DIR``."""
    code = ("import json, sys\nfrom pathlib import Path\nfrom pipeline.engine.kernels import shipped as kernels\n"
            "import stages.graph.trace as t, stages.flow.kernel as k\n"
            "print(json.dumps([[d._cache._cache_path, str(kernels.cache_dir(kernels.module_file(m)))]"
            " for d, m in ((t._trace_all, 'stages.graph.trace'), (k._flow_kernel, 'stages.flow.kernel'))]))")
    for extra in ({"NUMBA_CACHE_DIR": str(tmp_path / "nc")}, {}):
        env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"} | extra
        out = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True,
                             check=True).stdout
        for numbas, ours in json.loads(out):
            assert Path(numbas) == Path(ours), extra


def _fake_shipped(tmp_path: Path, monkeypatch, pythons=None, **changes) -> dict:
    """A copy of the shipped kernels for this machine, with ``changes`` to the manifest's target (and its
    ``pythons``), used by :func:`kernels.install`."""
    shipped = tmp_path / "shipped"
    shutil.copytree(kernels.SHIPPED, shipped)
    manifest = json.loads((shipped / "manifest.json").read_text())
    manifest["target"] = kernels.target()
    manifest["target"].update(changes)
    manifest["pythons"] = pythons or [kernels.python_tag()]
    (shipped / "manifest.json").write_text(json.dumps(manifest))
    monkeypatch.setattr(kernels, "SHIPPED", shipped)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "numba-cache"))
    return manifest


def test_install_copies_a_stages_kernels_only_where_numba_has_none_and_they_fit(tmp_path, monkeypatch):
    manifest = _fake_shipped(tmp_path, monkeypatch)
    assert warmup.uncompiled(["prep", "graph", "flow"]) == ["graph", "flow"]
    assert kernels.install(["prep", "graph"]) == ["stages.graph.trace", "stages.graph.cross_section"]
    assert warmup.uncompiled(["graph", "flow"]) == ["flow"]
    for module in ("stages.graph.trace", "stages.graph.cross_section"):
        where = kernels.cache_dir(kernels.module_file(module))
        assert sorted(p.name for p in where.iterdir() if p.stem.startswith(module.rsplit(".", 1)[1] + ".")) \
            == _ours(manifest["files"][module])
        for name in _ours(manifest["files"][module]):
            assert (where / name).read_bytes() == (kernels.SHIPPED / module / name).read_bytes()
    # A cache numba already has is left alone (it may hold more than the shipped one).
    index = next(kernels.cache_dir(kernels.module_file("stages.graph.trace")).glob("trace.*.nbi"))
    index.write_bytes(_index("stages.graph.trace", current=True))
    assert kernels.install(["graph", "flow"]) == ["stages.flow.kernel"]
    assert index.read_bytes() == _index("stages.graph.trace", current=True)


def _index(module: str, current: bool, numba: str | None = None, cpu: str | None = None) -> bytes:
    """A numba index as numba writes it: its version, then the digest of the source it compiled and its
    overloads, keyed by signature, target (CPU name: this process's by default) and bytecode hashes."""
    import pickle

    src = kernels.module_file(module).read_bytes()
    digest = hashlib.sha256(src if current else src + b"# an older line").digest()
    key = ("sig", ("x86_64-unknown-linux-gnu", cpu or os.environ.get("NUMBA_CPU_NAME", "znver3"), ""), ("h", "h"))
    return pickle.dumps(numba or version("numba"), protocol=-1) + pickle.dumps((digest, {key: "x.1.nbc"}), protocol=-1)


def test_an_index_from_before_the_source_changed_is_no_cache(tmp_path, monkeypatch):
    """After a ``git pull`` or an upgrade in place, numba's index of a changed module is stale: numba would
    compile again (on the critical path, unannounced). It is not taken for a cache: the shipped kernels,
    built from the new source, replace it (or, where none fit, the warm-up starts and the run says so)."""
    _fake_shipped(tmp_path, monkeypatch)
    where = kernels.cache_dir(kernels.module_file("stages.flow.kernel"))
    where.mkdir(parents=True)
    stale = where / "kernel._flow_kernel-273.py311.nbi".replace("py311", kernels.python_tag())
    stale.write_bytes(_index("stages.flow.kernel", current=False))
    assert not kernels.is_cached("stages.flow.kernel") and warmup.uncompiled(["flow"]) == ["flow"]
    assert kernels.install(["flow"]) == ["stages.flow.kernel"]
    assert kernels.is_cached("stages.flow.kernel") and stale.read_bytes() != _index("stages.flow.kernel", False)
    # A current index for another CPU target (numba's own, from before the portable target): no cache here.
    if os.environ.get("NUMBA_CPU_NAME"):
        stale.write_bytes(_index("stages.flow.kernel", current=True, cpu="znver3"))
        assert not kernels.is_cached("stages.flow.kernel")
    # Another numba's index (a format this does not read) counts as a cache, as numba's own business.
    other = kernels.cache_dir(kernels.module_file("stages.topology.constrained_path"))
    other.mkdir(parents=True, exist_ok=True)
    (other / f"constrained_path._search-1.{kernels.python_tag()}.nbi").write_bytes(
        _index("stages.topology.constrained_path", current=False, numba="0.1.0"))
    assert kernels.is_cached("stages.topology.constrained_path")
    # An index numba cannot read is no cache either, and a pickle that would run code is only read.
    marker = tmp_path / "ran"
    for junk in (b"not a pickle", b"", f"cbuiltins\nopen\n(S'{marker}'\nS'w'\ntR.".encode()):
        (other / f"constrained_path._search-1.{kernels.python_tag()}.nbi").write_bytes(junk)
        assert not kernels.is_cached("stages.topology.constrained_path")
    assert not marker.exists()


def test_the_index_of_a_kernel_an_edit_moved_is_removed_not_taken_for_an_uncompiled_module(tmp_path, monkeypatch):
    """numba names an index after its kernel's line: once an edit moves the kernel, numba never opens the
    old index again. Left in the folder, it made the module look uncompiled at every run (the compile
    message and the warm-ups each time); it is removed with its data, another Python's is not."""
    _fake_shipped(tmp_path, monkeypatch)
    module, tag = "stages.flow.kernel", kernels.python_tag()
    assert kernels.install(["flow"]) == [module] and kernels.is_cached(module)
    where = kernels.cache_dir(kernels.module_file(module))
    orphan, data = where / f"kernel._flow_kernel-250.{tag}.nbi", where / f"kernel._flow_kernel-250.{tag}.1.nbc"
    orphan.write_bytes(_index(module, current=False))
    data.write_bytes(b"machine code")
    other = where / "kernel._flow_kernel-250.py399.nbi"
    other.write_bytes(_index(module, current=False))
    assert not kernels.is_cached(module) and warmup.uncompiled(["flow"]) == ["flow"]
    assert kernels.forget_stale(["prep", "flow"]) == [orphan.name]
    assert not orphan.exists() and not data.exists() and other.exists()
    assert kernels.is_cached(module) and warmup.uncompiled(["flow"]) == []
    assert kernels.forget_stale(["flow"]) == []
    # The current kernels' own files are untouched.
    assert sorted(p.name for p in where.glob(f"kernel.*.{tag}*")) == sorted(
        n for n in json.loads((kernels.SHIPPED / "manifest.json").read_text())["files"][module] if f".{tag}." in n)


@pytest.mark.parametrize("change, why", [
    ({"numba": "0.1.0"}, "the shipped ones are numba 0.1.0's, this is numba "),
    ({"pythons": ["py399"]}, "none are shipped for Python 3."),
    ({"cpu_name": "znver3"}, "NUMBA_CPU_NAME / NUMBA_CPU_FEATURES are set"),
    ({"cpu_features": None}, "NUMBA_CPU_NAME / NUMBA_CPU_FEATURES are set"),
    ({"platform": "darwin-arm64"}, "the shipped ones are for darwin-arm64, not "),
    ("source", "stages.flow.kernel changed since they were built (python -m pipeline.engine.kernels.build)")])
def test_install_copies_nothing_built_for_another_machine_or_source(tmp_path, monkeypatch, change, why):
    """And the first run's compile message says why (:func:`kernels.why_compiled`)."""
    manifest = _fake_shipped(tmp_path, monkeypatch, **(change if isinstance(change, dict) else {}))
    if change == "source":  # a kernel module edited since the build
        manifest["modules"]["stages.flow.kernel"] = "0" * 64
        (kernels.SHIPPED / kernels.MANIFEST).write_text(json.dumps(manifest))
        assert kernels.why_compiled(["flow", "topology"]).startswith(why)
        assert kernels.install(["flow", "topology"]) == ["stages.topology.constrained_path"]
        assert warmup.uncompiled(["flow"]) == ["flow"]
    else:
        assert kernels.why_compiled(list(warmup.WARMED)).startswith(why)
        assert kernels.install(list(warmup.WARMED)) == []
        assert not (tmp_path / "numba-cache").exists() or not any((tmp_path / "numba-cache").rglob("*.nb?"))
    assert kernels.why_compiled(["prep", "select"]) == ""


def test_the_compile_message_names_a_cpu_without_the_level_and_a_missing_manifest(tmp_path, monkeypatch):
    manifest = _fake_shipped(tmp_path, monkeypatch)
    monkeypatch.setattr(kernels, "target", lambda environ=None: dict(manifest["target"], cpu_name=None,
                                                                    cpu_features=None))
    assert kernels.why_compiled(["graph"]) == "the shipped ones need an x86-64-v3 CPU (AVX2, FMA), which this one is not"
    (kernels.SHIPPED / kernels.MANIFEST).unlink()
    assert kernels.why_compiled(["graph"]) == "none are shipped with this install"


def test_the_portable_cpu_target_is_set_only_on_a_cpu_that_has_it(monkeypatch):
    monkeypatch.setattr(stages, "_cpu_flags", lambda: stages._PORTABLE_CPU_FLAGS | {"avx512f"})
    env = {}
    assert stages.portable_cpu_target(env) == (sys.platform.startswith("linux") and os.uname().machine == "x86_64")
    if env:
        assert env == {"NUMBA_CPU_NAME": "x86-64-v3", "NUMBA_CPU_FEATURES": ""}
    monkeypatch.setattr(stages, "_cpu_flags", lambda: stages._PORTABLE_CPU_FLAGS - {"avx2"})
    env = {}
    assert not stages.portable_cpu_target(env) and env == {}
    # A user's own choice is kept.
    env = {"NUMBA_CPU_NAME": "generic"}
    assert not stages.portable_cpu_target(env) and env == {"NUMBA_CPU_NAME": "generic"}


def test_the_first_run_of_a_fresh_install_compiles_nothing(tmp_path):
    """An empty numba cache (a fresh install): the run copies the shipped kernels, says nothing of a compile,
    and numba's cache then holds exactly the shipped files (nothing compiled beside them)."""
    _shipped_fit()
    (tmp_path / "vee.png").write_bytes(synthetic.vee(size=48).png_bytes())
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"))
    run = subprocess.run([sys.executable, "-m", "pipeline.launch", "vee.png", "runtime.cluster=sync",
                          f"store.path={tmp_path / 'store'}"], cwd=tmp_path, capture_output=True, text=True,
                         env=env, timeout=600)
    assert run.returncode == 0, run.stderr
    assert "compiling kernels" not in run.stderr and (tmp_path / "out" / "vee.svg").is_file()
    shipped = json.loads((kernels.SHIPPED / kernels.MANIFEST).read_text())["files"]
    cached = sorted(p.name for p in (tmp_path / "numba-cache").rglob("*.nb?"))
    assert cached == _ours([n for names in shipped.values() for n in names])


def test_install_passes_over_a_cache_folder_it_cannot_write(tmp_path, monkeypatch):
    """numba cannot cache there either (it then compiles in memory): no copy, no error."""
    _fake_shipped(tmp_path, monkeypatch)
    (tmp_path / "a file").write_text("")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "a file"))
    assert kernels.install(list(warmup.WARMED)) == []
    assert kernels.why_compiled(["graph"]) == "the shipped ones could not be copied into numba's cache folder"


def test_another_pythons_cache_in_the_same_folder_is_not_this_ones(tmp_path, monkeypatch):
    """numba names its files by Python version and Pythons share a cache folder: a py399 index is not ours."""
    _fake_shipped(tmp_path, monkeypatch)
    where = kernels.cache_dir(kernels.module_file("stages.flow.kernel"))
    where.mkdir(parents=True)
    (where / "kernel._flow_kernel-273.py399.nbi").write_bytes(_index("stages.flow.kernel", current=True))
    assert not kernels.is_cached("stages.flow.kernel")
    assert kernels.install(["flow"]) == ["stages.flow.kernel"] and kernels.is_cached("stages.flow.kernel")


def test_the_build_refuses_an_interpreter_without_the_same_numba(tmp_path):
    """``--python`` with a Python that lacks numba: one line, nothing built, the shipped kernels untouched."""
    proc = subprocess.run([sys.executable, "-m", "pipeline.engine.kernels.build", "--out", str(tmp_path / "built"), "--python",
                           sys.executable + "-nonexistent"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and "does not run, or has no numba" in proc.stderr
    assert not (tmp_path / "built").exists()


_TINY = """
import numpy as np
import numba


@numba.njit(cache=True)
def ramp(n):
    out = np.empty(n)       # NRT's allocator: what a loaded kernel needs of numba's runtime
    for i in range(n):
        out[i] = 0.5 * i
    return out
"""
_TINY_RUN = r"""
import json, sys
import stages
from pipeline.engine.kernels import shipped as kernels
kernels.KERNEL_MODULES["tiny"] = ("tiny_kernels",)
if sys.argv[1] == "quick":
    kernels.load_without_registries("tiny")
import tiny_kernels
r = tiny_kernels.ramp(5)
s = tiny_kernels.ramp.stats
print(json.dumps({"ramp": r.tolist(), "hits": sum(s.cache_hits.values()), "misses": sum(s.cache_misses.values()),
                  "registries": "numba.np.polynomial.polynomial_core" in sys.modules}))
"""


def test_a_cached_kernel_loads_without_numbas_registries_and_an_uncached_one_compiles(tmp_path):
    """``kernels.load_without_registries``: numba loads a cached kernel without importing the
    implementations it compiles with (~0.35 s of a λ re-run); a kernel not in the cache still compiles,
    and the loaded one gives the same result."""
    (tmp_path / "tiny_kernels.py").write_text(_TINY)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"), PYTHONPATH=f"{tmp_path}{os.pathsep}{REPO}")

    def run(mode):
        proc = subprocess.run([sys.executable, "-c", _TINY_RUN, mode], cwd=REPO, env=env, capture_output=True,
                              text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        return json.loads(proc.stdout.strip().splitlines()[-1])

    compiled = run("quick")               # an empty cache: compiled (numba refreshes its target to compile)
    assert compiled["misses"] == 1 and compiled["registries"]
    loaded = run("quick")
    assert loaded["hits"] == 1 and not loaded["misses"] and not loaded["registries"]
    assert loaded["ramp"] == compiled["ramp"] == [0.0, 0.5, 1.0, 1.5, 2.0]
    plain = run("plain")                  # numba's own way: the registries come with the load
    assert plain["hits"] == 1 and plain["registries"]


def test_quick_loads_only_with_the_numba_they_were_checked_on(monkeypatch):
    """Another numba than the shipped kernels' loads its kernels its own way (the private method may differ)."""
    import numba
    from numba.core.caching import Cache

    from stages.flow import kernel

    cache = kernel._flow_kernel._cache
    assert isinstance(cache, Cache)
    if "load_overload" in vars(cache):    # set by a run earlier in this process
        monkeypatch.delattr(cache, "load_overload")
    monkeypatch.setattr(kernels, "_QUICK_LOADS", set())
    monkeypatch.setattr(numba, "__version__", "0.0.0")
    kernels.load_without_registries("flow")
    assert "load_overload" not in vars(cache)
    monkeypatch.setattr(numba, "__version__", kernels._shipped_numba())
    monkeypatch.setattr(kernels, "_QUICK_LOADS", set())
    kernels.load_without_registries("flow")
    assert "load_overload" in vars(cache)
