"""The background kernel warm-up of a first in-process run (pipeline/warmup.py, issue 14)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline import warmup
from pipeline.runner import run_batch
from stages import synthetic

REPO = Path(__file__).resolve().parents[2]

# The real stages on another drawing than the warm-up's, in a fresh process: which numba kernels of
# graph and flow were loaded from the cache (hits) and which had to be compiled (misses).
_CHECK = r"""
import gc, json, sys
import numpy as np
from numba.core.dispatcher import Dispatcher
from pipeline.registry import default_config as cfg
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
from pipeline.registry import BY_NAME
# The tee needs no constrained walk; the example drawing does (the topology warm-up uses neither).
p = prep.run(cfg("prep"), image_bytes=synthetic.example_drawing().png_bytes(), image_name="example.png")
f = field_run(cfg("field"), prep=p)
g = graph.run(cfg("graph"), prep=p, field=f)
kp = BY_NAME["keypoints"].load().run(cfg("keypoints"), prep=p)
edits = BY_NAME["keypoint_edits"].load().run(cfg("keypoint_edits"), keypoints=kp)
topology.run(cfg("topology"), prep=p, keypoint_edits=edits, field=f, graph=g)
out = {}
for o in gc.get_objects():
    if isinstance(o, Dispatcher) and o.py_func.__module__.split(".")[1] in ("graph", "topology", "flow"):
        s = o.stats
        out[o.py_func.__name__] = [sum(s.cache_hits.values()), sum(s.cache_misses.values())]
print(json.dumps(out))
"""


@pytest.mark.slow
def test_a_warm_up_compiles_exactly_the_kernels_the_stages_then_load(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"))
    for stage in warmup.WARMED:
        subprocess.run([sys.executable, "-m", "pipeline.warmup", stage], cwd=REPO, env=env, check=True, timeout=600)
    proc = subprocess.run([sys.executable, "-c", _CHECK], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr
    kernels = json.loads(proc.stdout.strip().splitlines()[-1])
    # The entry kernels of tracing, cross-sections and the flow; their helpers are compiled into them.
    for name in ("_trace_all", "_build_sections", "_search", "_flow_kernel"):
        assert kernels[name][0] >= 1, (name, kernels)
    assert not {k: v for k, v in kernels.items() if v[1]}, kernels


def test_an_in_process_first_run_waits_for_each_warm_up_before_its_stage(tmp_path, compose_cfg, monkeypatch):
    events = []
    monkeypatch.setattr(warmup, "start", lambda stages: events.append(("start", tuple(stages))) or [])
    monkeypatch.setattr(warmup, "wait", lambda stage, limit_s=0: events.append(("wait", stage)))
    monkeypatch.setattr(warmup, "stop", lambda: events.append(("stop",)))
    image = tmp_path / "vee.png"
    image.write_bytes(synthetic.vee(size=48, width=3).png_bytes())
    cfg = compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.cluster=auto", "runtime.until=graph")
    run_batch([image], cfg)
    assert events[0] == ("start", ("field", "graph", "prep"))
    assert [e[1] for e in events if e[0] == "wait"] == ["prep", "field", "graph"]
    assert events[-1] == ("stop",)
    events.clear()
    run_batch([image], cfg)  # all cached: nothing to warm, nothing to wait for
    assert events == []


def test_start_skips_compiled_kernels_and_stop_ends_what_runs(tmp_path, monkeypatch):
    monkeypatch.setattr(warmup, "uncompiled", lambda stages: [])
    assert warmup.start(["graph", "flow"]) == []
    monkeypatch.setattr(warmup, "uncompiled", lambda stages: list(stages))
    monkeypatch.setattr(warmup.subprocess, "Popen", _SleepPopen)
    assert warmup.start(["prep", "graph", "topology", "flow"]) == ["graph", "topology", "flow"]
    # Two processes: the graph's, and topology's then the flow's.
    assert warmup._RUNNING["topology"] is warmup._RUNNING["flow"] is not warmup._RUNNING["graph"]
    assert warmup._RUNNING["flow"].args[-2:] == ["sleep", "60"] and _SleepPopen.calls[-1][-2:] == ["topology", "flow"]
    procs = list(warmup._RUNNING.values())
    warmup.stop()
    assert warmup._RUNNING == {} and all(p.poll() is not None for p in procs)


class _SleepPopen(subprocess.Popen):
    """A stand-in warm-up process that only sleeps."""

    calls: list = []

    def __init__(self, args, **kwargs):
        _SleepPopen.calls.append(list(args))
        super().__init__(["sleep", "60"], **kwargs)


def test_kernels_compile_without_colouring_numbas_rejected_overload_messages():
    """numba formats a message for each overload it rejects while typing; colouring them (colorama)
    cost ~8 % of a first run's compiles. A process that runs stages or warm-ups must have it off, also
    when the user's environment has none of numba's variables."""
    code = ("import pipeline.warmup, stages.graph.trace, stages.flow.kernel\n"
            "from numba.core import errors\n"
            "print(type(errors.termcolor()).__name__)")
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_DISABLE")}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[2])
    assert out.stdout.strip() == "NOPColorScheme"
