"""Quality of the complete vectorisation on realvec_dev (issue 6's targets), stages run in-process.

Usage::

    python tests/benchmarks/quality_realvec.py [--keypoints gt|detector] [--data DIR] [--cases PATTERN ...]
                                               [--limit N] [--procs 2] [--worst 12] [--json OUT]
                                               [--render DIR] [--no-cache]

For every case of ``../shared/data/realvec_dev`` (``<name>.png`` + ``<name>.json``) the stage functions
run in this process tree — prep → field → graph (→ keypoints) → topology → flow → select → export —
with the configs of ``conf/<stage>/default.yaml``, in a ``multiprocessing`` pool (``--procs``).
``--keypoints gt`` builds the keypoints artifact from the case JSON (endpoints → 1, junctions → 3,
corners → 5; zero heatmaps); ``--keypoints detector`` runs the keypoints stage (packaged weights).

Scores (:mod:`stages.evaluate`): Yan et al. raster metrics of the exported curves against the GT
strokes, both drawn with the benchmark's normalised thin stroke (F1 at 2 and 4 /1000 of the long
edge, F1 at 1 px, Chamfer, Hausdorff converted to px), and the valence topology (endpoint F1,
junction F1, short dangling branches per drawing) with the bench's tolerances
(``conf/bench/default.yaml``).  Prints medians and means overall and per style (clean / pencil), the
targets of issue 6, the topology errors broken down by what lies at them (:func:`error_breakdown`:
e.g. junctions where the ground truth has a corner), and the worst cases.

Every stage's artifact is cached under ``/tmp/polyvec-quality/<case>/<stage>-<key>.pkl``; the key
hashes the stage's source files, its config and the keys of its inputs, so editing a downstream stage
recomputes only that stage and what follows.
"""

from __future__ import annotations

import argparse
import fnmatch
import hashlib
import json
import math
import multiprocessing as mp
import os
import pickle
import sys
import time
import traceback
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT / ".." / "shared" / "data"
DATA = SHARED / "realvec_dev"
CACHE = Path(os.environ.get("POLYVEC_QUALITY_CACHE", "/tmp/polyvec-quality"))
sys.path.insert(0, str(ROOT))

from pipeline.engine.registry import STAGES as REGISTRY  # noqa: E402  (after the sys.path line)

# The DAG of pipeline.engine.registry without keypoint_edits: here the topology reads the keypoints directly.
STAGES = tuple(s.name for s in REGISTRY if s.name != "keypoint_edits")
INPUTS = {s.name: tuple("keypoints" if i == "keypoint_edits" else i for i in s.inputs)
          for s in REGISTRY if s.name != "keypoint_edits"}
SOURCES = {stage: [f"stages/{stage}"] for stage in STAGES}
KP_CODES = {"endpoints": 1, "junctions": 3, "corners": 5}
TARGETS = {"f1_2": (">=", 0.97), "hausdorff_px": ("<=", 3.0), "endpoint_f1": (">=", 0.9),
           "junction_f1": (">=", 0.85)}
COLUMNS = ["f1_2", "f1_4", "f1_1px", "chamfer_px", "hausdorff_px", "endpoint_f1", "junction_f1", "dangling",
           "curves", "gt_curves", "duplicated_px", "junction_gaps", "t_total"]


def load_cfg(stage: str) -> dict:
    """A stage's config section from ``conf/<stage>/default.yaml``."""
    import yaml

    return yaml.safe_load((ROOT / "conf" / stage / "default.yaml").read_text())


_HASHES: dict[str, str] = {}


def load_stages() -> None:
    """Import every stage's code and hash its source once, in this process.

    Pool workers fork from a process that already holds the code, so the cache keys always describe
    the code that runs, even when the sources change during a long run.
    """
    import importlib

    for stage in STAGES:
        importlib.import_module(f"stages.{stage}.stage")
        _HASHES[stage] = _source_hash(stage)


def _source_hash(stage: str) -> str:
    if stage in _HASHES:
        return _HASHES[stage]
    h = hashlib.sha1()
    for rel in SOURCES[stage]:
        p = ROOT / rel
        for f in sorted(p.rglob("*.py")) if p.is_dir() else [p]:
            h.update(f.read_bytes())
    if stage == "keypoints":  # the shipped model files are inputs too: their hashes are in STAGE_VERSION
        from stages.keypoints import STAGE_VERSION

        h.update(STAGE_VERSION.encode())
    return h.hexdigest()


