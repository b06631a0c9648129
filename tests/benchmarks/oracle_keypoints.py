"""Benchmark helper: a copy of a case folder whose keypoint edits replace the detector's keypoints by the labels.

Usage::

    polyvec CASES output=OUT store.path=STORE                       # the detector's keypoints, stored
    python tests/benchmarks/oracle_keypoints.py CASES STORE ORACLE [--types endpoint junction corner]
    polyvec ORACLE output=OUT_ORACLE store.path=STORE                # the same pipeline, labelled keypoints
    python ../shared/tools/score_folder.py OUT_ORACLE CASES

``ORACLE`` gets a link to each case's PNG and JSON and a ``<stem>.keypoints.json``
(:mod:`stages.keypoint_edits`) that removes every detected keypoint of the chosen ``--types`` (all three
by default) and adds the case's labelled ones of those types. The edits stage sits after the
detector, so the second run reuses prep, keypoints, field and graph from ``STORE`` and recomputes
topology onward: the end-to-end score with perfect keypoints (of some types), i.e. the share of
the distance to the targets that the detector holds. Not a test.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from pipeline.inspect import resolve  # noqa: E402
from pipeline.engine.store import ArtifactStore  # noqa: E402
from stages.keypoint_edits import FORMAT, TYPE_CODES  # noqa: E402

#: Case JSON key of each keypoint type's labels.
LABEL_KEYS = {"endpoint": "endpoints", "junction": "junctions", "corner": "corners"}


def oracle_edits(case: dict, points: np.ndarray, types: np.ndarray, image: str, which: list[str]) -> dict:
    """The edits that swap the detected keypoints of the types ``which`` for the case's labels.

    Parameters
    ----------
    case : dict
        A scored case (``size`` and the label lists ``endpoints``, ``junctions``, ``corners``).
    points, types : numpy.ndarray
        The detector's keypoints artifact (``points`` (n, 2) x, y; ``types`` codes 1 / 3 / 5).
    image : str
        The image's file name.
    which : list of str
        Keypoint types to replace.

    Returns
    -------
    dict
        A keypoint-edits document.
    """
    codes = {TYPE_CODES[t] for t in which}
    removed = [{"x": float(p[0]), "y": float(p[1])} for p, t in zip(points, types) if int(t) in codes]
    added = [{"x": float(x), "y": float(y), "type": t} for t in which for x, y in case.get(LABEL_KEYS[t], [])]
    size = case.get("size")
    return {"format": FORMAT, "version": 1, "image": image, "width": size, "height": size,
            "added": added, "removed": removed, "retyped": []}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cases", type=Path)
    ap.add_argument("store", help="artifact store holding the detector's keypoints of the cases")
    ap.add_argument("out", type=Path)
    ap.add_argument("--types", nargs="+", choices=sorted(LABEL_KEYS), default=sorted(LABEL_KEYS))
    a = ap.parse_args()
    store = ArtifactStore(a.store, create=False)
    a.out.mkdir(parents=True, exist_ok=True)
    n = 0
    for case_json in sorted(a.cases.glob("*.json")):
        png = case_json.with_suffix(".png")
        if case_json.name.endswith(".keypoints.json") or not png.exists():
            continue
        case = json.loads(case_json.read_text())
        kp = store.load("keypoints", resolve(store, "keypoints", None, str(png)))
        edits = oracle_edits(case, np.asarray(kp.arrays["points"]), np.asarray(kp.arrays["types"]), png.name,
                             a.types)
        for f in (case_json, png):
            link = a.out / f.name
            if not link.exists():
                os.symlink(f.resolve(), link)
        (a.out / f"{png.stem}.keypoints.json").write_text(json.dumps(edits))
        n += 1
    print(f"{n} cases with {'/'.join(a.types)} keypoints from their labels in {a.out}")


if __name__ == "__main__":
    main()
