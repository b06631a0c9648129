"""Human-stroke training data of the keypoint detector: readers, the category split, the thin aliased
style, the validation cases, resuming, and a tiny training run on human strokes."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.train import compose_plain
from stages.keypoints.training import category_split, draw_vector, stroke_count_cdf, train, vector_pool
from stages.keypoints.training.data import compose_settings, compose_strokes, stroke_count_power
from stages.keypoints.training.generator import drawing_from_strokes
from stages.keypoints.training.human_strokes import read_stroke3
from tests.conftest import train_configs

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
SHARED = ROOT / ".." / "shared"


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _write_categories(folder: Path, names: list[str], per: int = 3) -> None:
    """One ndjson per category; drawing i of every category is a T (bar 100 + 40 i, stem 120)."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        with open(folder / f"{name}.ndjson", "w") as f:
            for i in range(per):
                bar = [[0, 100 + 40 * i], [0, 0], [0, 1]]
                stem = [[50 + 20 * i, 50 + 20 * i], [0, 120], [2, 3]]
                f.write(json.dumps({"word": name, "drawing": [bar, stem]}) + "\n")


def _write_stroke3(path: Path) -> None:
    """Two symbols per split: an L (two strokes) and a one-stroke staircase diagonal."""
    ell = np.array([[0, 0, 0], [0, 60, 1], [0, 0, 0], [60, 0, 1]], np.int16)
    stairs = np.array([[0, 0, 0]] + [[6, 0, 0], [0, 6, 0]] * 10 + [[6, 0, 1]], np.int16)
    arr = np.empty(2, dtype=object)
    arr[0], arr[1] = ell, stairs
    np.savez(path, train=arr, valid=arr[:1], test=arr[:1])


def test_stroke3_reader_gives_absolute_strokes(tmp_path):
    _write_stroke3(tmp_path / "s3.npz")
    ell, stairs = read_stroke3(tmp_path / "s3.npz", "train")
    assert len(ell) == 2  # the pen lifts once between the two strokes
    np.testing.assert_allclose(ell[0], [[0, 0], [0, 60]])
    np.testing.assert_allclose(ell[1], [[0, 60], [60, 60]])  # the second starts where the pen was lifted
    assert len(stairs) == 1 and len(stairs[0]) == 22
    assert len(read_stroke3(tmp_path / "s3.npz", "valid")) == 1
    with pytest.raises(ValueError, match="no split 'dev'"):
        read_stroke3(tmp_path / "s3.npz", "dev")


def test_category_split_is_disjoint_deterministic_and_order_free():
    files = [f"/data/qd/cat_{i:03d}.ndjson" for i in range(296)]
    tr, va = category_split(files, 30, 0)
    assert len(va) == 30 and len(tr) == 266 and not set(tr) & set(va) and set(tr) | set(va) == set(files)
    assert category_split(list(reversed(files)), 30, 0) == (tr, va)          # order does not matter
    assert category_split([f.replace("/data/", "/elsewhere/") for f in files], 30, 0)[1] == \
        [f.replace("/data/", "/elsewhere/") for f in va]                        # only the names do
    assert category_split(files, 30, 1)[1] != va                                # the seed does
    assert category_split(files, 0, 0) == (sorted(files), [])


def test_vector_pool_holds_whole_categories_out(tmp_path):
    names = [f"thing{i}" for i in range(6)]
    _write_categories(tmp_path / "qd", names, per=3)
    _write_stroke3(tmp_path / "s3.npz")
    vcfg = {"files": [str(tmp_path / "qd" / "*.ndjson")], "holdout": 2, "split_seed": 0, "skip": 1,
            "stroke3": [str(tmp_path / "s3.npz")], "stroke3_simplify": 6.5}
    train_pool, valid_pool = vector_pool(vcfg, "train"), vector_pool(vcfg, "valid")
    assert len(train_pool["ndjson"]) == 4 * 2 and len(valid_pool["ndjson"]) == 2 * 2  # skip 1 of 3 each
    assert len(train_pool["stroke3"]) == 2 and len(valid_pool["stroke3"]) == 1
    # Douglas-Peucker at one grid cell turns the staircase into one straight segment.
    assert len(train_pool["stroke3"][1][0]) == 2
    with pytest.raises(ValueError):
        vector_pool(vcfg, "test")


