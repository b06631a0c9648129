"""Hydra sweeps over the flow knobs recompute flow → select → export only."""

from __future__ import annotations

import pytest

from pipeline.engine.registry import BY_NAME
from stages import synthetic

DOWNSTREAM = ("flow", "select", "export")


@pytest.mark.slow
def test_lambda_and_dt_sweep_recomputes_only_downstream(tmp_path, cli):
    img = tmp_path / "vee.png"
    img.write_bytes(synthetic.vee(size=56, width=3).png_bytes())
    common = (f"input={img}", "runtime.cluster=sync", "flow.iterations=60")
    first = cli(*common, cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    sweep = cli("-m", *common, "flow.lam=0.05,0.2,1.0", "flow.dt=0.005,0.01", cwd=tmp_path)
    assert sweep.returncode == 0, sweep.stderr
    jobs = 6
    rows = {}
    for line in sweep.stderr.splitlines():
        cells = [c.strip() for c in line.split("│")[1:-1]]
        if len(cells) == 6 and cells[0] in BY_NAME:
            rows.setdefault(cells[0], []).append((int(cells[1]), int(cells[2])))  # computed, cached
    for stage, per_job in rows.items():
        assert len(per_job) == jobs, (stage, per_job)
        computed = sum(c for c, _ in per_job)
        cached = sum(h for _, h in per_job)
        if stage in DOWNSTREAM:
            # one job (flow.lam/dt equal to the first run's defaults) may be a hit
            assert computed >= jobs - 1 and computed + cached == jobs, (stage, per_job)
        else:
            assert computed == 0 and cached == jobs, (stage, per_job)
    assert set(rows) == set(BY_NAME)
    # one artifact per upstream stage; one per distinct (lam, dt) downstream
    for stage in BY_NAME:
        n = len(list((tmp_path / "artifacts" / stage).glob("*/*")))
        assert n == (1 if stage not in DOWNSTREAM else n) and n >= 1
    assert len(list((tmp_path / "artifacts" / "flow").glob("*/*"))) >= jobs
    # each job's SVG lands in a folder named after its overrides
    svgs = sorted(p.parent.name for p in (tmp_path / "out").glob("*/vee.svg"))
    assert len(svgs) == jobs
    assert "flow.dt=0.005,flow.iterations=60,flow.lam=0.05" in svgs


@pytest.mark.slow
def test_an_extension_sweep_leaves_the_field_graph_and_topology_alone(tmp_path, cli):
    """The field's extension is its own stage: sweeping its wall (``extension.scale``) recomputes
    extension → flow → select → export, never the field solve, the graph or the topology."""
    img = tmp_path / "vee.png"
    img.write_bytes(synthetic.vee(size=56, width=3).png_bytes())
    common = (f"input={img}", "runtime.cluster=sync", "flow.iterations=30")
    assert cli(*common, cwd=tmp_path).returncode == 0
    sweep = cli("-m", *common, "extension.scale=1.0,4.0", cwd=tmp_path)
    assert sweep.returncode == 0, sweep.stderr
    computed = {}
    for line in sweep.stderr.splitlines():
        cells = [c.strip() for c in line.split("│")[1:-1]]
        if len(cells) == 6 and cells[0] in BY_NAME:
            computed[cells[0]] = computed.get(cells[0], 0) + int(cells[1])
    assert all(computed[s] == 2 for s in ("extension", "flow", "select", "export")), computed
    assert all(computed[s] == 0 for s in ("prep", "keypoints", "field", "graph", "topology")), computed