def gt_keypoints(case: dict, shape: tuple[int, int]):
    """The keypoints artifact built from a case's ground truth (zero heatmaps)."""
    from stages.artifact import Artifact

    pts, types = [], []
    for name, code in KP_CODES.items():
        for x, y in np.asarray(case.get(name, []), np.float64).reshape(-1, 2):
            pts.append((x, y))
            types.append(code)
    points = np.asarray(pts, np.float32).reshape(-1, 2)
    types = np.asarray(types, np.int8)
    data = [{"x": float(p[0]), "y": float(p[1]), "type": int(t), "score": 1.0} for p, t in zip(points, types)]
    return Artifact(arrays={"heatmaps": np.zeros((4, *shape), np.float32), "points": points, "types": types,
                            "scores": np.ones(len(points), np.float32)},
                    data={"points": data, "weights": "ground truth", "count": len(data)})


def run_case(name: str, keypoints: str = "gt", use_cache: bool = True, image: Path | None = None,
             case: dict | None = None, pts: tuple | None = None) -> dict:
    """Run (or load) every stage for one case; returns the artifacts and per-stage seconds.

    ``image``/``case`` default to the realvec_dev files of ``name``; ``pts`` = (points (N, 2) x, y,
    types (N,)) overrides the keypoints (e.g. the authors' example.pts).
    """
    import importlib

    from stages.artifact import Artifact

    image = image or DATA / f"{name}.png"
    data = image.read_bytes()
    case = case if case is not None else json.loads((DATA / f"{name}.json").read_text())
    folder = CACHE / name
    folder.mkdir(parents=True, exist_ok=True)
    arts: dict[str, Artifact] = {}
    keys: dict[str, str] = {}
    times: dict[str, float] = {}
    for stage in STAGES:
        cfg = load_cfg(stage)
        h = hashlib.sha1(json.dumps(cfg, sort_keys=True).encode())
        h.update(stage.encode() + _source_hash(stage).encode())
        for s in INPUTS[stage]:
            h.update(keys[s].encode())
        if stage == "prep":
            h.update(hashlib.sha1(data).digest())
        if stage == "keypoints":
            h.update(keypoints.encode())
            if pts is not None:
                h.update(np.asarray(pts[0], np.float64).tobytes() + np.asarray(pts[1], np.int64).tobytes())
            elif keypoints == "gt":
                h.update(json.dumps({k: case.get(k) for k in KP_CODES}, sort_keys=True).encode())
        keys[stage] = h.hexdigest()[:16]
        path = folder / f"{stage}-{keys[stage]}.pkl"
        if use_cache and path.exists():
            try:
                arts[stage] = pickle.loads(path.read_bytes())
                times[stage] = 0.0
                continue
            except Exception:                                       # a torn file: recompute
                pass
        t = time.perf_counter()
        if stage == "prep":
            arts[stage] = importlib.import_module("stages.prep").run(cfg, image_bytes=data, image_name=image.name)
        elif stage == "keypoints" and (keypoints == "gt" or pts is not None):
            shape = arts["prep"]["grey"].shape
            if pts is not None:
                from stages.artifact import Artifact as A

                p, ty = np.asarray(pts[0], np.float32).reshape(-1, 2), np.asarray(pts[1], np.int8)
                arts[stage] = A(arrays={"heatmaps": np.zeros((4, *shape), np.float32), "points": p, "types": ty,
                                        "scores": np.ones(len(p), np.float32)}, data={"weights": "given"})
            else:
                arts[stage] = gt_keypoints(case, shape)
        else:
            mod = importlib.import_module(f"stages.{stage}")
            arts[stage] = mod.run(cfg, **{s: arts[s] for s in INPUTS[stage]})
        times[stage] = time.perf_counter() - t
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        tmp.write_bytes(pickle.dumps(arts[stage]))
        tmp.replace(path)
    return {"arts": arts, "times": times, "case": case}