def test_busy_drawings_are_drawn_by_their_stroke_count():
    """``train.vector.stroke_count_power`` 1: every stroke of the pool equally likely, not every drawing."""
    t = np.linspace(0, 1, 5)
    one = [np.stack([10 + 80 * t, 10 + 0 * t], 1)]
    nine = [np.stack([10 + 80 * t, 10 + 9 * k + 0 * t], 1) for k in range(9)]
    pool = {"ndjson": [one, nine], "stroke3": []}
    vcfg = {"size": [48, 48]}
    generator, rules = train_configs()

    def busy_share(cdf, n=120):
        rng = np.random.default_rng(5)
        return np.mean([len(draw_vector(rng, pool, vcfg, generator, rules, ndjson_cdf=cdf).strokes) == 9
                        for _ in range(n)])

    assert stroke_count_cdf(pool["ndjson"], 0.0) is None                      # uniform, the old stream
    assert 0.35 < busy_share(None) < 0.65
    assert busy_share(stroke_count_cdf(pool["ndjson"], 1.0)) > 0.8            # 9 of 10 strokes
    with pytest.raises(ValueError, match="stroke_count_power must be >= 0"):
        stroke_count_power({"stroke_count_power": -1.0})


def test_a_composed_drawing_lays_a_smaller_turned_drawing_over_the_first():
    """``train.vector.compose_prob``: a second drawing, scaled into ``compose_scale`` of the canvas and
    turned, is laid over the first; the labels see both, so their strokes' crossings are junctions."""
    t = np.linspace(0, 1, 20)[:, None]
    bar = [np.hstack([10 + 300 * t, 60 + 0 * t])]                 # one horizontal stroke
    cross = [np.hstack([0 * t, 100 * t]), np.hstack([-50 + 100 * t, 50 + 0 * t])]   # a plus sign
    size = 200
    for seed in range(20):
        rng = np.random.default_rng(seed)
        strokes = compose_strokes(rng, bar, cross, size, (0.5, 0.5))
        assert len(strokes) == 3
        assert np.ptp(strokes[0][:, 0]) == pytest.approx(size - 32)   # the first, fitted to the canvas
        over = np.concatenate(strokes[1:])
        # the plus sign fills a 100-px square (12.5-px margins): its arms stay 75 px long, at right angles
        assert np.linalg.norm(strokes[1][-1] - strokes[1][0]) == pytest.approx(75)
        d1, d2 = strokes[1][-1] - strokes[1][0], strokes[2][-1] - strokes[2][0]
        assert abs(d1 @ d2) < 1e-6
        assert (over.mean(0) >= 50 - 1e-6).all() and (over.mean(0) <= 150 + 1e-6).all()
    # over many draws the angle turns (not always upright) and the position moves
    angles = {round(float(np.degrees(np.arctan2(*(s[1][-1] - s[1][0])))) % 90)
              for s in (compose_strokes(np.random.default_rng(k), bar, cross, size, (0.5, 0.5)) for k in range(20))}
    assert len(angles) > 10
    # through draw_vector: every Quick, Draw! draw is composed at probability 1, none at 0
    pool = {"ndjson": [bar, cross], "stroke3": []}
    generator, rules = train_configs()
    rng = np.random.default_rng(1)
    counts = [len(draw_vector(rng, pool, {"size": [96, 96], "compose_prob": 1.0}, generator, rules).strokes)
              for _ in range(8)]
    assert min(counts) >= 2
    counts = [len(draw_vector(rng, pool, {"size": [96, 96], "compose_prob": 0.0}, generator, rules).strokes)
              for _ in range(8)]
    assert max(counts) <= 2


def test_compose_settings_are_checked():
    assert compose_settings({}) == (0.0, (0.4, 0.7))
    assert compose_settings({"compose_prob": 0.3, "compose_scale": [0.5, 1.0]}) == (0.3, (0.5, 1.0))
    with pytest.raises(ValueError, match="compose_prob must be within"):
        compose_settings({"compose_prob": 1.5})
    for bad in ([0.8, 0.5], [0.0, 0.5], [0.5, 1.2]):
        with pytest.raises(ValueError, match="compose_scale must be"):
            compose_settings({"compose_scale": bad})


def test_thin_aliased_style_is_thin_and_labels_no_corner_on_a_circle():
    rng = np.random.default_rng(3)
    t = np.linspace(0, 2 * np.pi, 400)
    circle = [np.stack([100 + 70 * np.cos(t), 100 + 70 * np.sin(t)], 1)]
    arc = [np.stack([100 + 70 * np.cos(t[:200]), 100 + 70 * np.sin(t[:200])], 1)]
    generator, rules = train_configs()
    cfg = replace(generator, thin_prob=1.0)
    for strokes in (circle, arc):
        s = drawing_from_strokes(rng, strokes, (200, 200), cfg, rules)
        assert max(float(np.max(w)) for w in s.widths) <= 2.2
        assert 5 not in s.types.tolist()
    assert sorted(s.types.tolist()) == [1, 1]
    # hard-edged or coarsely anti-aliased: few distinct grey levels along the ink
    levels = [len(np.unique(np.round(drawing_from_strokes(np.random.default_rng(k), circle, (200, 200), cfg,
                                                         rules).grey, 3))) for k in range(6)]
    assert min(levels) < 40


