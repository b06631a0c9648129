"""Speed and sanity of the evaluation metrics on the ground truth of realvec_dev (no pipeline run).

For every case: rasterise the GT strokes at the benchmark width and score them against the binarised
input (fidelity of a perfect vectorisation: what the best possible output would get), and extract
the GT topology and compare it with the dataset's keypoint labels. Prints medians and timings.

    python tests/benchmarks/bench_evaluate.py [--limit N]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from stages.config import from_section
from stages.evaluate.matching import match_one_to_one, prf1
from stages.evaluate.score import RasterParams, render_ink, score_raster
from stages.evaluate.curve_topology import TopologyParams, curve_topology

REPO = Path(__file__).resolve().parents[2]
DATA = REPO.parent / "shared" / "data" / "realvec_dev"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--limit", type=int, default=None)
    args = ap.parse_args()
    bcfg = yaml.safe_load((REPO / "conf" / "bench" / "default.yaml").read_text())
    rp = from_section(RasterParams, bcfg["raster"], "bench.raster")
    tp = from_section(TopologyParams, bcfg["topology"], "bench.topology")
    files = sorted(p for p in DATA.glob("*_*.json"))[: args.limit]
    rows, t_raster, t_topo = [], [], []
    for p in files:
        d = json.loads(p.read_text())
        grey = np.asarray(Image.open(p.with_suffix(".png")).convert("L"))
        strokes = [np.asarray(s, dtype=float) for s in d["strokes"]]
        t0 = time.perf_counter()
        ink = render_ink(strokes, grey.shape, rp)
        fid = score_raster(ink, grey < rp.ink_threshold, rp, prefix="fid_")
        t1 = time.perf_counter()
        topo = curve_topology(strokes, d["width"], tp)
        t2 = time.perf_counter()
        f1 = {}
        for name, mine, theirs in (("end", topo.free_ends, d["endpoints"]), ("junc", topo.junctions, d["junctions"])):
            theirs = np.asarray(theirs, dtype=float).reshape(-1, 2)
            m = len(match_one_to_one(mine, theirs, max(tp.match_min_px, d["width"])))
            f1[name] = prf1(m, len(mine) - m, len(theirs) - m)[2]
        rows.append({"style": d["style"], "width": d["width"], **fid, **f1, "gaps": len(topo.gaps),
                     "dup": topo.duplicated_length})
        t_raster.append(t1 - t0)
        t_topo.append(t2 - t1)
    print(f"{len(rows)} cases; raster metrics {np.median(t_raster) * 1e3:.0f} ms median "
          f"(max {max(t_raster) * 1e3:.0f}); topology {np.median(t_topo) * 1e3:.0f} ms median (max {max(t_topo) * 1e3:.0f})")
    for style in sorted({r["style"] for r in rows}):
        for w in sorted({r["width"] for r in rows}):
            rs = [r for r in rows if r["style"] == style and r["width"] == w]
            if not rs:
                continue
            med = {k: np.median([r[k] for r in rs]) for k in ("fid_chamfer", "fid_f1_2", "fid_f1_4", "fid_f1_2px", "end",
                                                                "junc", "gaps", "dup")}
            print(f"{style:6s} w={w:g} n={len(rs):2d} " + " ".join(f"{k}={v:.4g}" for k, v in med.items()))


if __name__ == "__main__":
    main()
