"""polyvec-bench: case discovery, scoring from stored artifacts, and the command line."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import yaml

from pipeline.bench import Case, discover_cases, final_curves, load_case, score_case
from pipeline.engine.config import CONF_DIR as REPO_CONF
from pipeline.engine.execute.base import BatchResult, TaskResult
from pipeline.engine.store import ArtifactStore
from stages import synthetic
from stages.artifact import Artifact, pack_ragged

BCFG = yaml.safe_load((REPO_CONF / "bench" / "default.yaml").read_text())


def _write_case(folder, name, drawing, style="clean"):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{name}.png").write_bytes(drawing.png_bytes())
    kp = {1: "endpoints", 3: "junctions", 5: "corners"}
    payload = {"size": drawing.grey.shape[0], "width": drawing.width, "style": style,
               "strokes": [s.tolist() for s in drawing.strokes],
               **{v: [[x, y] for x, y, t in drawing.keypoints if t == k] for k, v in kp.items()}}
    (folder / f"{name}.json").write_text(json.dumps(payload))
    return folder / f"{name}.png"


def test_discover_cases(tmp_path):
    _write_case(tmp_path / "set", "tee", synthetic.tee())
    (tmp_path / "set" / "rough").mkdir()
    (tmp_path / "set" / "rough" / "line.png").write_bytes(synthetic.line().png_bytes())
    (tmp_path / "set" / "index.json").write_text("[]")  # not a case: no image beside it
    cases = discover_cases([str(tmp_path / "set")])
    by = {c.name: c for c in cases}
    assert set(by) == {"tee", "rough/line"}
    assert by["tee"].strokes is not None and by["tee"].width == 3.0 and by["tee"].group == "set:clean"
    assert by["rough/line"].strokes is None and by["rough/line"].style == "rough"
    assert len(discover_cases([str(tmp_path / "set")], limit=1)) == 1


def _fake_batch(tmp_path, image, artifacts: dict[str, Artifact]):
    """Store artifacts under made-up keys and a BatchResult pointing at them."""
    store = ArtifactStore(tmp_path / "store")
    batch = BatchResult(stages=list(artifacts))
    per = batch.results.setdefault(str(image), {})
    for i, (stage, art) in enumerate(artifacts.items()):
        key = f"{stage}{i:02d}" + "0" * 24
        store.save(stage, key, art, {"stage": stage, "duration_s": 0.25 * (i + 1), "peak_rss_mb": 100.0 + i})
        per[stage] = TaskResult(str(image), stage, key, "cached")
    return store, batch


def _export(curves):
    return Artifact(data={"svg": "<svg/>", "curves": [{"id": k, "points": np.asarray(c).tolist(), "end_types": [0, 0],
                                                      "width": None} for k, c in enumerate(curves)]})


def test_score_case_perfect_output_scores_perfectly(tmp_path):
    d = synthetic.example_drawing()
    image = _write_case(tmp_path / "cases", "house", d)
    case = load_case(image, tmp_path / "cases", "cases")
    store, batch = _fake_batch(tmp_path, image, {"prep": Artifact(), "export": _export(d.strokes)})
    row, pic = score_case(case, batch, store, BCFG)
    assert row["error"] == "" and row["curves_from"] == "export"
    assert row["chamfer"] == 0.0 and row["hausdorff"] == 0.0
    assert all(row[f"f1_{k}"] == 1.0 for k in (2, 4, 6, 8, 10))
    assert row["endpoint_f1"] == 1.0 and row["junction_f1"] == 1.0
    assert row["junctions"] == row["gt_junctions"] >= 4  # T, X, Y and the sun's rays do not touch it
    assert row["time_s"] == pytest.approx(0.25 + 0.5) and row["peak_rss_mb"] == 101.0
    assert row["fid_f1_10"] > 0.95  # the 3-px input strokes lie within 10/1000 x 300 px of the curves
    assert len(pic["curves"]) == len(d.strokes) and pic["gt"] is not None


def test_score_case_keypoints(tmp_path):
    d = synthetic.tee(size=96, width=3.0)
    image = _write_case(tmp_path / "cases", "tee", d)
    case = load_case(image, tmp_path / "cases", "cases")
    kp = np.array([[x, y] for x, y, _ in d.keypoints], dtype=np.float32)
    types = np.array([t for *_, t in d.keypoints], dtype=np.int8)
    # every GT point found within 1 px, plus one stray endpoint and one junction labelled as a corner
    pred = np.vstack([kp + 0.5, [[5.0, 90.0]]])  # 0.71 px off: inside the authors’ 0.96 px radius
    pred_types = np.r_[np.where(types == 3, 5, types), 1].astype(np.int8)
    store, batch = _fake_batch(tmp_path, image, {"prep": Artifact(), "keypoints": Artifact(
        arrays={"points": pred, "types": pred_types, "scores": np.ones(len(pred), np.float32)})})
    row, pic = score_case(case, batch, store, BCFG)
    n = len(kp)
    assert row["kp_count"] == n + 1
    assert row["kp_recall_1to1"] == 1.0 and row["kp_precision_1to1"] == pytest.approx(n / (n + 1))
    assert row["kp_class_acc"] == pytest.approx((n - 1) / n)
    assert row["kp_f1_junc"] == 0.0  # the junction came out as a corner
    assert row["kp_f1_corner"] == 0.5  # the authors' value for a class without GT points
    assert row["kp_f1"] == pytest.approx(2 * n / (2 * n + 1))
    assert pic["keypoints"] is not None
    # one-to-one class F1: the junction is missed as a junction, and a corner appears that the GT has not
    assert row["kp_f1_1to1_junc"] == 0.0 and row["kp_f1_1to1_corner"] == 0.0
    assert (row["kp_junc_tp"], row["kp_junc_fn"], row["kp_corner_fp"]) == (0, 1, 1)


def test_pooled_keypoint_table_pools_points_not_drawings():
    from pipeline.bench import pooled_keypoints

    def row(group, end, junc, corner, correct):
        r = {"group": group, "kp_tp": end[0] + junc[0] + corner[0], "kp_fp": end[1] + junc[1] + corner[1],
             "kp_fn": end[2] + junc[2] + corner[2], "kp_correct_type": correct}
        for name, c in (("end", end), ("junc", junc), ("corner", corner)):
            r[f"kp_{name}_tp"], r[f"kp_{name}_fp"], r[f"kp_{name}_fn"] = c
        return r

    rows = [row("clean", (9, 1, 0), (1, 0, 1), (0, 0, 0), 10),
            row("pencil", (1, 0, 0), (0, 0, 9), (2, 2, 0), 3)]
    table = {e["group"]: e for e in pooled_keypoints(rows)}
    assert set(table) == {"all", "clean", "pencil"} and table["all"]["cases"] == 2
    # junctions pooled: tp 1, fp 0, fn 10 -> 2/12; the mean of the per-drawing F1 would be (2/3 + 0)/2
    assert table["all"]["kp_f1_1to1_junc"]["median"] == pytest.approx(2 / 12)
    assert table["clean"]["kp_f1_1to1_corner"]["median"] == 0.0
    assert table["all"]["kp_class_acc"]["median"] == pytest.approx(13 / 13)


def test_score_case_broken_output(tmp_path):
    d = synthetic.tee(size=96, width=3.0)
    image = _write_case(tmp_path / "cases", "tee", d)
    case = load_case(image, tmp_path / "cases", "cases")
    # the bar alone, broken in two with a 4-px gap: the junction is lost, two false free ends appear
    bar = d.strokes[0]
    mid = 0.5 * (bar[0] + bar[-1])
    step = (bar[-1] - bar[0]) / np.linalg.norm(bar[-1] - bar[0])
    out = [np.array([bar[0], mid - 2 * step]), np.array([mid + 2 * step, bar[-1]])]
    store, batch = _fake_batch(tmp_path, image, {"prep": Artifact(), "export": _export(out)})
    row, _ = score_case(case, batch, store, BCFG)
    assert row["junction_f1"] == 0.0 and row["gt_junctions"] == 1
    assert row["endpoint_precision"] == 0.5 and row["endpoint_recall"] == pytest.approx(2 / 3)
    assert row["junction_gaps"] == 2  # the two ends of the break almost meet
    assert row["f1_2"] < 1.0 and row["hausdorff"] > 0


def test_score_case_missing_curves_and_failed_stage(tmp_path):
    d = synthetic.line()
    image = _write_case(tmp_path / "cases", "line", d)
    case = load_case(image, tmp_path / "cases", "cases")
    store, batch = _fake_batch(tmp_path, image, {"prep": Artifact()})
    batch.stages.append("export")
    batch.results[str(image)]["export"] = TaskResult(str(image), "export", "x" * 32, "failed", error="boom")
    row, _ = score_case(case, batch, store, BCFG)
    assert row["error"] == "export: boom" and row["curves_from"] == "none" and "chamfer" not in row


def test_curves_from_select_and_flow(tmp_path):
    curves = [np.array([[0.0, 0], [1, 1]]), np.array([[5.0, 5], [6, 6]]), np.array([[9.0, 9], [8, 8]])]
    flat, off = pack_ragged(curves)
    store, batch = _fake_batch(tmp_path, tmp_path / "x.png", {
        "topology": Artifact(data={"paths": [{"id": 10}, {"id": 11}, {"id": 12}]}),
        "flow": Artifact(arrays={"curve_xy": flat, "curve_xy_offsets": off}),
        "select": Artifact(data={"chosen": [12, 10]})})
    got, source = final_curves(store, batch.keys(str(tmp_path / "x.png")))
    assert source == "select+flow"
    assert [c.tolist() for c in got] == [curves[2].tolist(), curves[0].tolist()]


@pytest.mark.slow
def test_bench_cli(tmp_path, cli):
    cases = tmp_path / "cases"
    _write_case(cases, "tee", synthetic.tee(size=48, width=3.0))
    (cases / "plain").mkdir()
    (cases / "plain" / "line.png").write_bytes(synthetic.line(size=48).png_bytes())
    res = cli(f"bench.cases=[{cases}]", f"bench.out={tmp_path / 'report'}", "runtime.cluster=sync",
              "runtime.progress=false", cwd=tmp_path, module="pipeline.bench")
    assert res.returncode in (0, 1), res.stderr  # 1: some case failed (scored as a failure)
    assert "Traceback" not in res.stderr
    assert "polyvec-bench" in res.stderr and "fidelity, topology, cost" in res.stderr
    assert not list(tmp_path.glob("*.log")), "the run left a Hydra log file in the working directory"
    out = tmp_path / "report"
    rows = json.loads((out / "cases.json").read_text())
    assert {r["name"]: r["has_gt"] for r in rows} == {"tee": True, "plain/line": False}
    assert all(r["time_s"] > 0 for r in rows if not r["error"])
    with open(out / "cases.csv") as f:
        assert len(list(csv.DictReader(f))) == 2
    summary = json.loads((out / "summary.json").read_text())
    assert summary["cases"] == 2 and "tables" in summary
    assert "keypoints pooled over all points" in summary["tables"]
    assert "keypoints pooled over all points" in res.stderr
    page = (out / "report.html").read_text()
    assert "tee" in page and "plain/line" in page and (out / "img" / "tee.png").is_file()
    assert "chamfer [‰ L]" in page and "f1_2 [0–1]" in page and "time_s [s]" in page      # units
    assert summary["units"]["chamfer"] == "fraction of L" and summary["units"]["time_s"] == "s"
    assert (tmp_path / "artifacts" / "prep").is_dir()  # the polyvec store, shared with `polyvec`

    again = cli(f"bench.cases=[{tmp_path / 'nowhere'}]", f"bench.out={tmp_path / 'r2'}", cwd=tmp_path,
                module="pipeline.bench")
    assert again.returncode == 2 and "not found" in again.stderr and "Traceback" not in again.stderr


def test_case_without_json_is_fidelity_only(tmp_path):
    img = tmp_path / "a.png"
    img.write_bytes(synthetic.line().png_bytes())
    c = load_case(img)
    assert isinstance(c, Case) and c.strokes is None and c.keypoints is None


def test_every_column_has_a_unit_and_small_distances_show():
    """Issue 18 item 18: a 0.1–0.4 px Chamfer printed 0.000; every column of the default tables and
    of the report names its unit, and distances are shown in ‰ of the long edge with 3 decimals."""
    from pipeline.bench_report import _fmt, _head, column_unit
    from pipeline.engine.registry import STAGES
    from tests.benchmarks._common import stage_cfg

    rep = stage_cfg("bench")["report"]
    for col in rep["gt_columns"] + rep["fidelity_columns"] + [f"t_{s.name}" for s in STAGES] + \
            ["kp_f1_1to1", "kp_class_acc", "kp_f1_1to1_junction", "width"]:
        assert _head(col).endswith("]") and column_unit(col)
    assert column_unit("chamfer") == column_unit("fid_hausdorff") == "‰ L"
    assert column_unit("f1_2") == "0–1" and column_unit("t_flow") == "s" and column_unit("peak_rss_mb") == "MB"
    assert column_unit("duplicated_px") == "px" and column_unit("dangling") == "count"
    assert _fmt(0.2 / 1000, "chamfer") == "0.200" and _fmt(0.0004, "fid_chamfer") == "0.400"


def test_junction_errors_match_like_the_acceptance_scorer_and_class_by_cause():
    """tests/benchmarks/junction_errors.py: its unmatched junctions are the scorer's fn and fp."""
    from tests.benchmarks.junction_errors import SCORER, classify, unmatched

    if not (SCORER / "score.py").exists():
        pytest.skip("../shared/tools/score.py (the acceptance scorer) is not here")
    pytest.importorskip("svgpathtools", reason="the acceptance scorer reads SVGs with svgpathtools")
    import sys

    sys.path.insert(0, str(SCORER))
    import score as S

    rng = np.random.default_rng(4)
    for _ in range(30):
        pred, ref = rng.uniform(0, 40, (rng.integers(0, 8), 2)), rng.uniform(0, 40, (rng.integers(0, 8), 2))
        _, tp, fp, fn = S.match_f1(pred, ref, 5.0)
        missed, false = unmatched(pred, ref, 5.0)
        assert (int(missed.sum()), int(false.sum())) == (fn, fp)
    ends = np.array([[0.0, 0.0], [50.0, 0.0]])
    labels = np.array([[20.0, 1.0]])
    points, types = np.array([[21.0, 0.0], [40.0, 0.0]]), np.array([3, 5], np.int8)
    assert classify(np.array([20.0, 0.0]), ends, 2.0, labels, points, types) == "mid lab kp=junction"
    assert classify(np.array([41.0, 0.0]), ends, 2.0, labels, points, types) == "mid unlab kp=corner"
    assert classify(np.array([49.0, 0.0]), ends, 2.0, labels, points, types) == "end unlab kp=none"