def _tiny(tmp_path: Path, extra: list[str]) -> dict:
    return compose_plain(CONF, [
        f"train.out_dir={tmp_path / 'run'}", "train.batch_size=4", "train.num_workers=0",
        "train.crop_schedule=[[0,48]]", "train.val.count=1", "train.val.vector_count=0", "train.val.every=1000",
        "train.log_every=1000", "train.lr=0.003", "train.network.level_channels=[4,8,8,8]",
        "train.network.stem_mid=4", "train.network.bottleneck_blocks=1", "train.seed=1"] + extra)


def test_tiny_training_on_human_strokes_lowers_its_loss(tmp_path):
    _write_categories(tmp_path / "qd", [f"thing{i}" for i in range(4)], per=4)
    cfg = _tiny(tmp_path, [f"train.vector.files=[{tmp_path / 'qd' / '*.ndjson'}]", "train.vector.holdout=1",
                           "train.vector.stroke3=[]", "train.vector.size=[96,128]", "train.vector_prob=1.0",
                           "train.vector_crops_per_image=4", "train.steps=14", "train.checkpoint_every=100"])
    torch.manual_seed(0)
    curve = train(cfg)["loss_curve"]
    assert len(curve) == 14 and np.mean(curve[-4:]) < np.mean(curve[:4])


def test_training_resumes_where_it_stopped(tmp_path):
    cfg = _tiny(tmp_path, ["train.steps=6", "train.checkpoint_every=3"])
    first = train(cfg)
    ck = torch.load(tmp_path / "run" / "last.pt", map_location="cpu", weights_only=False)
    assert ck["step"] == 6
    # The same command with more steps continues from step 6: only the new steps run.
    cfg["train"]["steps"] = 9
    second = train(cfg)
    assert first["steps"] == 6 and second["steps"] == 9 and len(second["loss_curve"]) == 3


def test_validation_cases_from_held_out_categories(tmp_path):
    from pipeline.eval_keypoints import evaluate_folder, load_ground_truth
    from pipeline.validation_cases import write_cases

    _write_categories(tmp_path / "qd", [f"thing{i}" for i in range(5)], per=3)
    cfg = compose_plain(CONF, [f"train.vector.files=[{tmp_path / 'qd' / '*.ndjson'}]", "train.vector.holdout=2",
                               "train.vector.stroke3=[]"])
    names = write_cases(cfg, tmp_path / "cases", per_category=1, stroke3=0)
    _, held = category_split([str(p) for p in (tmp_path / "qd").glob("*.ndjson")], 2, 0)
    assert sorted(names) == sorted(f"val_qd_{Path(f).stem}_0_{style}" for f in held for style in ("clean", "pencil"))
    d = json.loads((tmp_path / "cases" / f"{names[0]}.json").read_text())
    assert d["size"] == 512 and d["width"] in (2.0, 3.0, 5.0) and len(d["strokes"]) == 2
    assert len(d["endpoints"]) == 3 and len(d["junctions"]) == 1  # a T
    pts, types = load_ground_truth(tmp_path / "cases" / f"{names[0]}.png")
    assert sorted(types.tolist()) == [1, 1, 1, 3]
    again = write_cases(cfg, tmp_path / "again", per_category=1, stroke3=0)
    assert again == names and (tmp_path / "again" / f"{names[0]}.png").read_bytes() == \
        (tmp_path / "cases" / f"{names[0]}.png").read_bytes()
    res = evaluate_folder(tmp_path / "cases", {}, limit=1)
    assert res["summary"]["cases"] == 1


def test_busy_validation_split_keeps_only_drawings_with_enough_strokes(tmp_path, capsys):
    from pipeline.validation_cases import main

    folder = tmp_path / "qd"
    folder.mkdir()
    for name in ("a", "b", "c"):
        with open(folder / f"{name}.ndjson", "w") as f:
            for i in range(3):  # drawing i has 2 + i strokes: a T, then one more bar per drawing
                strokes = [[[0, 100], [10 * k, 10 * k], [0, 1]] for k in range(1 + i)]
                strokes.append([[50, 50], [0, 120], [2, 3]])
                f.write(json.dumps({"word": name, "drawing": strokes}) + "\n")
    common = [f"train.vector.files=[{folder / '*.ndjson'}]", "train.vector.holdout=1", "train.vector.stroke3=[]",
              "--stroke3", "0", "--per-category", "2"]
    assert main([str(tmp_path / "busy"), "--min-strokes", "3", *common]) == 0
    names = sorted(p.stem for p in (tmp_path / "busy").glob("*.json"))
    assert len(names) == 4 and {n.rsplit("_", 2)[1] for n in names} == {"1", "2"}  # drawing 0 has 2 strokes
    for n in names:
        d = json.loads((tmp_path / "busy" / f"{n}.json").read_text())
        assert len(d["strokes"]) >= 3
    assert main([str(tmp_path / "all"), *common]) == 0
    assert {p.stem.rsplit("_", 2)[1] for p in (tmp_path / "all").glob("*.json")} == {"0", "1"}
    assert "4 validation cases written" in capsys.readouterr().out


