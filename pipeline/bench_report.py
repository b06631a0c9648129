"""The report of ``polyvec-bench`` (:mod:`pipeline.bench`): summary tables (rich), ``cases.json``,
``cases.csv``, ``summary.json`` and ``report.html`` with a picture per case, worst cases first.
"""

from __future__ import annotations

import csv
import html
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np


def _is_distance(col: str) -> bool:
    return col in ("chamfer", "hausdorff") or col.endswith(("_chamfer", "_hausdorff"))


def column_unit(col: str) -> str:
    """The unit a table or report column is shown in (every column has one).

    Chamfer and Hausdorff are stored as fractions of the long edge L (metrics.md §2.4) and shown in
    per-mille of L (‰ L: pixels at the benchmark's L = 1000, the unit of the F1 tolerances), so a
    0.3-px Chamfer reads 0.300, not 0.000.
    """
    base = col[4:] if col.startswith("fid_") else col
    if _is_distance(base):
        return "‰ L"
    if base.startswith(("f1_", "kp_f1", "precision", "recall")) or base.endswith(("_f1", "_acc")) \
            or "_precision" in base or "_recall" in base:
        return "0–1"
    if base.startswith("t_") or base.endswith("_s"):
        return "s"
    if base.endswith("_mb"):
        return "MB"
    if base.endswith("_px") or base == "width":
        return "px"
    return "count"


def _head(col: str) -> str:
    """A column heading with its unit."""
    return f"{col} [{column_unit(col)}]"


def _fmt(v: Any, col: str = "") -> str:
    if isinstance(v, bool):
        return "yes" if v else ""
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        if not math.isfinite(v):
            return "–"
        if _is_distance(col):
            return f"{1000.0 * v:.3f}"      # ‰ of the long edge (column_unit)
        if abs(v) >= 100:
            return f"{v:.0f}"
        return f"{v:.3f}" if abs(v) < 10 else f"{v:.1f}"
    return str(v)


def sort_key(sort_by: str):
    lower_is_better = ("chamfer" in sort_by or "hausdorff" in sort_by or sort_by in
                       ("junction_gaps", "dangling", "duplicated_px", "time_s"))

    def key(row: dict):
        if row.get("error"):
            return (0, 0.0)
        v = row.get(sort_by, row.get("fid_" + sort_by))  # plain images: their fidelity counterpart
        if not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            return (1, 0.0)
        return (2, -float(v) if lower_is_better else float(v))

    return key


def pick_sort_column(rows: list[dict], sort_by: str) -> str:
    """``sort_by``, or the fidelity counterpart when no row has it (plain images only)."""
    if any(isinstance(r.get(sort_by), (int, float)) for r in rows):
        return sort_by
    return "fid_" + sort_by if any(isinstance(r.get("fid_" + sort_by), (int, float)) for r in rows) else sort_by


def _summary_cell(entry: dict, column: str) -> str:
    """``median (mean)`` of a summary entry, or the one value of a pooled figure."""
    if entry.get("pooled"):
        return _fmt(entry["median"], column)
    return f"{_fmt(entry['median'], column)} ({_fmt(entry['mean'], column)})"


def print_tables(tables: dict[str, list[dict]], console) -> None:
    """rich tables: one row per group, each cell ``median (mean)``."""
    from rich.markup import escape
    from rich.table import Table

    for title, entries in tables.items():
        cols = [k for k in entries[0] if k not in ("group", "cases", "failures")]
        cols = [c for c in cols if any(e[c]["n"] for e in entries)]
        pooled = any(e[c].get("pooled") for e in entries for c in cols)
        t = Table(title=f"polyvec-bench — {title}" + ("" if pooled else ": median (mean)"), show_lines=False)
        t.add_column("group", no_wrap=True)
        t.add_column("cases", justify="right")
        t.add_column("fail", justify="right")
        for c in cols:
            t.add_column(_head(c), justify="right")
        for e in entries:
            cells = [_summary_cell(e[c], c) for c in cols]
            fail = f"[red]{e['failures']}[/]" if e["failures"] else "0"
            t.add_row(escape(str(e["group"])), str(e["cases"]), fail, *cells)
        console.print(t)


def safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


def case_picture(pic: dict, scale: int) -> np.ndarray:
    """Labelled panels: output curves and their topology; ground truth and its topology; keypoints."""
    from PIL import Image, ImageDraw

    from stages.evaluate.report_pictures import hstack_panels, overlay

    panels: list[tuple[str, np.ndarray]] = []
    if pic["curves"] is not None:
        panels.append((f"output: {len(pic['curves'])} curves",
                       overlay(pic["grey"], pic["curves"], pic["markers"], scale=scale)))
    else:
        panels.append(("input (no curves)", overlay(pic["grey"], [], {}, scale=scale, fade=0.0)))
    if pic["gt"] is not None:
        panels.append((f"ground truth: {len(pic['gt'][0])} strokes", overlay(pic["grey"], *pic["gt"], scale=scale)))
    if pic["keypoints"] is not None:
        pts, types = pic["keypoints"]
        marks = {"free_end": pts[types == 1], "junction": pts[types == 3], "corner": pts[types == 5]}
        if pic.get("gt_keypoints"):
            marks["gt"] = np.concatenate(list(pic["gt_keypoints"].values())).reshape(-1, 2)
        panels.append((f"keypoints: {len(pts)} detected" + (", GT purple" if "gt" in marks else ""),
                       overlay(pic["grey"], [], marks, scale=scale, marker_radius=3)))
    labelled = []
    for title, img in panels:
        im = Image.fromarray(img)
        ImageDraw.Draw(im).text((4, 2), title, fill=(0, 0, 0))
        labelled.append(np.asarray(im))
    return hstack_panels(labelled)


