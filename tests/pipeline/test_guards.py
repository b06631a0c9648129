"""Every stage has a guard against super-linear blow-up that degrades and says so (issue 18 item 4).

A bound forced tiny must make its stage do less — never hang, crash or fail the image — and leave one
warning line on the console and in the artifact's manifest (``warnings``).
"""

from __future__ import annotations

import json

import pytest

from stages import synthetic

# stage -> (override forcing its guard, words of its warning)
TINY = {
    "keypoints": ("keypoints.max_keypoints=1", "keypoints.max_keypoints (1)"),
    "field": ("field.cg_max_iterations=1", "field.cg_max_iterations (1)"),
    "graph": ("graph.cleanup.max_loop_searches=0", "graph.cleanup.max_loop_searches (0)"),
    "topology": ("topology.max_enumeration_steps=1", "topology.max_enumeration_steps (1)"),
    "flow": ("flow.max_vertices=10", "flow.max_vertices (10)"),
    "export": ("export.max_curves=1", "export.max_curves (1)"),
}


@pytest.mark.slow
def test_tiny_guards_degrade_and_say_so(tmp_path, cli):
    (tmp_path / "drawing.png").write_bytes(synthetic.example_drawing().png_bytes())
    proc = cli("drawing.png", "runtime.cluster=sync", *(o for o, _ in TINY.values()), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    assert (tmp_path / "out" / "drawing.svg").is_file()
    warnings = [ln for ln in proc.stderr.splitlines() if ln.startswith("warning")]
    for stage, (_, words) in TINY.items():
        said = [ln for ln in warnings if f": {stage}: " in ln]
        assert len(said) == 1 and words in said[0], (stage, warnings)
        manifests = [json.loads(p.read_text()) for p in (tmp_path / "artifacts" / stage).glob("*/*/manifest.json")]
        assert [m.get("warnings") for m in manifests] and words in manifests[0]["warnings"][0]
    assert len(warnings) == len(TINY)        # prep, keypoint_edits and select: nothing bound


def test_default_bounds_leave_a_plain_drawing_alone(tmp_path, compose_cfg):
    """The bounds are guards, not settings: on an ordinary drawing no stage says anything."""
    from pipeline.engine.execute.batch import run_batch

    img = tmp_path / "vee.png"
    img.write_bytes(synthetic.vee(size=48).png_bytes())
    batch = run_batch([img], compose_cfg(f"store.path={tmp_path / 'store'}", "runtime.cluster=sync"))
    per = batch.results[str(img)]
    assert per["export"].status == "computed"
    assert all(r.warnings == () for r in per.values())
