"""Keypoint typing by local valence (stages/keypoints/valence.py) and its training."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from stages import synthetic
from stages.artifact import Artifact
from stages.errors import InputError
from stages.keypoints import PACKAGED_TYPE_CLASSIFIER, STAGE_VERSION, run
from stages.keypoints.valence import (FEATURES, MAX_RUNS, RING_RADII, TypeClassifier, class_scores_at,
                                      local_width, ring_profiles, valence_features)

CONF = Path(__file__).resolve().parents[2] / "conf"


def _runs(features: np.ndarray, ring: int) -> int:
    col = 3 + ring * (MAX_RUNS + 4)
    return int(np.argmax(features[col:col + MAX_RUNS + 1]))


def test_ring_profiles_count_arcs_and_angles():
    rings = np.zeros((4, 96), bool)
    rings[1, 10:14] = True
    rings[1, 58:62] = True  # opposite: a straight stroke through the centre
    rings[2, 94:] = True
    rings[2, :3] = True     # one arc wrapping around the start of the vector
    rings[3] = True         # all ink: a blob
    runs, coverage, widest, cos_pair = ring_profiles(rings)
    assert list(runs) == [0, 2, 1, 0]
    assert cos_pair[1] == pytest.approx(-1.0) and coverage[1] == pytest.approx(8 / 96)
    assert widest[2] == pytest.approx(5 / 96) and cos_pair[2] == 1.0
    assert (coverage[3], widest[3]) == (1.0, 1.0) and (coverage[0], widest[0]) == (0.0, 0.0)


def test_rings_of_many_points_are_those_of_each_point_alone(monkeypatch):
    # The rings of all points are labelled together, windows of one size stacked in one call: no
    # window may see another's ink, whatever the chunking, at the border or off the image.
    import stages.keypoints.valence as valence

    rng = np.random.default_rng(5)
    mask = np.zeros((120, 200), bool)
    mask[39:42, 10:38] = True     # an end at x = 37.5 that stops 3 px short of ...
    mask[10:70, 41:44] = True     # ... a vertical stroke
    mask[20:100, 110:190] = True  # a blob: its window is all ink where the end's has a gap
    pts = np.concatenate([[[37.5, 40.5], [150.5, 60.5]], rng.uniform(-8, 208, (40, 2)),
                          [[0.5, 0.5], [199.9, 40.2], [-30.0, 10.0]]])
    radii = np.concatenate([[12.0, 12.0], rng.choice([3.0, 7.5, 12.0], len(pts) - 2)])
    together = valence._connected_rings(mask, pts, radii)
    alone = np.concatenate([valence._connected_rings(mask, pts[k:k + 1], radii[k:k + 1]) for k in range(len(pts))])
    assert together.any() and np.array_equal(together, alone)
    assert ring_profiles(alone[:1])[0][0] == 1  # the end sees its own stroke only
    monkeypatch.setattr(valence, "_LABEL_CHUNK", 700)  # a few windows per call
    assert np.array_equal(valence._connected_rings(mask, pts, radii), alone)
    assert not alone[-1].any()  # off the image: no ink


@pytest.mark.parametrize("drawing, point, runs", [
    (synthetic.line(size=96, angle=20.0, length=60.0, width=3.0), "end", 1),
    (synthetic.cross(size=96, length=70.0, width=3.0), "centre", 4),
    (synthetic.tee(size=96, length=70.0, width=3.0), "junction", 3),
    (synthetic.vee(size=96, opening=60.0, length=40.0, width=3.0), "corner", 2),
])
def test_valence_features_see_the_branches(drawing, point, runs):
    kinds = {"end": 1, "centre": 3, "junction": 3, "corner": 5}
    pts = np.array([k[:2] for k in drawing.keypoints if k[2] == kinds[point]][:1], float)
    mask = drawing.grey < 0.65
    f = valence_features(mask, pts, np.zeros((1, 3)))
    assert f.shape == (1, FEATURES)
    # At the larger rings (beyond the stroke's own width) the branch count is the valence.
    assert _runs(f[0], 2) == runs and _runs(f[0], 3) == runs
    assert 2.0 <= local_width(mask, pts)[0] <= 6.0  # a vee tip is wider than its 3-px legs


def test_a_stroke_passing_near_an_end_is_not_a_branch():
    # An end that stops 3 px short of a crossing stroke: an endpoint by the labelling rule. Only the
    # stroke the point lies on is sampled, so every ring sees one branch.
    from skimage.draw import line_aa

    img = np.ones((80, 80), np.float32)
    for r0, c0, r1, c1, off in [(40, 10, 40, 37, 0), (10, 43, 70, 43, 0)]:
        for d in (-1, 0, 1):
            rr, cc, val = line_aa(r0 + d * (c0 == c1), c0 + d * (r0 == r1), r1 + d * (c0 == c1), c1 + d * (r0 == r1))
            img[rr, cc] = np.minimum(img[rr, cc], 1 - val)
    mask = img < 0.65
    f = valence_features(mask, np.array([[37.5, 40.5]]), np.zeros((1, 3)))
    assert [_runs(f[0], k) for k in range(len(RING_RADII))] == [1] * len(RING_RADII)
    # Joined to the other stroke (a T), the larger rings see three branches.
    mask[39:42, 37:43] = True
    f = valence_features(mask, np.array([[43.5, 40.5]]), np.zeros((1, 3)))
    assert _runs(f[0], 3) == 3 and _runs(f[0], 4) == 3


def test_class_scores_at_reads_the_peak_pixel():
    h = np.zeros((4, 10, 10), np.float32)
    h[1:4, 3, 7] = [0.1, 0.9, 0.2]
    assert np.allclose(class_scores_at(h, np.array([[7.5, 3.5]])), [[0.1, 0.9, 0.2]])


def test_type_classifier_roundtrip(tmp_path):
    rng = np.random.default_rng(0)
    p = {"mean": np.zeros(FEATURES), "std": np.ones(FEATURES), "w1": rng.normal(size=(FEATURES, 4)),
         "b1": np.zeros(4), "w2": rng.normal(size=(4, 3)), "b2": np.zeros(3)}
    clf = TypeClassifier(p)
    x = rng.normal(size=(5, FEATURES))
    clf.save(tmp_path / "c.npz")
    assert np.array_equal(TypeClassifier.load(tmp_path / "c.npz").predict(x), clf.predict(x))
    with pytest.raises(ValueError):
        TypeClassifier(p | {"w1": np.zeros((FEATURES + 1, 4))})


def _kp_cfg(**kw) -> dict:
    return yaml.safe_load((CONF / "keypoints" / "default.yaml").read_text()) | kw


@pytest.mark.skipif(not PACKAGED_TYPE_CLASSIFIER.is_file(), reason="no shipped type classifier")
def test_stage_types_by_valence_by_default():
    assert _kp_cfg()["typing"] == "valence" and _kp_cfg()["type_classifier"] == "packaged"
    d = synthetic.tee(size=96, length=70.0, width=3.0)
    prep = Artifact(arrays={"grey": d.grey, "mask": d.grey < 0.65}, data={})
    a = run(_kp_cfg(), prep=prep)
    b = run(_kp_cfg(typing="argmax"), prep=prep)
    assert np.array_equal(a["points"], b["points"])  # typing never moves or drops points
    gt = {(round(k[0]), round(k[1])): k[2] for k in d.keypoints}
    got = {(round(float(x)), round(float(y))): int(t) for (x, y), t in zip(a["points"], a["types"])}
    near = [t for (x, y), t in got.items() if any(abs(x - gx) <= 3 and abs(y - gy) <= 3 and gt[(gx, gy)] == 3
                                                 for gx, gy in gt)]
    assert near == [3]  # the T's junction is typed as a junction
    assert STAGE_VERSION.count("+") == 3  # hashes of the network, the type classifier, the ensemble member


def test_stage_rejects_unknown_typing_and_missing_classifier(tmp_path):
    d = synthetic.line(size=48)
    prep = Artifact(arrays={"grey": d.grey, "mask": d.grey < 0.65}, data={})
    with pytest.raises(InputError, match="typing"):
        run(_kp_cfg(typing="bogus"), prep=prep)
    with pytest.raises(InputError, match="type_classifier"):
        run(_kp_cfg(type_classifier=str(tmp_path / "none.npz")), prep=prep)


def test_type_classifier_training_smoke(tmp_path):
    from pipeline.train import compose_plain
    from stages.keypoints.training import train_type_classifier

    torch.set_num_threads(1)
    ndjson = tmp_path / "doodles.ndjson"
    _write_ndjson(ndjson, 3)
    cfg = compose_plain(CONF, [f"train.out_dir={tmp_path}", "train.type_classifier.drawings=4",
                               "train.type_classifier.val_drawings=2", "train.type_classifier.epochs=20",
                               f"train.vector.files=[{ndjson}]", "train.vector.holdout=0",
                               "train.vector.stroke3=[]", "train.vector.skip=2", "train.vector.size=[96,128]",
                               "train.type_classifier.vector_drawings=null"])   # the one drawing left, `renders` times
    rec = train_type_classifier(cfg)
    assert rec["keypoints"] > 0 and sum(rec["class_counts"]) == rec["keypoints"]
    assert rec["vector_files"] == ["doodles.ndjson"]
    clf = TypeClassifier.load(tmp_path / "type_classifier.npz")
    assert clf.params["w1"].shape == (FEATURES, int(cfg["train"]["type_classifier"]["hidden"]))
    assert 0.0 <= rec["val_accuracy"] <= 1.0


def _write_ndjson(path, n):
    """``n`` Quick, Draw!-style drawings: drawing i is a T, bar 100 + 50 i long, stem 120 long from its middle."""
    import json

    with open(path, "w") as f:
        for i in range(n):
            bar = [[0, 100 + 50 * i], [0, 0]]
            stem = [[50 + 25 * i, 50 + 25 * i], [0, 120]]
            f.write(json.dumps({"word": "t", "drawing": [bar, stem]}) + "\n")


def test_vector_samples_skip_renders_and_labels(tmp_path):
    """Human-stroke training drawings: the first ``skip`` drawings never appear, each is styled
    ``renders`` times on a canvas within ``size``, and its keypoints come from the label rules."""
    from stages.config import from_section
    from stages.keypoints.training import vector_samples
    from stages.keypoints.training.generator import GeneratorConfig
    from stages.keypoints.training.labels import LabelRules

    ndjson = tmp_path / "doodles.ndjson"
    _write_ndjson(ndjson, 3)
    train_cfg = yaml.safe_load((CONF / "train" / "default.yaml").read_text())
    gcfg = from_section(GeneratorConfig, train_cfg["generator"], "train.generator")
    rules = from_section(LabelRules, train_cfg["labels"], "train.labels")
    vcfg = {"files": [str(tmp_path / "*.ndjson")], "skip": 1, "renders": 2, "size": [100, 140]}
    samples = list(vector_samples(vcfg, np.random.default_rng(0), gcfg, rules))
    assert len(samples) == 4  # drawings 1 and 2, twice each
    for s in samples:
        assert 100 <= s.grey.shape[0] <= 140 and s.grey.shape[0] == s.grey.shape[1]
        # a T: two endpoints of the bar, the stem's free end, one junction where it meets the bar
        assert sorted(s.types.tolist()) == [1, 1, 1, 3]
    # drawing 0 (bar 100 units) is skipped: bar/stem length ratios are those of drawings 1 and 2
    ratios = sorted({round(float(np.ptp(s.strokes[0][:, 0]) / np.ptp(s.strokes[1][:, 1])), 2) for s in samples})
    assert ratios == [round(150 / 120, 2), round(200 / 120, 2)]
    assert list(vector_samples({"files": [str(tmp_path / "none*.ndjson")]}, np.random.default_rng(0), gcfg, rules)) == []


def test_detector_stream_mixes_human_strokes(tmp_path, monkeypatch):
    """``train.vector_prob`` is the share of detector-training drawings drawn from the human strokes;
    each of those gives ``vector_crops_per_image`` crops, and 0 keeps training procedural only."""
    import itertools

    import stages.keypoints.training.data as tr
    from pipeline.train import compose_plain

    ndjson = tmp_path / "doodles.ndjson"
    _write_ndjson(ndjson, 3)
    calls = {"vector": 0, "generated": 0}
    real_render, real_generate = tr.render_vector, tr.generate

    def render(*a, **k):
        calls["vector"] += 1
        return real_render(*a, **k)

    def gen(*a, **k):
        calls["generated"] += 1
        return real_generate(*a, **k)

    monkeypatch.setattr(tr, "render_vector", render)
    monkeypatch.setattr(tr, "generate", gen)

    def crops(prob, n):
        cfg = compose_plain(CONF, [f"train.vector.files=[{ndjson}]", "train.vector.skip=1",
                                      "train.vector.holdout=0", "train.vector.stroke3=[]",
                                      "train.vector.size=[96,128]", f"train.vector_prob={prob}",
                                      "train.vector_crops_per_image=3", "train.crops_per_image=2"])
        calls.update(vector=0, generated=0)
        out = list(itertools.islice(iter(tr.DrawingStream(cfg, 64, 0)), n))
        assert all(x.shape == (1, 64, 64) and t.shape == (4, 64, 64) for x, t, _ in out)
        return dict(calls)

    assert crops(1.0, 9) == {"vector": 3, "generated": 0}
    assert crops(0.0, 8) == {"vector": 0, "generated": 4}
    mixed = crops(0.5, 60)
    assert mixed["vector"] > 0 and mixed["generated"] > 0
