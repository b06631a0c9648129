"""Choose the keypoint stage's networks, NMS threshold and typing on a folder of scored cases.

Run::

    python tests/benchmarks/choose_keypoints.py CASES_DIR --net new=outputs/run/keypoints.pt \\
        --net procedural=packaged_procedural --ensemble new new+procedural \\
        --typing argmax valence=packaged valence=outputs/typing/type_classifier.npz \\
        --thresholds 0.2 0.3 0.4 --views none transpose flip_x+flip_y+rot180 --json choice.json

Every network runs once per drawing (``prep`` then the network, as the stage does); every
combination of ensemble (``a+b``: H1 is the mean of the listed networks' H1, the class maps are the
first one's), test-time views (``a+b``: the first network's four maps averaged over the drawing and
those mirror images, as ``keypoints.test_time_views``; ``none`` = the drawing alone), threshold and
typing is then scored by one-to-one matching within 5 px, pooled over
all points: detection F1, class accuracy and class F1 per type. The rows are printed best first by
the mean of the three class F1 (it rewards detection and typing together). Use it on the validation
split of ``pipeline.validation_cases``, never on the set you report.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from _common import stage_cfg  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    from pipeline.eval_keypoints import load_ground_truth
    from stages import prep as prep_stage
    from stages.evaluate.keypoints import TYPES, MatchResult, match_keypoints
    from stages.keypoints import keypoints_from_heatmaps, load_model
    from stages.keypoints import VIEWS
    from stages.keypoints.inference import network_input, predict_heatmaps
    from stages.prep import to_source

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cases", type=Path)
    ap.add_argument("--net", action="append", required=True, help="NAME=WEIGHTS (packaged, packaged_procedural or a path)")
    ap.add_argument("--ensemble", nargs="+", required=True, help="NAME or NAME+NAME… (the first gives the class maps)")
    ap.add_argument("--typing", nargs="+", default=["argmax", "valence=packaged"])
    ap.add_argument("--thresholds", nargs="+", type=float, default=[0.3])
    ap.add_argument("--views", nargs="+", default=["none"], help="none or VIEW+VIEW… (keypoints.test_time_views)")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)

    import torch

    torch.set_num_threads(1)
    nets = dict(n.split("=", 1) for n in a.net)
    pcfg, kcfg = stage_cfg("prep"), stage_cfg("keypoints")
    mains = {e.split("+")[0] for e in a.ensemble}
    view_sets = {v: [] if v == "none" else v.split("+") for v in a.views}
    views = sorted({v for vs in view_sets.values() for v in vs})
    if set(views) - set(VIEWS):
        ap.error(f"--views: unknown view(s) {sorted(set(views) - set(VIEWS))}; known: {sorted(VIEWS)}")
    cases = []
    for png in sorted(a.cases.glob("*.png"))[:a.limit]:
        gt = load_ground_truth(png)
        if gt is None:
            continue
        p = prep_stage.run(pcfg, image_bytes=png.read_bytes(), image_name=png.name)
        x = network_input(np.asarray(p["grey"], np.float32), float(kcfg["contrast_floor"]))
        maps = {}
        for name, w in nets.items():
            model, _ = load_model(w)
            for v in [None] + (views if name in mains else []):
                view = VIEWS[v] if v else (lambda arr: arr)
                hm = view(predict_heatmaps(model, np.ascontiguousarray(view(x)), int(kcfg["tile_size"]),
                                           int(kcfg["tile_overlap"]), detection_only=name not in mains,
                                           single_pass_max=int(kcfg["single_pass_max"])))
                maps[name if v is None else f"{name}@{v}"] = np.ascontiguousarray(hm).astype(np.float16)
        # a supersampled, downsampled or cropped prep gives internal pixels: keypoints are mapped back
        cases.append((png.stem, gt, np.asarray(p["mask"], bool), maps, p.data))
        print(f"\r{len(cases)} drawings", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    rows = []
    for ens, vset, thr, typing in itertools.product(a.ensemble, a.views, a.thresholds, a.typing):
        members = ens.split("+")
        cfg = dict(kcfg, threshold=thr, typing=typing.split("=")[0],
                   type_classifier=typing.split("=", 1)[1] if "=" in typing else kcfg["type_classifier"])
        pooled = MatchResult()
        for _, (gpts, gtypes), mask, maps, prep_data in cases:
            # As the stage: the main network's maps averaged over the views, then its H1 with the others'.
            hm = np.mean([maps[members[0]].astype(np.float32)]
                         + [maps[f"{members[0]}@{v}"].astype(np.float32) for v in view_sets[vset]], axis=0)
            hm[0] = (hm[0] + sum(maps[m][0].astype(np.float32) for m in members[1:])) / len(members)
            _, pts, types, _ = keypoints_from_heatmaps(cfg, hm, mask)
            pooled = pooled + match_keypoints(gpts, gtypes, to_source(pts, prep_data), types, 5.0)
        cf = {t: pooled.class_f1(t) for t in TYPES}
        rows.append({"ensemble": ens, "views": vset, "threshold": thr, "typing": typing, "f1": pooled.f1,
                     "precision": pooled.precision, "recall": pooled.recall, "accuracy": pooled.accuracy,
                     "f1_endpoint": cf[1], "f1_junction": cf[3], "f1_corner": cf[5],
                     "mean_class_f1": float(np.mean(list(cf.values())))})
    rows.sort(key=lambda r: -r["mean_class_f1"])
    print(f"{len(cases)} drawings of {a.cases}; one-to-one within 5 px, pooled")
    print(f"{'ensemble':<28}{'views':<24}{'thr':>5} {'typing':<40}{'F1':>7}{'P':>7}{'R':>7}{'acc':>7}{'end':>7}{'junc':>7}{'corner':>7}{'mean':>7}")
    for r in rows:
        print(f"{r['ensemble']:<28}{r['views'][-24:]:<24}{r['threshold']:>5.2f} {r['typing'][-40:]:<40}{r['f1']:7.3f}{r['precision']:7.3f}"
              f"{r['recall']:7.3f}{r['accuracy']:7.3f}{r['f1_endpoint']:7.3f}{r['f1_junction']:7.3f}"
              f"{r['f1_corner']:7.3f}{r['mean_class_f1']:7.3f}")
    if a.json:
        a.json.write_text(json.dumps({"cases": str(a.cases), "drawings": len(cases), "nets": nets, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
