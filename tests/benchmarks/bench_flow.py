"""Benchmark of the flow → select → export tail of the pipeline (the part a λ or δ sweep re-runs).

Usage::

    python tests/benchmarks/bench_flow.py [--cases NAME ...] [--paths 250] [--repeat 1] [--render OUT_DIR]

Cases (default: all available):

* ``many-paths``: a 500×714 synthetic drawing of ``--paths`` random smooth strokes 25–100 px long
  (so 33–133 flow vertices each at the default 0.75 px spacing), its real prep and field, and one
  candidate path per stroke: the stroke's centre line sampled every pixel with 0.4 px of noise, as
  the traced graph gives it;
* ``example``: the authors' pencil dog with the authors' keypoints (``../shared/data/authors_example``);
* three ``realvec_dev`` drawings with their ground-truth keypoints.

The real cases run prep → field → graph → topology once (cached as pickles under
``$TMPDIR/polyvec-bench-flow``, keyed by the image bytes, configs and stage sources).  Timed, per case:
the flow (best of ``--repeat``, after a warm-up that loads the compiled kernel), select, export, and a
λ re-run (``flow.lam`` halved: flow + select + export, what a sweep recomputes).  ``ns/v·it`` is the
wall flow time per vertex and iteration; ``cpu`` sums the kernel's threads (``NUMBA_NUM_THREADS``; the
engine's workers use 1).  ``--render`` writes PNGs (initial paths blue, flowed red, selected curves
coloured) over the drawing.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pickle
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import ROOT, source_hash, stage_cfg  # noqa: E402

SHARED = ROOT / ".." / "shared" / "data"
sys.path.insert(0, str(ROOT))

REALVEC = ["qd_dog_00_pencil", "cr_test_277_clean", "qd_giraffe_00_clean"]


_cfg = stage_cfg
_source_hash = source_hash


def _cached(name: str, data: bytes, cache: Path, build):
    stages = ROOT / "stages"
    names = ("prep", "field", "extension", "graph", "topology")
    cfgs = json.dumps([_cfg(s) for s in names], sort_keys=True).encode()
    src = _source_hash(*(stages / s for s in names)).encode()
    key = hashlib.sha1(data + cfgs + src).hexdigest()[:16]
    out = cache / f"{name}-{key}.pkl"
    if out.exists():
        return pickle.loads(out.read_bytes())
    t = time.perf_counter()
    arts = build()
    out.write_bytes(pickle.dumps(arts))
    print(f"  {name}: upstream stages {time.perf_counter() - t:.1f} s (cached)", file=sys.stderr)
    return arts


def _keypoints_artifact(kps):
    from stages.artifact import Artifact

    pts = np.array([(x, y) for x, y, _ in kps], np.float32).reshape(-1, 2)
    return Artifact(arrays={"points": pts, "types": np.array([t for *_, t in kps], np.int8),
                            "scores": np.ones(len(pts), np.float32)},
                    data={"points": [{"x": float(x), "y": float(y), "type": int(t), "score": 1.0} for x, y, t in kps]})


def _real_case(name: str, cache: Path) -> dict:
    from stages import extension, field, graph, prep, topology

    if name == "example":
        img = SHARED / "authors_example" / "example.png"
        lines = (SHARED / "authors_example" / "example.pts").read_text().split("\n")
        rows = [list(map(float, ln.split())) for ln in lines[1:1 + int(lines[0].split()[0])]]
        kps = [(c + 0.5, r + 0.5, int(t)) for r, c, t in rows]     # .pts is (row, col, type)
    else:
        img = SHARED / "realvec_dev" / f"{name}.png"
        d = json.loads((SHARED / "realvec_dev" / f"{name}.json").read_text())
        kps = ([(x, y, 1) for x, y in d["endpoints"]] + [(x, y, 3) for x, y in d["junctions"]]
               + [(x, y, 5) for x, y in d["corners"]])
    data = img.read_bytes()

    def build():
        p = prep.run(_cfg("prep"), image_bytes=data, image_name=img.name)
        f = field.run(_cfg("field"), prep=p)
        g = graph.run(_cfg("graph"), prep=p, field=f)
        k = _keypoints_artifact(kps)
        t = topology.run(_cfg("topology"), prep=p, field=f, graph=g, keypoints=k)
        e = extension.run(_cfg("extension"), prep=p, field=f)
        return {"prep": p, "extension": e, "graph": g, "topology": t}

    return _cached(name, data, cache, build)


def _many_paths_case(npaths: int, cache: Path, seed: int = 0) -> dict:
    from stages import extension, field, prep
    from stages.artifact import Artifact
    from stages.synthetic import Drawing, render

    rng = np.random.default_rng(seed)
    h, w = 714, 500
    strokes = []
    for _ in range(npaths):
        length = rng.uniform(25, 100)
        start = rng.uniform([20, 20], [w - 20, h - 20])
        ang0, bend = rng.uniform(0, 2 * np.pi), rng.uniform(-1.2, 1.2) / length
        s = np.linspace(0, length, int(length) + 1)
        ang = ang0 + bend * s
        pts = start + np.cumsum(np.stack([np.cos(ang), np.sin(ang)], 1), axis=0) - [np.cos(ang0), np.sin(ang0)]
        strokes.append(np.clip(pts, 2, [w - 2, h - 2]))
    drawing = Drawing(render((h, w), strokes, 3.0), strokes, 3.0)
    data = drawing.png_bytes()

    def build():
        p = prep.run(_cfg("prep"), image_bytes=data, image_name="many-paths.png")
        f = field.run(_cfg("field"), prep=p)
        paths = []
        for k, s in enumerate(strokes):
            xy = s + rng.normal(0, 0.4, s.shape) * np.r_[0, np.ones(len(s) - 2), 0][:, None]
            arc = np.r_[0, np.cumsum(np.hypot(*np.diff(xy, axis=0).T))]
            paths.append({"id": k, "component": k, "vertices": list(range(len(xy))), "xy": xy.tolist(),
                          "widths": [3.0] * len(xy), "interest_dist": np.minimum(arc, arc[-1] - arc).tolist(),
                          "end_types": [1, 1], "end_keypoints": [2 * k, 2 * k + 1], "through_keypoints": []})
        # Coverage: band pixels within 2 px of each path (what the topology stage would report).
        mask = p["mask"]
        cov = []
        for path in paths:
            xy = np.asarray(path["xy"])
            lo = np.maximum(np.floor(xy.min(0) - 3).astype(int), 0)
            hi = np.minimum(np.ceil(xy.max(0) + 3).astype(int), [w, h])
            jj, ii = np.meshgrid(np.arange(lo[0], hi[0]), np.arange(lo[1], hi[1]))
            c = np.stack([jj.ravel() + 0.5, ii.ravel() + 0.5], 1)
            near = np.sqrt(((c[:, None] - xy[None]) ** 2).sum(-1)).min(1) < 2.0
            sel = near & mask[ii.ravel(), jj.ravel()]
            cov.append((ii.ravel()[sel] * w + jj.ravel()[sel]).astype(np.int32))
        from stages.artifact import pack_ragged

        flat, off = pack_ragged(cov, np.int32)
        t = Artifact(arrays={"coverage": flat, "coverage_offsets": off}, data={"paths": paths, "key_vertices": []})
        e = extension.run(_cfg("extension"), prep=p, field=f)
        return {"prep": p, "extension": e, "graph": Artifact(), "topology": t}

    return _cached(f"many-paths-{npaths}-{seed}", data, cache, build)


def _render(arts: dict, fl, sel, out: Path, name: str) -> None:
    from PIL import Image, ImageDraw

    from stages.artifact import unpack_ragged

    grey = arts["prep"]["grey"]
    paths = arts["topology"].data["paths"]
    curves = unpack_ragged(fl["curve_xy"], fl["curve_xy_offsets"])
    chosen = set(sel.data["chosen"])
    sc = max(1, int(round(1200 / max(grey.shape))))
    base = (150 + np.clip(grey, 0, 1) * 105).astype(np.uint8)
    for tag in ("flow", "selected"):
        im = Image.fromarray(base).resize((grey.shape[1] * sc, grey.shape[0] * sc), Image.NEAREST).convert("RGB")
        dr = ImageDraw.Draw(im)
        for k, (p, c) in enumerate(zip(paths, curves)):
            if tag == "flow":
                dr.line([tuple(q * sc) for q in np.asarray(p["xy"])], fill=(90, 90, 255), width=1)
                dr.line([tuple(q * sc) for q in c], fill=(220, 0, 0), width=1)
            elif p["id"] in chosen:
                col = tuple(int(v) for v in np.random.default_rng(k).integers(0, 200, 3))
                dr.line([tuple(q * sc) for q in c], fill=col, width=2)
        im.save(out / f"{name}-{tag}.png")


def _bench(name: str, arts: dict, repeat: int, render: Path | None) -> dict:
    from stages import export, flow, select

    fcfg, scfg, ecfg = _cfg("flow"), _cfg("select"), _cfg("export")
    ins = {k: arts[k] for k in ("prep", "extension", "graph", "topology")}
    warm = dict(fcfg, iterations=1)
    flow.run(warm, **ins)                                  # load the compiled kernel
    best, cpu = np.inf, np.inf
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        fl = flow.run(fcfg, **ins)
        best, cpu = min(best, time.perf_counter() - t), min(cpu, time.process_time() - c)
    t = time.perf_counter()
    sel = select.run(scfg, prep=arts["prep"], topology=arts["topology"], flow=fl)
    t_sel = time.perf_counter() - t
    t = time.perf_counter()
    export.run(ecfg, prep=arts["prep"], topology=arts["topology"], flow=fl, select=sel)
    t_exp = time.perf_counter() - t
    t = time.perf_counter()
    fl2 = flow.run(dict(fcfg, lam=fcfg["lam"] / 2), **ins)
    sel2 = select.run(scfg, prep=arts["prep"], topology=arts["topology"], flow=fl2)
    export.run(ecfg, prep=arts["prep"], topology=arts["topology"], flow=fl2, select=sel2)
    t_rerun = time.perf_counter() - t
    nv = fl.data["n_vertices"]
    e0, e1 = np.array(fl.data["energies_initial"]), np.array(fl.data["energies"])
    if render is not None:
        render.mkdir(parents=True, exist_ok=True)
        _render(arts, fl, sel, render, name)
    return {"case": name, "shape": "x".join(map(str, arts["prep"]["grey"].shape)),
            "paths": len(arts["topology"].data["paths"]), "vertices": nv, "flow_s": best, "flow_cpu_s": cpu,
            "ns_per_vertex_iter": best / max(nv, 1) / fcfg["iterations"] * 1e9,
            "rejected_frac": fl.data["rejected_steps"] / max(1, len(e0) * fcfg["iterations"]),
            "energy_drop_median": float(np.median(1 - e1 / np.maximum(e0, 1e-300))) if len(e0) else 0.0,
            "select_s": t_sel, "select_status": sel.data["status"], "chosen": len(sel.data["chosen"]),
            "export_s": t_exp, "lambda_rerun_s": t_rerun}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="*", default=None)
    ap.add_argument("--paths", type=int, default=250)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--render", type=Path, default=None)
    args = ap.parse_args(argv)
    cache = Path(tempfile.gettempdir()) / "polyvec-bench-flow"
    cache.mkdir(exist_ok=True)
    names = args.cases or (["many-paths", "example"] + REALVEC)
    rows = []
    for name in names:
        if name == "many-paths":
            arts = _many_paths_case(args.paths, cache)
        else:
            if not SHARED.exists():
                print(f"  {name}: skipped (no ../shared/data)", file=sys.stderr)
                continue
            arts = _real_case(name, cache)
        rows.append(_bench(name, arts, args.repeat, args.render))
        r = rows[-1]
        print(f"{r['case']:>20} {r['shape']:>8} paths {r['paths']:4d} verts {r['vertices']:6d} "
              f"flow {r['flow_s']:6.2f} s (cpu {r['flow_cpu_s']:5.2f} s, {r['ns_per_vertex_iter']:5.1f} ns/v·it, "
              f"{100 * r['rejected_frac']:4.1f} % "
              f"rejected) | select {r['select_s']:5.2f} s [{r['select_status']}, {r['chosen']} chosen] | "
              f"export {r['export_s']:5.3f} s | λ re-run {r['lambda_rerun_s']:5.2f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
