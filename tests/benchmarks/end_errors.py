"""Benchmark helper: the acceptance scorer's missed and false endpoints, classed by what lies there (not a test).

Usage::

    polyvec CASES output=OUT store.path=STORE
    python tests/benchmarks/end_errors.py OUT CASES STORE [--json errors.json]

The free ends are the acceptance scorer's own (``../shared/tools/score.py``, ``topology``, run as it
is), ground truth and output matched one to one within max(5, w) px as ``match_f1`` does (the greedy
matching of :mod:`junction_errors`).  Each false end (output, unmatched) is classed by

- ``spur``: its curve is shorter than 3 r (the scorer's spurious branch), r = max(2, w);
- ``off``: no ground-truth stroke within the tolerance (ink the truth does not draw);
- ``at-junc``: a ground-truth junction within 2 r (a curve stopping at, or short of, a meeting);
- ``break``: another false output end within 4 r (a stroke broken in two, the pieces facing);
- ``short``: a missed ground-truth end within 4 r (the curve stops short of the stroke's real end);
- ``mid``: anything else on a stroke (a curve ends in the middle of a stroke, nothing facing it);

and each missed end (ground truth, unmatched) by

- ``stops-short``: an output curve end (free or not) within 4 r: the output stops before it (or the
  end there is not free);
- ``passes``: an output curve comes within r but no output end does (the curve goes on: the stroke's
  end is joined into something);
- ``lost``: nothing of the output within r (the stroke's tip is not drawn);

each with the nearest detected keypoint's type within 5 px (the image's newest ``keypoints`` artifact
in ``STORE``), or ``none``.  For each class the table gives its count and the endpoint F1 median /
mean over the cases if that class alone were right.  Use it on a validation split; never to choose on
the set you report.
"""

from __future__ import annotations

import collections
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from junction_errors import command_line, keypoint_type, near, print_table, scored_cases, scorer, unmatched  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    a = command_line(argv, __doc__, "end")
    S = scorer()
    counts: dict[str, collections.Counter] = {}
    totals = collections.Counter()
    rows = []
    for case in scored_cases(a):
        strokes, r, tol, points, types = case.strokes, case.r, case.tol, case.points, case.types
        curves = [c for c in case.curves if len(c) >= 2]
        ge, gj, _, _ = S.topology(strokes, r)
        oe, _, _, _ = S.topology(curves, r)
        gt_pts = np.concatenate(strokes)
        out_pts = np.concatenate(curves) if curves else np.zeros((0, 2))
        out_ends = np.array([c[k] for c in curves for k in (0, -1)]).reshape(-1, 2)
        missed, false = unmatched(oe, ge, tol)
        c = counts.setdefault(case.stem, collections.Counter())
        c["_matched"] = int((~missed).sum())
        for p in oe[false]:
            curve = min(curves, key=lambda q: min(np.linalg.norm(q[[0, -1]] - p, axis=1)))
            others = oe[false][np.linalg.norm(oe[false] - p, axis=1) > 1e-9]
            if len(curve) * 0.5 < 3 * r:
                kind = "spur"
            elif not near(gt_pts, p, tol):
                kind = "off"
            elif near(gj, p, 2 * r):
                kind = "at-junc"
            elif near(others, p, 4 * r):
                kind = "break"
            elif near(ge[missed], p, 4 * r):
                kind = "short"
            else:
                kind = "mid"
            cls = f"false {kind} kp={keypoint_type(p, points, types)}"
            c[cls] += 1
            rows.append({"case": case.stem, "class": cls, "x": float(p[0]), "y": float(p[1])})
        for p in ge[missed]:
            d_end = float(np.linalg.norm(out_ends - p, axis=1).min()) if len(out_ends) else np.inf
            if d_end <= 4 * r:
                kind = "stops-short"
            elif near(out_pts, p, r):
                kind = "passes"
            else:
                kind = "lost"
            cls = f"missed {kind} kp={keypoint_type(p, points, types)}"
            c[cls] += 1
            rows.append({"case": case.stem, "class": cls, "x": float(p[0]), "y": float(p[1]),
                         "nearest_out_end": d_end})
        totals.update(truth=len(ge), output=len(oe), matched=int((~missed).sum()))

    print_table(counts, totals, "end", a.cases, rows, a.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