def write_report(rows: list[dict], tables: dict, pictures: dict[str, str], out: Path, bcfg: dict,
                 extra: dict) -> None:
    """cases.json, cases.csv, summary.json and report.html (pictures already in ``out/img``)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "cases.json").write_text(json.dumps(rows, indent=1, default=_json_default))
    cols: list[str] = []
    for r in rows:
        cols.extend(k for k in r if k not in cols)
    with open(out / "cases.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in cols})
    # Units of the stored values (Chamfer and Hausdorff as fractions of L; the tables show them in ‰ L).
    units = {c: "fraction of L" if _is_distance(c) else column_unit(c) for c in cols}
    (out / "summary.json").write_text(json.dumps(dict(extra, tables=tables, units=units), indent=1,
                                                 default=_json_default))
    if bcfg["report"]["html"]:
        (out / "report.html").write_text(html_report(rows, tables, pictures, bcfg, extra))


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def html_report(rows: list[dict], tables: dict, pictures: dict[str, str], bcfg: dict, extra: dict) -> str:
    """A self-contained HTML page (pictures linked from img/): summaries, then cases worst first."""
    esc = html.escape
    rep = bcfg["report"]
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>polyvec-bench</title><style>",
             "body{font-family:sans-serif;margin:1em}table{border-collapse:collapse;margin:.5em 0}"
             "td,th{border:1px solid #ccc;padding:2px 6px;font-size:12px;text-align:right}"
             "th{background:#eee}td:first-child{text-align:left}.case{margin:1.5em 0;border-top:2px solid #888}"
             "img{max-width:100%;image-rendering:pixelated}.err{color:#b00}</style></head><body>",
             "<h1>polyvec-bench</h1>",
             f"<p>{esc(extra.get('command', ''))}<br>{len(rows)} cases; batch wall time "
             f"{extra.get('batch_wall_s', 0):.1f} s; stages: {esc(', '.join(extra.get('stages', [])))}</p>",
             "<p>Pictures: output curves (one colour each) with their <b style='color:#00a000'>free ends</b>, "
             "<b style='color:#dc0000'>junctions</b>, <b style='color:#ff8c00'>junction gaps</b> and "
             "<b style='color:#ff00ff'>duplicated pieces</b> (magenta dots); then the "
             "ground truth with the same extraction; then the detected keypoints (green endpoint, red junction, "
             "blue corner).</p>"]
    for title, entries in tables.items():
        cols = [k for k in entries[0] if k not in ("group", "cases", "failures") and any(e[k]["n"] for e in entries)]
        pooled = any(e[c].get("pooled") for e in entries for c in cols)
        parts.append(f"<h2>{esc(title)}{'' if pooled else ': median (mean)'}</h2><table><tr><th>group</th><th>cases</th><th>fail</th>"
                     + "".join(f"<th>{esc(_head(c))}</th>" for c in cols) + "</tr>")
        for e in entries:
            parts.append(f"<tr><td>{esc(e['group'])}</td><td>{e['cases']}</td><td>{e['failures']}</td>"
                         + "".join(f"<td>{_summary_cell(e[c], c)}</td>" for c in cols)
                         + "</tr>")
        parts.append("</table>")
    sort_by = extra.get("sorted_by", rep["sort_by"])
    parts.append(f"<h2>Cases, worst first by {esc(sort_by)}</h2>")
    shown = [c for c in list(rep["gt_columns"]) + list(rep["fidelity_columns"])]
    for r in rows:
        cells = [c for c in shown if c in r]
        parts.append(f"<div class='case'><h3>{esc(r['name'])} <small>({esc(r['group'])})</small></h3>")
        if r.get("error"):
            parts.append(f"<p class='err'>{esc(str(r['error']))}</p>")
        parts.append("<table><tr>" + "".join(f"<th>{esc(_head(c))}</th>" for c in cells) + "</tr><tr>"
                     + "".join(f"<td>{_fmt(r[c], c)}</td>" for c in cells) + "</tr></table>")
        if r["name"] in pictures:
            parts.append(f"<img src='{esc(pictures[r['name']])}' loading='lazy'>")
        parts.append("</div>")
    parts.append("</body></html>")
    return "\n".join(parts)


# -- driver ------------------------------------------------------------------------------------
