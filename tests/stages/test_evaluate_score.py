"""Case scoring helpers, summaries, SVG polylines and report pictures (stages/evaluate)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stages.evaluate.report_pictures import hstack_panels, overlay
from stages.evaluate.score import estimate_stroke_width, stage_timings, summarise
from stages.evaluate.svg import parse_svg_polylines, svg_size
from stages.synthetic import render


def test_stage_timings_sum_and_peak():
    row = stage_timings({"prep": {"duration_s": 0.5, "peak_rss_mb": 100.0},
                         "field": {"duration_s": 2.0, "peak_rss_mb": 300.0}})
    assert row["time_s"] == pytest.approx(2.5) and row["peak_rss_mb"] == 300.0
    assert row["t_field"] == 2.0 and row["rss_prep"] == 100.0
    assert math.isnan(stage_timings({})["time_s"])


def test_summarise_groups_failures_and_nans():
    rows = [{"group": "a", "x": 1.0, "error": ""}, {"group": "a", "x": 3.0, "error": ""},
            {"group": "b", "x": float("nan"), "error": "boom"}, {"group": "b", "x": 10.0, "error": ""}]
    out = {e["group"]: e for e in summarise(rows, ["x"], group_by="group")}
    assert out["all"]["cases"] == 4 and out["all"]["failures"] == 1
    assert out["all"]["x"] == {"median": 3.0, "mean": pytest.approx(14 / 3), "n": 3}
    assert out["a"]["x"]["median"] == 2.0 and out["b"]["failures"] == 1
    single = summarise(rows[:2], ["x"], group_by="group")
    assert [e["group"] for e in single] == ["all"]


@pytest.mark.parametrize("width", [2.0, 3.0, 5.0])
def test_estimate_stroke_width(width):
    t = np.linspace(0, 2 * np.pi, 200)
    strokes = [np.c_[60 + 40 * np.cos(t), 60 + 40 * np.sin(t)], np.array([[10.0, 110], [110, 112]])]
    ink = render((128, 128), strokes, width) < 0.75
    assert estimate_stroke_width(ink) == pytest.approx(width, rel=0.25)
    assert estimate_stroke_width(np.zeros((8, 8), bool)) == 1.0


def test_svg_polylines_paths_and_underlay():
    svg = """<svg xmlns="http://www.w3.org/2000/svg" width="100px" height="50px">
      <image href="x.png" width="100" height="50"/>
      <polyline points="1,2 3,4 5,6"/><line x1="0" y1="0" x2="10" y2="0"/>
      <path d="M0 0 L10 0 l0 10 h-10 z M 5 5 Q 10 10 15 5"/></svg>"""
    pl = parse_svg_polylines(svg, chord_px=0.5)
    assert len(pl) == 4
    assert pl[0].tolist() == [[1, 2], [3, 4], [5, 6]]
    assert pl[2].tolist() == [[0, 0], [10, 0], [10, 10], [0, 10], [0, 0]]
    q = pl[3]
    assert q[0].tolist() == [5, 5] and q[-1].tolist() == pytest.approx([15, 5])
    assert q[:, 1].max() == pytest.approx(7.5, abs=0.05)  # the quadratic's apex
    assert svg_size(svg)[:2] == (100.0, 50.0)


def test_svg_errors_are_clear():
    with pytest.raises(ValueError, match="transform"):
        parse_svg_polylines('<svg xmlns="http://www.w3.org/2000/svg"><g transform="scale(2)">'
                            '<path d="M0 0 L1 1"/></g></svg>')
    with pytest.raises(ValueError, match="not an SVG"):
        parse_svg_polylines("<svg")


def test_overlay_draws_curves_and_markers():
    grey = np.ones((20, 30))
    img = overlay(grey, [np.array([[2.5, 10.5], [27.5, 10.5]])], {"junction": np.array([[15.0, 5.0]])}, scale=2)
    assert img.shape == (40, 60, 3) and img.dtype == np.uint8
    assert (img[21, 10:50] != 255).any(axis=-1).all()  # the curve's row at scale 2
    assert (img[:, :, 0] > 150).any() and (img[:, :, 1] < 100).any()  # red-ish marker somewhere
    both = hstack_panels([img, img[:10]], gap=4)
    assert both.shape == (40, 124, 3)
