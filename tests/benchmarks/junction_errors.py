"""Benchmark helper: the acceptance scorer's missed and false junctions, classed by their cause (not a test).

Usage::

    polyvec CASES output=OUT store.path=STORE
    python tests/benchmarks/junction_errors.py OUT CASES STORE [--json errors.json]

The junctions are the acceptance scorer's own (``../shared/tools/score.py``, ``topology`` and
``match_f1``, imported from there and run, not copied): those of the ground-truth strokes and those of
the output curves, matched one to one within max(5, w) px. Each missed (ground truth, unmatched) and
false (output, unmatched) junction is classed by

- where it lies: at a ground-truth stroke end (within 2 r) or mid-stroke;
- whether a labelled junction of the case (the §4.2 rules the detector is trained on) lies within 5 px;
- the type of the nearest detected keypoint within 5 px (the image's newest ``keypoints`` artifact in
  ``STORE``: run it right after the ``polyvec`` run it explains, or on a store of that run alone), or none;

and for each class the table gives its count and the junction F1 median / mean over the cases if that
class alone were right (misses found, false ones gone): where the end-to-end junction F1 is lost.
Use it on a validation split; never to choose on the set you report.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
SCORER = REPO.parent / "shared" / "tools"

from pipeline.inspect import resolve  # noqa: E402
from pipeline.engine.store import ArtifactStore  # noqa: E402
from stages.keypoints.codes import TYPE_CODES  # noqa: E402

#: Keypoint type names by code, for the classes.
TYPE_NAMES = dict(zip(TYPE_CODES, ("endpoint", "junction", "corner")))
#: Radius (px) within which a label or a detected keypoint explains a junction.
NEAR = 5.0


def unmatched(pred: np.ndarray, ref: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Which of ``ref`` and of ``pred`` the scorer's greedy one-to-one matching leaves unmatched."""
    if len(pred) == 0 or len(ref) == 0:
        return np.ones(len(ref), bool), np.ones(len(pred), bool)
    d = np.linalg.norm(pred[:, None] - ref[None], axis=2)
    ref_free, pred_free = np.ones(len(ref), bool), np.ones(len(pred), bool)
    # the same order and rule as score.match_f1
    for i in np.argsort(d.min(1)):
        j = int(np.argmin(np.where(ref_free, d[i], np.inf)))
        if d[i, j] <= tol and ref_free[j]:
            ref_free[j] = pred_free[i] = False
    return ref_free, pred_free


def near(points: np.ndarray, p: np.ndarray, radius: float) -> bool:
    """Whether any of ``points`` lies within ``radius`` of ``p``."""
    return bool(len(points)) and float(np.linalg.norm(points - p, axis=1).min()) <= radius


def keypoint_type(p: np.ndarray, points: np.ndarray, types: np.ndarray) -> str:
    """The type name of the detected keypoint nearest ``p`` within :data:`NEAR`, or ``'none'``."""
    if len(points):
        d = np.linalg.norm(points - p, axis=1)
        if d.min() <= NEAR:
            return TYPE_NAMES.get(int(types[int(np.argmin(d))]), "other")
    return "none"


def classify(p: np.ndarray, stroke_ends: np.ndarray, r: float, labels: np.ndarray, points: np.ndarray,
             types: np.ndarray) -> str:
    """``'end|mid lab|unlab kp=TYPE|none'`` of one junction position ``p``."""
    where = "end" if near(stroke_ends, p, 2 * r) else "mid"
    lab = "lab" if near(labels, p, NEAR) else "unlab"
    return f"{where} {lab} kp={keypoint_type(p, points, types)}"


