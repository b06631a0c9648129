"""The background kernel warm-up of a first in-process run (pipeline/engine/kernels/warmup.py, issue 14)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from pipeline.engine.kernels import warmup
from pipeline.engine.execute.batch import run_batch
from stages import synthetic

REPO = Path(__file__).resolve().parents[2]


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
    code = ("import pipeline.engine.kernels.warmup, stages.graph.trace, stages.flow.kernel\n"
            "from numba.core import errors\n"
            "print(type(errors.termcolor()).__name__)")
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_DISABLE")}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[2])
    assert out.stdout.strip() == "NOPColorScheme"