def score_case(name: str, keypoints: str = "gt", use_cache: bool = True) -> dict:
    """One row of scores for a realvec_dev case (never raises: errors go into ``row['error']``)."""
    row: dict = {"name": name, "error": ""}
    try:
        from stages.config import from_section
        from stages.evaluate.curve_topology import TopologyParams, compare_topology, curve_topology
        from stages.evaluate.score import RasterParams, render_ink, score_raster

        res = run_case(name, keypoints, use_cache)
        case, arts = res["case"], res["arts"]
        bench = load_cfg("bench")
        rp = from_section(RasterParams, bench["raster"], "bench.raster")
        tp = from_section(TopologyParams, bench["topology"], "bench.topology")
        shape = arts["prep"]["grey"].shape
        long_edge = float(max(shape))
        row.update(style=case.get("style", ""), width=float(case["width"]), t_total=sum(res["times"].values()))
        row.update({f"t_{s}": v for s, v in res["times"].items()})
        curves = [np.asarray(c["points"], np.float64) for c in arts["export"].data["curves"]]
        strokes = [np.asarray(s, np.float64).reshape(-1, 2) for s in case["strokes"]]
        row["select_status"] = arts["select"].data.get("status", "")
        row["candidates"] = len(arts["topology"].data["paths"])
        if not curves:
            row["error"] = "no curves"
            return row
        m = score_raster(render_ink(curves, shape, rp), render_ink(strokes, shape, rp), rp)
        row.update({k: m[k] for k in m if k.startswith("f1_")})
        row["chamfer_px"] = m["chamfer"] * long_edge
        row["hausdorff_px"] = m["hausdorff"] * long_edge
        w = float(case["width"])
        topo_o, topo_g = curve_topology(curves, w, tp), curve_topology(strokes, w, tp)
        row.update(compare_topology(topo_o, topo_g, w, tp))
        row.update(error_breakdown(topo_o, topo_g, case, w, tp, np.asarray(arts["keypoints"]["points"]).reshape(-1, 2)))
    except Exception as e:                                          # one case must not sink the run
        row["error"] = f"{type(e).__name__}: {e}"
        row["traceback"] = traceback.format_exc()
    return row


ERROR_CLASSES = ("junction_fp", "endpoint_fp", "junction_fn", "endpoint_fn")


def error_breakdown(topo_o, topo_g, case: dict, width: float, tp, keypoints: np.ndarray) -> dict:
    """Unmatched junctions / free ends, each labelled by what lies within the matching radius.

    False positives (output points without a GT partner) get the GT keypoint types there
    (``E``/``J``/``C``, or ``-`` for none): a junction FP at ``C`` is a corner where three or more
    curve ends met, at ``E`` a stroke end that touches another curve.  False negatives (GT points
    without an output partner) get what the output has there: ``oJ`` junction, ``oC`` continuation,
    ``oF`` free end, ``-`` nothing.  Returned as ``err_<kind>_<label>`` counts, with three counts
    that separate the causes of junction errors (see the issue 6 notes):

    * ``cause_junction_fn_undetected`` — a missed GT junction with no input keypoint (``keypoints``,
      of any type) within the radius: the detector did not fire there;
    * ``cause_junction_fn_pair`` — a missed GT junction with an output junction within the radius
      that is matched to *another* GT junction: two GT junctions closer than the radius (a
      tangential merge next to a crossing, three strokes meeting) where the output, like the ink,
      has one;
    * ``cause_junction_fp_stops_short`` — a false output junction within the radius of a GT free
      end: the GT stroke stops just short of the other stroke (beyond the labelling radius
      max(2, w)) while the ink touches.
    """
    from stages.evaluate.matching import match_one_to_one

    radius = max(tp.match_min_px, width)
    kps = {t: np.asarray(case.get(k, []), np.float64).reshape(-1, 2)
           for k, t in (("endpoints", "E"), ("junctions", "J"), ("corners", "C"))}
    out_pts = {"oJ": topo_o.junctions, "oC": topo_o.continuations, "oF": topo_o.free_ends}

    def near(p, pts):
        return len(pts) > 0 and float(np.min(np.hypot(*(np.asarray(pts) - p).T))) <= radius

    counts: dict[str, int] = {"cause_junction_fn_undetected": 0, "cause_junction_fn_pair": 0,
                              "cause_junction_fp_stops_short": 0}
    for kind, a, b in (("junction", topo_o.junctions, topo_g.junctions), ("endpoint", topo_o.free_ends,
                                                                          topo_g.free_ends)):
        m = match_one_to_one(a, b, radius)
        for i in np.setdiff1d(np.arange(len(a)), m[:, 0]):
            lab = "".join(t for t, pts in kps.items() if near(a[i], pts)) or "-"
            counts[f"err_{kind}_fp_{lab}"] = counts.get(f"err_{kind}_fp_{lab}", 0) + 1
            if kind == "junction":
                counts["cause_junction_fp_stops_short"] += int(near(a[i], topo_g.free_ends))
        for j in np.setdiff1d(np.arange(len(b)), m[:, 1]):
            lab = "".join(t for t, pts in out_pts.items() if near(b[j], pts)) or "-"
            counts[f"err_{kind}_fn_{lab}"] = counts.get(f"err_{kind}_fn_{lab}", 0) + 1
            if kind == "junction":
                counts["cause_junction_fn_undetected"] += int(not near(b[j], keypoints))
                counts["cause_junction_fn_pair"] += int(near(b[j], a[m[:, 0]]))
    return counts