def print_table(counts: dict, totals: collections.Counter, what: str, cases: Path, rows: list,
                json_path: Path | None) -> None:
    """Print each error class's count and the case F1 median / mean if that class alone were right
    (``counts``: per case, a Counter of ``'missed …'`` / ``'false …'`` classes and ``_matched``), and
    write ``rows`` to ``json_path``."""
    def f1(case: collections.Counter, fixed: str | None) -> float:
        fn = sum(v for k, v in case.items() if k.startswith("missed"))
        fp = sum(v for k, v in case.items() if k.startswith("false"))
        tp = case["_matched"]
        if fixed is not None and fixed.startswith("missed"):
            fn, tp = fn - case[fixed], tp + case[fixed]
        elif fixed is not None:
            fp -= case[fixed]
        return 1.0 if tp + fp + fn == 0 else 2 * tp / (2 * tp + fp + fn)

    classes = sorted({k for c in counts.values() for k in c if not k.startswith("_")})
    print(f"{len(counts)} cases of {cases}: {totals['truth']} scorer {what}s in the ground truth, "
          f"{totals['output']} in the output, {totals['matched']} matched")
    print(f"{'class':<34}{'count':>7}  {what} F1 median / mean if right")
    for cls in [None] + classes:
        vals = [f1(c, cls) for c in counts.values()]
        n = sum(c[cls] for c in counts.values()) if cls else 0
        print(f"{cls or '(as it is)':<34}{n:>7}  {np.median(vals):.3f} / {np.mean(vals):.3f}")
    if json_path:
        json_path.write_text(json.dumps(rows, indent=1))


@dataclass
class ScoredCase:
    """One case of a benchmark run: its ground truth and output, resampled as the acceptance scorer does,
    its radii (``r`` = max(2, w) the meeting radius, ``tol`` = max(5, w) the matching tolerance) and the
    keypoints detected on it (the store's newest ``keypoints`` artifact of the image)."""

    stem: str
    gt: dict
    r: float
    tol: float
    strokes: list
    curves: list
    points: np.ndarray
    types: np.ndarray


def command_line(argv: list[str] | None, doc: str, what: str) -> argparse.Namespace:
    """The benchmark's arguments: ``out``, ``cases``, ``store`` and ``--json`` (its missed / false ``what``s)."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="folder of <case>.svg (polyvec's output)")
    ap.add_argument("cases", type=Path, help="folder of scored cases (<case>.png and .json)")
    ap.add_argument("store", help="artifact store of that run (for the detected keypoints)")
    ap.add_argument("--json", type=Path, default=None, help=f"write every missed / false {what} here")
    return ap.parse_args(argv)


def scorer():
    """The acceptance scorer's module (``../shared/tools/score.py``), imported and run as it is."""
    sys.path.insert(0, str(SCORER))
    import score

    return score


def scored_cases(a: argparse.Namespace) -> Iterator[ScoredCase]:
    """Every scored case of ``a.cases`` (a PNG beside its JSON) with the output of ``a.out`` and the
    detected keypoints of ``a.store``."""
    S = scorer()
    store = ArtifactStore(a.store, create=False)
    for case_json in sorted(a.cases.glob("*.json")):
        png = case_json.with_suffix(".png")
        if case_json.name.endswith(".keypoints.json") or not png.exists():
            continue
        gt = json.loads(case_json.read_text())
        w = float(gt["width"])
        kp = store.load("keypoints", resolve(store, "keypoints", None, str(png)))
        yield ScoredCase(png.stem, gt, max(2.0, w), max(5.0, w), [S.resample(s) for s in gt["strokes"]],
                         [S.resample(c) for c in S.svg_polylines(str(a.out / f"{png.stem}.svg"))],
                         np.asarray(kp.arrays["points"]), np.asarray(kp.arrays["types"]))


def main(argv: list[str] | None = None) -> int:
    a = command_line(argv, __doc__, "junction")
    S = scorer()
    counts: dict[str, collections.Counter] = {}
    totals = collections.Counter()
    rows = []
    for case in scored_cases(a):
        strokes, r, points, types = case.strokes, case.r, case.points, case.types
        _, gj, _, _ = S.topology(strokes, r)
        _, oj, _, _ = S.topology(case.curves, r)
        labels = np.asarray(case.gt.get("junctions", []), float).reshape(-1, 2)
        ends = np.array([s[k] for s in strokes for k in (0, -1)]).reshape(-1, 2)
        missed, false = unmatched(oj, gj, case.tol)
        c = counts.setdefault(case.stem, collections.Counter())
        c["_matched"] = int((~missed).sum())
        for kind, where in (("missed", gj[missed]), ("false", oj[false])):
            for p in where:
                cls = f"{kind} {classify(p, ends, r, labels, points, types)}"
                c[cls] += 1
                rows.append({"case": case.stem, "class": cls, "x": float(p[0]), "y": float(p[1])})
        totals.update(truth=len(gj), output=len(oj), matched=int((~missed).sum()))

    print_table(counts, totals, "junction", a.cases, rows, a.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