@pytest.mark.shared
def test_shared_split_holds_out_thirty_categories():
    qd = SHARED / "data" / "vector" / "quickdraw_train"
    if not qd.is_dir():
        pytest.skip("../shared absent")
    files = sorted(str(p) for p in qd.glob("*.ndjson"))
    tr, va = category_split(files, 30, 0)
    assert len(files) == 296 and len(va) == 30
    # none of realvec_dev's Quick, Draw! categories is among them
    dev = {p.stem for p in (SHARED / "data" / "vector" / "quickdraw").glob("*.ndjson")}
    assert not dev & {Path(f).stem for f in files}


def test_keypoint_crops_centre_on_the_weighted_types(tmp_path):
    """``train.keypoint_crop_type_weights`` chooses which keypoints the keypoint crops centre on: with
    the weight on junctions only, every crop of a T holds the T's junction; on endpoints only, few do."""
    import itertools

    from stages.keypoints.training.data import DrawingStream

    _write_categories(tmp_path / "qd", ["tee"], per=3)

    def junction_share(weights: str) -> float:
        cfg = compose_plain(CONF, [f"train.vector.files=[{tmp_path / 'qd' / '*.ndjson'}]", "train.vector.holdout=0",
                                   "train.vector.stroke3=[]", "train.vector.size=[160,192]", "train.vector_prob=1.0",
                                   "train.keypoint_crop_prob=1.0", f"train.keypoint_crop_type_weights={weights}"])
        crops = list(itertools.islice(iter(DrawingStream(cfg, 32, 0)), 48))
        return float(np.mean([float(t[2].max()) > 0.9 for _, t, _ in crops]))

    assert junction_share("[0,1,0]") == 1.0
    assert junction_share("[1,0,0]") < 0.5
    with pytest.raises(ValueError, match="three weights"):
        junction_share("[1,1]")


def test_junction_weighted_band_counts_junction_pixels_more():
    from stages.keypoints.training.targets import gaussian_heatmaps, junction_weighted_band

    t = torch.from_numpy(gaussian_heatmaps((16, 16), np.array([[4.5, 4.5], [11.5, 11.5]]), np.array([3, 1]), 2.0))[None]
    band = torch.ones(1, 1, 16, 16)
    band[..., :, 14:] = 0
    assert junction_weighted_band(band, t, 0.0) is band
    w = junction_weighted_band(band, t, 4.0)
    assert float(w[0, 0, 4, 4]) == pytest.approx(5.0)        # the junction's centre counts 1 + 4 times
    assert float(w[0, 0, 11, 11]) == pytest.approx(1.0)      # an endpoint's does not
    assert float(w[..., 14:].abs().sum()) == 0.0              # nothing outside the band


def test_cpu_autocast_only_where_the_cpu_has_native_bf16(monkeypatch):
    """``train.cpu_amp: auto`` (the default): emulated bf16 made a CPU step 7x slower than fp32."""
    from stages.errors import InputError
    from stages.keypoints.training.loop import cpu_autocast

    assert compose_plain(CONF, [])["train"]["cpu_amp"] == "auto"
    for native in (False, True):
        monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda native=native: native)
        assert cpu_autocast("auto") is native
        assert cpu_autocast(True) is True and cpu_autocast(False) is False
    with pytest.raises(InputError, match="cpu_amp"):
        cpu_autocast("sometimes")


def test_a_bad_training_value_is_one_error_line(tmp_path):
    import subprocess
    import sys

    for bad, line in (("train.cpu_amp=sometimes", "train.cpu_amp must be true, false or auto, got 'sometimes'"),
                      ("train.vector.stroke_count_power=-1", "train.vector.stroke_count_power must be >= 0, got -1.0"),
                      ("train.vector.compose_prob=2", "train.vector.compose_prob must be within [0, 1], got 2.0")):
        proc = subprocess.run([sys.executable, "-m", "pipeline.train", "--plain", str(CONF), bad,
                               f"train.out_dir={tmp_path / 'run'}"], cwd=ROOT, capture_output=True, text=True,
                              timeout=120)
        assert proc.returncode == 2 and proc.stderr.strip().splitlines() == [f"polyvec-train: error: {line}"], \
            proc.stderr
        assert not (tmp_path / "run").exists()