def _worker(args):
    import numba

    numba.set_num_threads(1)
    return score_case(*args)


def _stat(rows: list[dict], col: str) -> tuple[float, float, int]:
    v = np.array([r[col] for r in rows if isinstance(r.get(col), (int, float)) and math.isfinite(r[col])], float)
    if not len(v):
        return math.nan, math.nan, 0
    return float(np.median(v)), float(v.mean()), len(v)


def summary(rows: list[dict]) -> dict:
    """Median / mean per column, overall and per style."""
    groups = {"all": rows}
    for r in rows:
        groups.setdefault(r.get("style") or "?", []).append(r)
    return {g: {"cases": len(rs), "failures": sum(bool(r["error"]) for r in rs),
                **{c: _stat(rs, c) for c in COLUMNS}} for g, rs in groups.items()}


def print_report(rows: list[dict], worst: int) -> None:
    summ = summary(rows)
    print(f"\n{'column':<14}" + "".join(f"{g + ' (' + str(s['cases']) + ')':>24}" for g, s in summ.items()))
    print(f"{'':<14}" + "".join(f"{'median':>12}{'mean':>12}" for _ in summ))
    for c in COLUMNS:
        print(f"{c:<14}" + "".join(f"{s[c][0]:>12.4f}{s[c][1]:>12.4f}" for s in summ.values()))
    print("failures: " + ", ".join(f"{g} {s['failures']}" for g, s in summ.items()))
    a = summ["all"]
    print("\ntargets (medians over all cases; dangling = mean per drawing):")
    for col, (op, val) in TARGETS.items():
        got = a[col][0]
        ok = got >= val if op == ">=" else got <= val
        print(f"  {col:<14} {got:8.4f} {op} {val:<6} {'ok' if ok else 'MISSED'}")
    got = a["dangling"][1]
    print(f"  {'dangling':<14} {got:8.4f} <= 0.2    {'ok' if got <= 0.2 else 'MISSED'}")
    for err in [r for r in rows if r["error"]]:
        print(f"  ERROR {err['name']}: {err['error']}")
    tot: dict[str, int] = {}
    for r in rows:
        for k, v in r.items():
            if k.startswith("err_"):
                tot[k] = tot.get(k, 0) + v
    print("\ntopology errors by what lies there (FP: GT keypoints E/J/C; FN: output oJ/oC/oF; - none):")
    for kind in ERROR_CLASSES:
        items = sorted(((v, k[len(f"err_{kind}_"):]) for k, v in tot.items() if k.startswith(f"err_{kind}_")),
                       reverse=True)
        print(f"  {kind:<12} " + ", ".join(f"{lab} {v}" for v, lab in items))
    causes = {k: sum(r.get(k, 0) for r in rows) for k in
              ("cause_junction_fn_undetected", "cause_junction_fn_pair", "cause_junction_fp_stops_short")}
    print("junction errors by cause (error_breakdown): missed with no input keypoint near "
          f"{causes['cause_junction_fn_undetected']}, missed beside a GT junction the output matched "
          f"{causes['cause_junction_fn_pair']}; false at a GT free end {causes['cause_junction_fp_stops_short']}")
    ok = [r for r in rows if not r["error"]]
    for col, rev in (("f1_2", False), ("hausdorff_px", True), ("endpoint_f1", False), ("junction_f1", False),
                     ("dangling", True)):
        srt = sorted(ok, key=lambda r: (r.get(col, math.nan) if not rev else -r.get(col, math.nan)))
        print(f"\nworst by {col}: " + ", ".join(f"{r['name']}={r.get(col, math.nan):.3f}" for r in srt[:worst]))


