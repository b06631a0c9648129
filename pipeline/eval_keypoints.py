"""Score the keypoint stage on a folder of drawings with ground-truth keypoints.

Usage::

    python -m pipeline.eval_keypoints DIR [--weights PATH] [--ensemble [PATH ...]] [--threshold 0.5] [--min-distance 3]
                                          [--typing valence|argmax] [--type-classifier NPZ]
                                          [--precision fp32|bf16|auto] [--limit N] [--render OUT_DIR]
                                          [--json OUT.json] [--crossing-angle DEG]

``DIR`` holds ``<name>.png`` drawings, each with ``<name>.json`` (the realvec_dev format: lists
``endpoints``, ``junctions``, ``corners`` of (x, y)) or ``<name>.pts`` (the authors' format: ``N`` then
``row col type`` lines, y first). ``DIR`` may also be a single PNG file. Every drawing goes through the
real stages — ``prep`` then ``keypoints`` with conf/prep/default.yaml and conf/keypoints/default.yaml
(plus the options above) — and is scored by :mod:`stages.evaluate.keypoints`:

* the authors' F1 (radius 1 % of the padded height, per class and all types together), averaged over
  drawings;
* one-to-one matching within ``--radius`` px (default 5): detection F1 pooled over all drawings, and
  classification accuracy on the matched points.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from stages.evaluate.keypoints import TYPES, MatchResult, f1_authors, f1_authors_per_class, match_keypoints, read_pts
from stages.prep import to_internal, to_source

if TYPE_CHECKING:
    from stages.keypoints.training.config import LabelRules

_JSON_KEYS = (("endpoints", 1), ("junctions", 3), ("corners", 5))


def load_ground_truth(png: Path, rules: LabelRules | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """Ground-truth keypoints beside ``png`` (``.json`` or ``.pts``), or None.

    ``rules`` (:class:`~stages.keypoints.training.config.LabelRules`, see :func:`relabel_rules`): instead
    of the case's own labels, label its ``strokes`` (and ``width``) again with these rules
    (:func:`stages.keypoints.training.labels.label_keypoints`).
    """
    js = png.with_suffix(".json")
    if js.is_file():
        d = json.loads(js.read_text())
        if rules is not None:
            return _relabelled(d, rules, js)
        pts, types = [], []
        for key, code in _JSON_KEYS:
            for p in d.get(key, []):
                pts.append(p[:2])
                types.append(code)
        return np.asarray(pts, float).reshape(-1, 2), np.asarray(types, np.int8)
    for pts_path in (png.with_suffix(".pts"), png.parent / (png.name + ".pts")):
        if pts_path.is_file():
            return read_pts(pts_path.read_text())
    return None


def relabel_rules(crossing_angle: float) -> LabelRules:
    """The training label rules (``conf/train`` ``labels``) with crossings junctions from
    ``crossing_angle`` degrees: the case labels (metrics.md §4.2) use about 37°, the acceptance scorer 20°."""
    from pipeline.engine.config import default_config
    from stages.config import from_section
    from stages.keypoints.training.config import LabelRules

    section = dict(default_config("train")["labels"], crossing_min_deg=float(crossing_angle))
    return from_section(LabelRules, section, "train.labels")


def _relabelled(case: dict, rules: LabelRules, where: Path) -> tuple[np.ndarray, np.ndarray]:
    from stages.errors import InputError
    from stages.keypoints.training.labels import label_keypoints

    if "strokes" not in case or "width" not in case:
        raise InputError(f"{where.name}: --crossing-angle needs the case's vector strokes and width")
    strokes = [np.asarray(st, np.float64).reshape(-1, 2) for st in case["strokes"]]
    widths = np.broadcast_to(np.asarray(case["width"], np.float64), (len(strokes),))
    pts, types = label_keypoints(strokes, widths, rules)
    return np.asarray(pts, float).reshape(-1, 2), np.asarray(types, np.int8)


def _configs(overrides: dict) -> tuple[dict, dict]:
    from pipeline.engine.config import default_config

    prep_cfg, kp_cfg = default_config("prep"), default_config("keypoints")
    kp_cfg.update({k: v for k, v in overrides.items() if v is not None})
    return prep_cfg, kp_cfg


def evaluate_folder(folder: Path, kp_overrides: dict, radius: float = 5.0, limit: int | None = None,
                    render_dir: Path | None = None, crossing_angle: float | None = None) -> dict:
    """Run prep + keypoints on every drawing with ground truth in ``folder`` and score it.

    ``crossing_angle``: score against labels made again from the cases' strokes with this crossing
    angle (:func:`relabel_rules`, :func:`load_ground_truth`).

    Returns
    -------
    dict
        ``cases`` (per drawing figures) and ``summary`` (pooled / averaged figures).
    """
    from stages import prep as prep_stage
    from stages import keypoints as kp_stage

    prep_cfg, kp_cfg = _configs(kp_overrides)
    rules = None if crossing_angle is None else relabel_rules(crossing_angle)
    pngs = [folder] if folder.is_file() else sorted(folder.glob("*.png"))
    cases, pooled = [], MatchResult()
    t_total = 0.0
    weights_name = None  # the stage's own name for the networks it ran (main + ensemble)
    for png in pngs:
        gt = load_ground_truth(png, rules)
        if gt is None:
            continue
        if limit is not None and len(cases) >= limit:
            break
        gpts, gtypes = gt
        p = prep_stage.run(prep_cfg, image_bytes=png.read_bytes(), image_name=png.name)
        t0 = time.perf_counter()
        a = kp_stage.run(kp_cfg, prep=p)
        dt = time.perf_counter() - t0
        t_total += dt
        # a supersampled, downsampled or cropped prep: internal pixels
        pts, types = to_source(a["points"], p.data), a["types"]
        weights_name = a.data["weights"]
        h = int(p.data["height"])
        h_pad = h + (8 - h % 8)  # the authors' padded network input height
        m = match_keypoints(gpts, gtypes, pts, types, radius)
        pooled = pooled + m
        case = {"name": png.stem, "n_gt": int(len(gpts)), "n_pred": int(len(pts)),
                "f1_authors": f1_authors(gpts, pts, h_pad),
                "f1_authors_class": {str(k): v for k, v in f1_authors_per_class(gpts, gtypes, pts, types, h_pad).items()},
                "f1_matched": m.f1, "precision": m.precision, "recall": m.recall, "accuracy": m.accuracy,
                "seconds": dt}
        cases.append(case)
        if render_dir is not None:
            from PIL import Image

            render_dir.mkdir(parents=True, exist_ok=True)
            img = kp_stage.render_keypoints(p["grey"], a["heatmaps"], np.asarray(a["points"], np.float64), types)
            Image.fromarray(_with_gt(img, to_internal(gpts, p.data))).save(render_dir / f"{png.stem}_keypoints.png")
    n = max(len(cases), 1)
    summary = {
        "cases": len(cases),
        "weights": weights_name,
        "radius_px": radius,
        "f1_matched_pooled": pooled.f1, "precision_pooled": pooled.precision, "recall_pooled": pooled.recall,
        "accuracy_pooled": pooled.accuracy,
        "f1_matched_mean": sum(c["f1_matched"] for c in cases) / n,
        "f1_authors_mean": sum(c["f1_authors"] for c in cases) / n,
        "f1_authors_class_mean": {str(t): sum(c["f1_authors_class"][str(t)] for c in cases) / n for t in TYPES},
        "class_f1_pooled": {str(t): pooled.class_f1(t) for t in TYPES},
        "seconds_per_case": t_total / n,
        "threshold": kp_cfg["threshold"], "min_distance": kp_cfg["min_distance"], "typing": kp_cfg["typing"],
        "test_time_views": list(kp_cfg["test_time_views"]),
        "labels": "case" if crossing_angle is None else f"relabelled, crossings from {crossing_angle:g}°",
    }
    return {"summary": summary, "cases": cases}


def _with_gt(img: np.ndarray, gpts: np.ndarray) -> np.ndarray:
    """Mark ground-truth points with small black crosses."""
    img = img.copy()
    h, w = img.shape[:2]
    for x, y in gpts:
        i, j = int(np.floor(y)), int(np.floor(x))
        for d in range(-2, 3):
            if 0 <= i + d < h and 0 <= j < w:
                img[i + d, j] = 0
            if 0 <= i < h and 0 <= j + d < w:
                img[i, j + d] = 0
    return img


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipeline.eval_keypoints", description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--weights", default=None, help="checkpoint (default: the packaged weights)")
    ap.add_argument("--ensemble", nargs="*", default=None, metavar="WEIGHTS",
                    help="detection ensemble (default: the config's); give no value for the main network alone")
    ap.add_argument("--threshold", type=float, default=None)
    ap.add_argument("--min-distance", type=int, default=None)
    ap.add_argument("--typing", choices=("valence", "argmax"), default=None,
                    help="keypoint typing (default: conf/keypoints/default.yaml)")
    ap.add_argument("--type-classifier", default=None, help="type classifier .npz (default: the packaged one)")
    ap.add_argument("--views", nargs="*", default=None, metavar="VIEW",
                    help="test-time views averaged in (keypoints.test_time_views: flip_x flip_y rot180 transpose)")
    ap.add_argument("--precision", choices=("fp32", "bf16", "auto"), default=None,
                    help="network arithmetic (keypoints.precision)")
    ap.add_argument("--radius", type=float, default=5.0, help="one-to-one matching radius, px")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--render", type=Path, default=None, help="write overlays here")
    ap.add_argument("--json", type=Path, default=None, help="write all figures here")
    ap.add_argument("--crossing-angle", type=float, default=None, metavar="DEG",
                    help="score against labels made again from each case's strokes, crossings junctions from "
                         "DEG degrees (the case labels: about 37; the acceptance scorer: 20)")
    args = ap.parse_args(argv)
    if not args.folder.exists():
        print(f"error: {args.folder} does not exist", file=sys.stderr)
        return 2
    from stages.errors import InputError

    try:
        res = evaluate_folder(args.folder, {"weights": args.weights, "detection_ensemble": args.ensemble,
                                            "threshold": args.threshold,
                                            "min_distance": args.min_distance, "typing": args.typing,
                                            "type_classifier": args.type_classifier, "precision": args.precision,
                                            "test_time_views": args.views},
                              args.radius, args.limit, args.render, args.crossing_angle)
    except InputError as exc:        # a bad setting (threshold, view, weights): one line, as polyvec says it
        print(f"error: {exc}", file=sys.stderr)
        return 2
    s = res["summary"]
    if s["cases"] == 0:
        print(f"error: no PNG with a .json or .pts ground truth in {args.folder}", file=sys.stderr)
        return 2
    try:
        from rich.console import Console
        from rich.table import Table

        t = Table(title=f"keypoints on {args.folder} ({s['cases']} drawings, weights {s['weights']}, "
                          f"typing {s['typing']}, labels: {s['labels']})")
        t.add_column("metric")
        t.add_column("value", justify="right")
        rows = [("detection F1, one-to-one ≤ %.0f px (pooled)" % s["radius_px"], s["f1_matched_pooled"]),
                ("  precision / recall", f"{s['precision_pooled']:.3f} / {s['recall_pooled']:.3f}"),
                ("classification accuracy on matched points", s["accuracy_pooled"]),
                ("detection F1, one-to-one (mean per drawing)", s["f1_matched_mean"]),
                ("authors' F1, ρ = 1 % height (mean per drawing)", s["f1_authors_mean"])]
        names = {"1": "endpoint", "3": "junction", "5": "corner"}
        rows += [(f"authors' F1 {names[k]}", v) for k, v in s["f1_authors_class_mean"].items()]
        rows += [(f"class F1 one-to-one {names[k]} (pooled)", v) for k, v in s["class_f1_pooled"].items()]
        rows += [("seconds per drawing (keypoints stage)", s["seconds_per_case"])]
        for k, v in rows:
            t.add_row(k, v if isinstance(v, str) else f"{v:.3f}")
        Console().print(t)
    except ImportError:  # pragma: no cover
        print(json.dumps(s, indent=2))
    if args.json is not None:
        args.json.write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
