"""``polyvec-bench``: run the pipeline over folders of cases and score it (shared/reference/metrics.md).

Examples
--------
``polyvec-bench bench.cases=[../shared/data/realvec_dev] bench.out=bench_out``
``polyvec-bench bench.cases=[../shared/data/realvec_dev,../shared/data/drawings] bench.limit=10``
``polyvec-bench bench.cases=[scans/] flow.lam=0.1 bench.run_pipeline=false``  (score the store only)

Cases
-----
- **Ground-truth case**: ``<name>.png`` with ``<name>.json`` holding ``strokes`` (polylines, x right,
  y down, pixels), ``width``, ``style`` and optionally ``endpoints``, ``junctions``, ``corners`` (the
  realvec_dev format). Scored against the strokes (raster metrics, topology F1), the keypoints, and
  for fidelity to the input.
- **Plain image** (no such JSON): fidelity to the binarised input and topology counts only.

Every image runs through :func:`pipeline.engine.execute.batch.run_batch` (the same store and cache as ``polyvec``);
whatever stages exist are scored: without an ``export`` stage, the curves come from ``select`` +
``flow``; without those, only keypoints and timings are reported.

Writes into ``bench.out``: ``cases.json`` and ``cases.csv`` (one row per case), ``summary.json``
(medians, means, failures, per group), ``report.html`` with ``img/<case>.png`` (worst cases first),
and prints the summary tables. Exit status: 0, or 1 when any case failed, 2 on a usage error.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from pipeline.bench_report import case_picture, pick_sort_column, print_tables, safe_name, sort_key, write_report
from pipeline.engine.execute.base import BatchResult, TaskResult
from pipeline.engine.execute.batch import run_batch
from pipeline.engine.plan import plan
from pipeline.engine.store import ArtifactStore
from pipeline.hydra_command import ExitCode, UsageError, hydra_app, multirun_folder
from pipeline.inputs import IMAGE_SUFFIXES
from stages.config import from_section
from stages.evaluate import BenchConfig, RasterParams, TopologyParams

KEYPOINT_CLASSES = {"endpoints": 1, "junctions": 3, "corners": 5}


@dataclass
class Case:
    """One image to score.

    Attributes
    ----------
    name : str
        Path of the image relative to the folder it was found in, without suffix.
    image : Path
    dataset : str
        Name of the folder given on the command line.
    style : str
        ``style`` of the case JSON, else the image's sub-folder (clean / rough / scanned ...).
    width : float or None
        Stroke width of the drawing in pixels (ground-truth cases).
    strokes : list of numpy.ndarray or None
        Ground-truth strokes (x, y); None for a plain image.
    keypoints : dict or None
        Class code (1, 3, 5) → (k, 2) ground-truth keypoints (x, y).
    """

    name: str
    image: Path
    dataset: str
    style: str
    width: float | None = None
    strokes: list[np.ndarray] | None = None
    keypoints: dict[int, np.ndarray] | None = None
    meta: dict = field(default_factory=dict)

    @property
    def group(self) -> str:
        return f"{self.dataset}:{self.style}" if self.style else self.dataset


# -- cases -------------------------------------------------------------------------------------
def _case_json(image: Path) -> dict | None:
    js = image.with_suffix(".json")
    if not js.is_file():
        return None
    try:
        d = json.loads(js.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return d if isinstance(d, dict) and isinstance(d.get("strokes"), list) else None


def load_case(image: Path, root: Path | None = None, dataset: str = "") -> Case:
    """A :class:`Case` for one image, with ground truth when a case JSON sits beside it."""
    root = root or image.parent
    rel = image.relative_to(root) if image.is_relative_to(root) else Path(image.name)
    name = str(rel.with_suffix(""))
    sub = rel.parent.name
    d = _case_json(image)
    if d is None:
        return Case(name=name, image=image, dataset=dataset or root.name, style=sub)
    strokes = [np.asarray(s, dtype=np.float64).reshape(-1, 2) for s in d["strokes"]]
    kps = {code: np.asarray(d[k], dtype=np.float64).reshape(-1, 2) for k, code in KEYPOINT_CLASSES.items() if k in d}
    return Case(name=name, image=image, dataset=dataset or root.name, style=str(d.get("style", sub) or sub),
                width=float(d["width"]) if d.get("width") is not None else None, strokes=strokes,
                keypoints=kps or None, meta={k: d[k] for k in ("source", "licence") if k in d})


def discover_cases(specs: list[str], limit: int | None = None) -> list[Case]:
    """Cases named by ``bench.cases``: folders (searched recursively for images) or image files."""
    cases: list[Case] = []
    for spec in specs:
        p = Path(str(spec)).expanduser()
        if p.is_dir():
            root = p.resolve()
            images = sorted(q for q in root.rglob("*") if q.is_file() and q.suffix.lower() in IMAGE_SUFFIXES)
            if not images:
                raise UsageError(f"no images in folder {spec}")
            cases.extend(load_case(q, root, root.name) for q in images)
        elif p.is_file():
            cases.append(load_case(p.resolve(), p.resolve().parent, p.resolve().parent.name))
        else:
            raise UsageError(f"case folder or image not found: {spec}")
    if not cases:
        raise UsageError("no cases: give bench.cases=[FOLDER,...]")
    if limit is not None:
        cases = cases[: int(limit)]
    return cases


def load_grey(path: Path) -> np.ndarray:
    """8-bit grey of an image file (PIL ``L``), transparent pixels composited over white first.

    The benchmark drops alpha (metrics.md §2.2); inputs such as the authors' RGBA example draw on a
    transparent background, so fidelity needs the composite.
    """
    from PIL import Image, ImageOps

    with Image.open(path) as im:
        im.load()
        im = ImageOps.exif_transpose(im)   # upright, as the prep stage reads it
        if im.mode in ("RGBA", "LA", "PA") or (im.mode == "P" and "transparency" in im.info):
            rgba = im.convert("RGBA")
            bg = Image.new("RGBA", rgba.size, (255, 255, 255, 255))
            im = Image.alpha_composite(bg, rgba)
        return np.asarray(im.convert("L"))


# -- artifacts ---------------------------------------------------------------------------------
def stored_keys(images: list[Path], cfg: Any, store: ArtifactStore) -> BatchResult:
    """What a batch would produce, from the store only (``bench.run_pipeline=false``)."""
    from pipeline.engine.registry import active_stages

    stages = active_stages(cfg.runtime.get("until"))
    batch = BatchResult(stages=[s.name for s in stages])
    for tasks in plan(images, cfg, stages):
        per = batch.results.setdefault(tasks[0].image, {})
        for t in tasks:
            status = "cached" if store.exists(t.stage, t.key) else "skipped"
            per[t.stage] = TaskResult(t.image, t.stage, t.key, status,
                                      error=None if status == "cached" else "not in the store")
    return batch


def final_curves(store: ArtifactStore, keys: dict[str, str]) -> tuple[list[np.ndarray] | None, str]:
    """The output curves of an image and where they came from (``export``, ``select+flow`` or ``none``)."""
    if "export" in keys:
        art = store.load("export", keys["export"])
        return [np.asarray(c["points"], dtype=np.float64).reshape(-1, 2) for c in art.data.get("curves", [])], "export"
    if "select" in keys and "flow" in keys:
        from stages.artifact import unpack_ragged

        flow = store.load("flow", keys["flow"])
        chosen = store.load("select", keys["select"]).data.get("chosen", [])
        curves = unpack_ragged(flow.arrays["curve_xy"], flow.arrays["curve_xy_offsets"])
        ids = None
        if "topology" in keys:  # chosen are path ids; flow curves are in topology path order
            paths = store.load("topology", keys["topology"]).data.get("paths", [])
            ids = {int(p["id"]): k for k, p in enumerate(paths)}
        out = []
        for c in chosen:
            k = ids.get(int(c)) if ids is not None else int(c)
            if k is not None and 0 <= k < len(curves):
                out.append(np.asarray(curves[k], dtype=np.float64).reshape(-1, 2))
        return out, "select+flow"
    return None, "none"


def predicted_keypoints(store: ArtifactStore, keys: dict[str, str]) -> tuple[np.ndarray, np.ndarray] | None:
    """(points (n, 2) in (x, y) of the drawing's pixels, types (n,)) of the keypoints artifact, or None."""
    if "keypoints" not in keys:
        return None
    art = store.load("keypoints", keys["keypoints"])
    # A supersampled, downsampled or cropped prep puts the keypoints at `scale` × (the drawing's pixels − origin).
    from stages.prep import to_source

    pts = to_source(art.arrays.get("points", np.zeros((0, 2))), art.data)
    types = np.asarray(art.arrays.get("types", np.zeros(0)), dtype=np.int64).reshape(-1)
    return pts, types


_KP_NAMES = {1: "end", 3: "junc", 5: "corner"}  # keypoint codes in the column names


def score_keypoints(pred: tuple[np.ndarray, np.ndarray], gt: dict[int, np.ndarray], height: int,
                    kcfg: dict) -> dict:
    """Keypoint metrics (metrics.md §3) via :mod:`stages.evaluate.keypoints`.

    ``kp_f1`` is the authors' F1 with every class pooled (radius ``radius_height_fraction`` x the image
    height; the authors use their padded network input's height, a few pixels more), ``kp_f1_end``,
    ``kp_f1_junc``, ``kp_f1_corner`` the same per class; ``kp_f1_1to1`` (with precision and recall)
    the one-to-one F1 within ``one_to_one_radius_px``, ``kp_class_acc`` the classification accuracy on
    the matched points, ``kp_f1_1to1_<class>`` the one-to-one F1 per class.
    """
    from stages.evaluate.keypoints import f1_authors, f1_authors_per_class, match_keypoints

    names = _KP_NAMES
    gt_pts = np.concatenate([gt.get(t, np.zeros((0, 2))) for t in names]).reshape(-1, 2)
    gt_types = np.concatenate([np.full(len(gt.get(t, ())), t) for t in names]).astype(np.int64)
    pts, types = pred
    rel = float(kcfg["radius_height_fraction"])
    row = {"kp_f1": f1_authors(gt_pts, pts, height, rel)}
    for t, f in f1_authors_per_class(gt_pts, gt_types, pts, types, height, rel).items():
        row[f"kp_f1_{names[t]}"] = f
    m = match_keypoints(gt_pts, gt_types, pts, types, float(kcfg["one_to_one_radius_px"]))
    row.update(kp_f1_1to1=m.f1, kp_precision_1to1=m.precision, kp_recall_1to1=m.recall,
               kp_class_acc=m.accuracy if m.tp else float("nan"),
               kp_tp=m.tp, kp_fp=m.fp, kp_fn=m.fn, kp_correct_type=m.correct_type)
    for t in names:
        # A class absent from both the ground truth and the output has no F1 (not 0).
        row[f"kp_f1_1to1_{names[t]}"] = m.class_f1(t) if sum(m.per_class[t]) else float("nan")
        row[f"kp_{names[t]}_tp"], row[f"kp_{names[t]}_fp"], row[f"kp_{names[t]}_fn"] = m.per_class[t]
    return row


def pooled_keypoints(rows: list[dict]) -> list[dict]:
    """Keypoint figures pooled over all points of each group (and of all cases): one-to-one detection
    F1, class accuracy, and class F1 per type (endpoint, junction, corner) — as ``pipeline.eval_keypoints``
    reports them. Per-drawing class F1 is noisy (a drawing has a handful of corners), so these are
    the figures the keypoint targets are stated in.
    """
    from stages.evaluate.keypoints import TYPES, MatchResult

    names = _KP_NAMES
    scored = [r for r in rows if "kp_tp" in r]
    groups = [("all", scored)] + [(g, [r for r in scored if r.get("group") == g])
                                  for g in sorted({r.get("group") for r in scored if r.get("group")})]
    out = []
    for g, rr in groups:
        if not rr:
            continue
        m = MatchResult()
        for r in rr:
            m = m + MatchResult(r["kp_tp"], r["kp_fp"], r["kp_fn"], r["kp_correct_type"],
                                {t: [r[f"kp_{names[t]}_{k}"] for k in ("tp", "fp", "fn")] for t in TYPES})
        figures = {"kp_f1_1to1": m.f1, "kp_class_acc": m.accuracy,
                   **{f"kp_f1_1to1_{names[t]}": m.class_f1(t) for t in TYPES}}
        out.append({"group": g, "cases": len(rr), "failures": 0,
                    **{k: {"median": v, "mean": v, "n": len(rr), "pooled": True} for k, v in figures.items()}})
    return out


# -- scoring one case ----------------------------------------------------------------------------
def score_case(case: Case, batch: BatchResult, store: ArtifactStore, bcfg: dict) -> tuple[dict, dict]:
    """One row of metrics for a case, and what its picture needs.

    Returns
    -------
    (dict, dict)
        The row (flat, JSON-friendly) and picture data (grey, curves, markers).
    """
    from stages.evaluate.curve_topology import compare_topology, curve_topology
    from stages.evaluate.score import (estimate_stroke_width, fidelity_reference, gt_scale, render_ink, score_raster,
                                       stage_timings)

    rparams = from_section(RasterParams, bcfg["raster"], "bench.raster")
    tparams = from_section(TopologyParams, bcfg["topology"], "bench.topology")
    image = str(case.image)
    per = batch.results.get(image, {})
    keys = batch.keys(image)
    row: dict[str, Any] = {"name": case.name, "dataset": case.dataset, "style": case.style, "group": case.group,
                           "image": image, "has_gt": case.strokes is not None, "error": ""}
    for stage in batch.stages:
        r = per.get(stage)
        if r is not None and r.status in ("failed", "skipped") and not row["error"]:
            row["error"] = f"{stage}: {r.error}"
    row.update(stage_timings({s: store.manifest(s, keys[s]) for s in batch.stages if s in keys}))

    grey = load_grey(case.image)
    shape = grey.shape
    input_ink = grey.astype(np.float64) < rparams.ink_threshold
    width = case.width if case.width is not None else estimate_stroke_width(input_ink)
    row["width"] = round(float(width), 3)
    pic: dict[str, Any] = {"grey": grey, "curves": None, "markers": {}, "gt": None, "keypoints": None,
                           "gt_keypoints": None}

    curves, source = final_curves(store, keys)
    row["curves_from"] = source
    expects_curves = "export" in batch.stages or "select" in batch.stages
    if curves is not None:
        pic["curves"] = curves
        ink = render_ink(curves, shape, rparams)
        fid = score_raster(ink, fidelity_reference(input_ink, rparams), rparams, prefix="fid_")
        row.update({k: v for k, v in fid.items() if k != "fid_blank"})
        if case.strokes is not None:
            scale = gt_scale(shape, rparams)        # the benchmark's long edge (1000 px)
            gt_ink = render_ink(case.strokes, shape, rparams, scale)
            out_ink = render_ink(curves, shape, rparams, scale)
            row.update({k: v for k, v in score_raster(out_ink, gt_ink, rparams, scale=scale).items() if k != "blank"})
        if fid["fid_blank"] and not row["error"]:
            row["error"] = "blank output (no ink after rasterising the curves)"
        topo = curve_topology(curves, width, tparams)
        pic["markers"] = {"duplicate": topo.duplicated_points, "free_end": topo.free_ends,
                          "junction": topo.junctions, "gap": topo.gaps[:, :2]}
    elif expects_curves and not row["error"]:
        row["error"] = "no curves"
    if case.strokes is not None:
        gt_topo = curve_topology(case.strokes, width, tparams)
        pic["gt"] = (case.strokes, {"duplicate": gt_topo.duplicated_points, "free_end": gt_topo.free_ends,
                                    "junction": gt_topo.junctions, "gap": gt_topo.gaps[:, :2]})
        if curves is not None:
            row.update(compare_topology(topo, gt_topo, width, tparams))
    elif curves is not None:
        row.update(topo.counts())

    kp = predicted_keypoints(store, keys)
    if kp is not None:
        row["kp_count"] = int(len(kp[0]))
        pic["keypoints"] = kp
        pic["gt_keypoints"] = case.keypoints
        if case.keypoints is not None:
            row.update(score_keypoints(kp, case.keypoints, shape[0], dict(bcfg["keypoints"])))
    return row, pic


# -- report ------------------------------------------------------------------------------------
def summary_tables(rows: list[dict], bcfg: dict) -> dict[str, list[dict]]:
    """Summaries of the ground-truth metrics (cases with GT) and of fidelity/topology/cost (all cases)."""
    from stages.evaluate.score import summarise

    rep = bcfg["report"]
    gt_rows = [r for r in rows if r.get("has_gt")]
    out = {}
    if gt_rows:
        out["ground truth"] = summarise(gt_rows, list(rep["gt_columns"]), group_by="group")
        if pooled := pooled_keypoints(gt_rows):
            out["keypoints pooled over all points"] = pooled
    out["fidelity, topology, cost"] = summarise(rows, list(rep["fidelity_columns"]), group_by="group")
    from pipeline.engine.registry import STAGES

    stage_cols = [f"t_{s.name}" for s in STAGES if any(f"t_{s.name}" in r for r in rows)]
    if stage_cols:
        out["seconds per stage"] = summarise(rows, stage_cols + ["time_s"], group_by="group")
    return out


def run_bench(cfg: DictConfig, console=None) -> tuple[list[dict], dict]:
    """Run the pipeline over the cases of ``cfg.bench``, score them and write the report.

    Returns
    -------
    (list of dict, dict)
        Per-case rows (worst first) and the summary tables.
    """
    from PIL import Image
    from rich.console import Console
    from rich.markup import escape

    if console is None:
        console = Console(stderr=True)
        if not console.is_terminal:  # a log file: do not squeeze the tables into 80 columns
            console = Console(stderr=True, width=220)
    bcfg = OmegaConf.to_container(cfg.bench, resolve=True)
    from_section(BenchConfig, bcfg, "bench")  # every key present, none unknown
    cases = discover_cases(list(bcfg["cases"] or []), bcfg["limit"])
    out = multirun_folder(Path(str(bcfg["out"])))   # a sweep (-m): one report per job
    store = ArtifactStore(str(cfg.store.path))
    images = [c.image for c in cases]
    if len({str(i) for i in images}) != len(images):
        raise UsageError("the same image is listed twice in bench.cases")
    t0 = time.perf_counter()
    if bcfg["run_pipeline"]:
        from pipeline.console import StageProgress
        from pipeline.engine.registry import active_stages

        stages = [s.name for s in active_stages(cfg.runtime.get("until"))]
        show = bool(cfg.runtime.get("progress", True)) and console.is_terminal
        with StageProgress(stages, len(images), show) as prog:
            batch = run_batch([str(i) for i in images], cfg, on_result=prog, store=store)
    else:
        batch = stored_keys([str(i) for i in images], cfg, store)
    batch_wall = time.perf_counter() - t0

    rows, pics = [], {}
    for case in cases:
        try:
            row, pic = score_case(case, batch, store, bcfg)
        except Exception as exc:  # noqa: BLE001 - one unscorable case must not sink the report
            row, pic = {"name": case.name, "dataset": case.dataset, "style": case.style, "group": case.group,
                        "image": str(case.image), "has_gt": case.strokes is not None,
                        "error": f"scoring failed: {type(exc).__name__}: {exc}"}, None
        rows.append(row)
        pics[case.name] = pic
    sort_by = pick_sort_column(rows, bcfg["report"]["sort_by"])
    rows.sort(key=sort_key(sort_by))

    pictures: dict[str, str] = {}
    if bcfg["report"]["html"]:
        (out / "img").mkdir(parents=True, exist_ok=True)
        for r in rows[: int(bcfg["report"]["max_html_cases"])]:
            pic = pics.get(r["name"])
            if pic is None:
                continue
            rel = f"img/{safe_name(r['name'])}.png"
            Image.fromarray(case_picture(pic, int(bcfg["report"]["image_scale"]))).save(out / rel)
            pictures[r["name"]] = rel
    tables = summary_tables(rows, bcfg)
    extra = {"command": "polyvec-bench " + " ".join(sys.argv[1:]), "batch_wall_s": batch_wall,
             "stage_status": batch.counts(),
             "stages": batch.stages, "sorted_by": sort_by, "cases": len(rows),
             "failures": sum(1 for r in rows if r.get("error")), "bench": bcfg,
             "config": {k: OmegaConf.to_container(v, resolve=True) if isinstance(v, DictConfig) else v
                        for k, v in cfg.items() if k not in ("bench", "hydra")}}
    write_report(rows, tables, pictures, out, bcfg, extra)
    print_tables(tables, console)
    fails = [r for r in rows if r.get("error")]
    for r in fails[:20]:
        console.print(f"[red]failed[/] {escape(str(r['name']))}: {escape(str(r['error']))}", highlight=False,
                      soft_wrap=True)
    if len(fails) > 20:
        console.print(f"… and {len(fails) - 20} more failures (see {out / 'cases.csv'})", markup=False)
    counts = batch.counts()
    computed = max((c.get("computed", 0) for c in counts.values()), default=0)
    console.print(f"pipeline wall time {batch_wall:.1f} s for {len(rows)} images ({computed} with stages computed "
                  f"in this run); time_s = the sum of an image's stage times, cached or not", highlight=False)
    console.print(f"report in {out}/ (report.html, cases.csv, cases.json, summary.json)", highlight=False,
                  markup=False)
    return rows, tables


_EXIT = ExitCode("polyvec-bench")


def _job(cfg: DictConfig) -> bool:
    return any(r.get("error") for r in run_bench(cfg)[0])


def _run_job(cfg: DictConfig) -> None:
    _EXIT.job(_job, cfg)


_app = hydra_app(_run_job, "bench_app")


def main() -> None:
    """Console entry point; exits 1 when any case failed, 2 on a usage error."""
    _EXIT.console(_app, single=(_job, "bench_app"))


if __name__ == "__main__":
    main()