def render_case(name: str, out: Path, keypoints: str = "gt", scale: int = 2, crops: int = 3,
                crop_px: int = 48, crop_scale: int = 8, regions: list | None = None, suffix: str = "") -> Path:
    """Error picture of one case, written as PNG.

    Left: the curves (colours, ends as dots) over the input with the GT strokes (thin grey); the
    input keypoints as crosses (endpoints blue, junctions orange, corners green); the scored topology
    of the ground truth as rings and of the output as squares (free ends blue, junctions orange).  Right: the benchmark's thin-stroke rasters — output ink
    farther than τ (2/1000 of the long edge) from the GT ink in red (precision misses), GT ink farther
    than τ from the output in blue (recall misses), agreement in grey.  Below: ``crops`` zooms
    (``crop_px`` square, ``crop_scale``×) on the largest clusters of misses, or on ``regions``
    (``(x0, y0)`` top-left corners) when given; then only the zooms are drawn.
    """
    from PIL import Image
    from scipy import ndimage
    from skimage.draw import circle_perimeter, disk, line_aa

    from stages.config import from_section
    from stages.evaluate.score import RasterParams, render_ink

    res = run_case(name, keypoints)
    arts, case = res["arts"], res["case"]
    grey = np.asarray(arts["prep"]["grey"], np.float32)
    h, w = grey.shape
    curves = [np.asarray(c["points"], float) for c in arts["export"].data["curves"]]
    strokes = [np.asarray(s, float).reshape(-1, 2) for s in case.get("strokes", [])]
    rp = from_section(RasterParams, load_cfg("bench")["raster"], "bench.raster")
    ink_o, ink_g = render_ink(curves, (h, w), rp), render_ink(strokes, (h, w), rp)
    tau = 2 * max(h, w) / 1000
    fp = ink_o & (ndimage.distance_transform_edt(~ink_g) > tau)
    fn = ink_g & (ndimage.distance_transform_edt(~ink_o) > tau)
    err = np.ones((h, w, 3))
    err[ink_g | ink_o] = 0.6
    err[fp] = (1.0, 0.0, 0.0)
    err[fn] = (0.0, 0.3, 1.0)
    kp = arts["keypoints"]
    kps = list(zip(np.asarray(kp["points"]).reshape(-1, 2), np.asarray(kp["types"]).ravel()))
    colours = {1: (0.1, 0.3, 1.0), 3: (1.0, 0.55, 0.0), 5: (0.0, 0.7, 0.2)}
    from stages.config import from_section
    from stages.evaluate.curve_topology import TopologyParams, curve_topology

    tp = from_section(TopologyParams, load_cfg("bench")["topology"], "bench.topology")
    wd = float(case.get("width", 3.0))
    topo_o, topo_g = curve_topology(curves, wd, tp), curve_topology(strokes, wd, tp)

    def picture(x0, y0, cw, ch, sc):
        img = np.repeat((0.6 + 0.4 * np.kron(grey[y0:y0 + ch, x0:x0 + cw], np.ones((sc, sc))))[..., None], 3, 2)
        rng = np.random.default_rng(0)
        off = np.array([x0, y0], float)

        def draw(p, col, alpha=1.0):
            p = (np.asarray(p, float) - off) * sc
            for a, b in zip(p[:-1], p[1:]):
                rr, cc, v = line_aa(int(round(a[1])), int(round(a[0])), int(round(b[1])), int(round(b[0])))
                k = (rr >= 0) & (rr < ch * sc) & (cc >= 0) & (cc < cw * sc)
                img[rr[k], cc[k]] = img[rr[k], cc[k]] * (1 - alpha * v[k, None]) + alpha * v[k, None] * np.array(col)

        for s in strokes:
            draw(s, (0.35, 0.35, 0.35), 0.6)
        for c in curves:
            col = rng.uniform(0.1, 0.9, 3)
            col[rng.integers(3)] = 0.0
            draw(c, col)
            for e in (c[0], c[-1]):
                rr, cc = disk(((e[1] - y0) * sc, (e[0] - x0) * sc), max(1.5, 0.25 * sc), shape=img.shape[:2])
                img[rr, cc] = col
        r = max(3, int(1.5 * sc))
        for (x, y), t in kps:
            cy, cx = int((y - y0) * sc), int((x - x0) * sc)
            for d in range(-r // 2, r // 2 + 1):
                for yy, xx in ((cy + d, cx + d), (cy + d, cx - d)):
                    if 0 <= yy < img.shape[0] and 0 <= xx < img.shape[1]:
                        img[yy, xx] = colours.get(int(t), (1, 0, 1))
        for pts, t in ((topo_g.free_ends, 1), (topo_g.junctions, 3)):
            for x, y in pts:
                for rad in (r + 2, r + 3):
                    rr, cc = circle_perimeter(int((y - y0) * sc), int((x - x0) * sc), rad, shape=img.shape[:2])
                    img[rr, cc] = colours[t]
        for pts, t in ((topo_o.free_ends, 1), (topo_o.junctions, 3)):
            for x, y in pts:
                cy, cx = int((y - y0) * sc), int((x - x0) * sc)
                yy, xx = np.mgrid[cy - r:cy + r + 1, cx - r:cx + r + 1]
                ring = (np.maximum(abs(yy - cy), abs(xx - cx)) >= r - 1)
                ok = ring & (yy >= 0) & (yy < img.shape[0]) & (xx >= 0) & (xx < img.shape[1])
                img[yy[ok], xx[ok]] = colours[t]
        return img

    if regions:
        tiles = [picture(int(x0), int(y0), crop_px, crop_px, crop_scale) for x0, y0 in regions]
        out.mkdir(parents=True, exist_ok=True)
        path = out / f"{name}{suffix}-zoom.png"
        Image.fromarray((np.clip(np.concatenate(tiles, 1), 0, 1) * 255).astype(np.uint8)).save(path)
        return path
    top = np.concatenate([picture(0, 0, w, h, scale), np.kron(err, np.ones((scale, scale, 1)))], axis=1)
    rows = [top]
    lab, n = ndimage.label(ndimage.binary_dilation(fp | fn, iterations=3))
    if n:
        sizes = ndimage.sum(fp | fn, lab, np.arange(1, n + 1))
        tiles = []
        for k in np.argsort(-sizes)[:crops]:
            cy, cx = ndimage.center_of_mass(lab == k + 1)
            x0 = int(np.clip(cx - crop_px / 2, 0, w - crop_px))
            y0 = int(np.clip(cy - crop_px / 2, 0, h - crop_px))
            tiles.append(picture(x0, y0, crop_px, crop_px, crop_scale))
        strip = np.ones((crop_px * crop_scale, top.shape[1], 3))
        x = 0
        for t in tiles:
            if x + t.shape[1] > strip.shape[1]:
                break
            strip[:, x:x + t.shape[1]] = t
            x += t.shape[1] + 8
        rows.append(strip)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}{suffix}.png"
    Image.fromarray((np.clip(np.concatenate(rows, 0), 0, 1) * 255).astype(np.uint8)).save(path)
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--keypoints", choices=("gt", "detector"), default="gt")
    ap.add_argument("--cases", nargs="*", default=["*"], help="name patterns (fnmatch)")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--procs", type=int, default=2)
    ap.add_argument("--worst", type=int, default=10)
    ap.add_argument("--json", type=Path, default=None, help="write the per-case rows here")
    ap.add_argument("--render", type=Path, default=None, help="render the worst cases (by f1_2) into this folder")
    ap.add_argument("--no-cache", action="store_true")
    ap.add_argument("--data", type=Path, default=None,
                    help="a folder of realvec-style cases instead of realvec_dev (e.g. the validation split "
                         "written by `python -m pipeline.validation_cases`)")
    args = ap.parse_args(argv)
    global DATA
    if args.data is not None:
        DATA = args.data
    if not DATA.is_dir():
        print(f"{DATA} not found (../shared is absent)", file=sys.stderr)
        return 2
    names = sorted(p.stem for p in DATA.glob("*.json") if p.with_suffix(".png").is_file())
    names = [n for n in names if any(fnmatch.fnmatch(n, pat) for pat in args.cases)][:args.limit]
    t0 = time.perf_counter()
    load_stages()
    jobs = [(n, args.keypoints, not args.no_cache) for n in names]
    if args.procs > 1:
        with mp.get_context("fork").Pool(args.procs, maxtasksperchild=8) as pool:
            rows = []
            for k, r in enumerate(pool.imap_unordered(_worker, jobs), 1):
                rows.append(r)
                print(f"\r{k}/{len(jobs)} {r['name']:<40}", end="", file=sys.stderr, flush=True)
    else:
        rows = [_worker(j) for j in jobs]
    print(f"\n{len(rows)} cases in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    rows.sort(key=lambda r: r["name"])
    print_report(rows, args.worst)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=float))
    if args.render:
        ok = sorted((r for r in rows if not r["error"]), key=lambda r: r.get("f1_2", 0))
        for r in ok[:args.worst]:
            print("rendered", render_case(r["name"], args.render, args.keypoints))
    return 0


if __name__ == "__main__":
    sys.exit(main())
