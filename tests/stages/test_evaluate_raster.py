"""Raster metrics of Yan et al. 2020 (metrics.md §2) and the thin-stroke rasteriser."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import ndimage

from stages.evaluate.raster import (INK_THRESHOLD, benchmark_stroke_width, binarise, raster_metrics,
                                    rasterise_polylines)
from stages.evaluate.score import RasterParams, render_ink
from tests.conftest import shared_path

ALL_D = [0, 2, 4, 6, 8, 10, 20, 40]


def _mask(shape, pixels):
    m = np.zeros(shape, dtype=bool)
    for r, c in pixels:
        m[r, c] = True
    return m


# -- the metric on hand-made masks whose values follow from the definition -------------------------
def test_parallel_lines_three_pixels_apart():
    # every ink pixel of either image is exactly 3 px from the other image's ink
    t = _mask((1000, 1000), [(10, c) for c in range(5, 25)])
    g = _mask((1000, 1000), [(13, c) for c in range(5, 25)])
    m = raster_metrics(t, g, f1_permille=[2, 3], f1_pixels=[2.9, 3])
    assert m["chamfer"] == pytest.approx(3 / 1000)
    assert m["hausdorff"] == pytest.approx(3 / 1000)
    assert m["f1_2"] == 0.0 and m["f1_2.9px"] == 0.0
    assert m["f1_3"] == 1.0 and m["f1_3px"] == 1.0  # inclusive <=


def test_stray_dot_costs_precision_only():
    line = [(50, c) for c in range(10, 30)]
    t = _mask((100, 100), line + [(90, 90)])
    g = _mask((100, 100), line)
    m = raster_metrics(t, g, f1_permille=[10])
    stray = math.hypot(90 - 50, 90 - 29)
    assert m["precision_10"] == pytest.approx(20 / 21)
    assert m["recall_10"] == 1.0
    assert m["f1_10"] == pytest.approx(2 * (20 / 21) / (1 + 20 / 21))
    assert m["hausdorff"] == pytest.approx(stray / 100)
    assert m["chamfer"] == pytest.approx((stray / 21 + 0.0) / 2 / 100)


def test_long_edge_is_the_larger_side():
    t = _mask((40, 200), [(5, 5)])
    g = _mask((40, 200), [(5, 9)])
    m = raster_metrics(t, g, f1_permille=[20])  # tau = 20 * 200 / 1000 = 4 px
    assert m["chamfer"] == pytest.approx(4 / 200)
    assert m["f1_20"] == 1.0


def test_identical_and_blank():
    g = _mask((64, 64), [(i, i) for i in range(10, 50)])
    m = raster_metrics(g, g, f1_permille=ALL_D)
    assert m["chamfer"] == 0 and m["hausdorff"] == 0
    assert all(m[f"f1_{d}"] == 1.0 for d in ALL_D)
    blank = raster_metrics(np.zeros_like(g), g)
    assert blank["blank"] and math.isnan(blank["chamfer"]) and math.isnan(blank["f1_4"])


def test_metric_rejects_mismatched_shapes():
    with pytest.raises(ValueError):
        raster_metrics(np.zeros((4, 5), bool), np.zeros((5, 4), bool))


def test_binarise_threshold_is_strict():
    grey = np.array([[0, 191, 192, 255]], dtype=np.uint8)
    assert binarise(grey).tolist() == [[True, True, False, False]]
    assert INK_THRESHOLD == 191.25


# -- the original benchmark's numbers (shared fixtures) ------------------------------------------------
@pytest.mark.shared
def test_reproduces_benchmark_fixtures():
    from PIL import Image

    root = shared_path("data")
    expected = json.loads((root / "metric_fixtures" / "expected_values.json").read_text())
    assert len(expected) == 9
    for e in expected:
        t = binarise(np.asarray(Image.open(root / e["test"]).convert("L")))
        g = binarise(np.asarray(Image.open(root / e["gt"]).convert("L")))
        m = raster_metrics(t, g, f1_permille=ALL_D)
        o = e["orig"]
        assert m["chamfer"] == pytest.approx(o["chamfer"], abs=1e-6), e["test"]
        assert m["hausdorff"] == pytest.approx(o["hausdorff"], abs=1e-6), e["test"]
        for d, v in o["f1"].items():
            assert m[f"f1_{d}"] == pytest.approx(v, abs=1e-6), (e["test"], d)


# -- rasteriser --------------------------------------------------------------------------------------
def test_stroke_width_rule():
    assert benchmark_stroke_width((512, 400), 1.0, 0.0) == pytest.approx(0.512)
    assert benchmark_stroke_width((512, 400), 1.0, 1.0) == 1.0
    assert benchmark_stroke_width((3000, 2000), 1.0, 1.0) == pytest.approx(3.0)


def test_horizontal_line_on_pixel_centres_is_one_black_row():
    grey = rasterise_polylines([np.array([[2.5, 5.5], [12.5, 5.5]])], (10, 16), width=1.0, supersample=4)
    assert np.allclose(grey[5, 3:12], 0.0)  # fully covered between the caps
    assert np.allclose(grey[4], 1.0) and np.allclose(grey[6], 1.0)
    assert 0.0 < grey[5, 2] < 1.0 and 0.0 < grey[5, 12] < 1.0  # round caps: partial coverage


def test_disc_area_and_union_without_double_darkening():
    dot = rasterise_polylines([np.array([[20.0, 20.0]])], (40, 40), width=10.0, supersample=8)
    assert (1 - dot).sum() == pytest.approx(math.pi * 25, rel=0.02)
    twice = rasterise_polylines([np.array([[20.0, 20.0]])] * 2, (40, 40), width=10.0, supersample=8)
    assert np.array_equal(dot, twice)


def test_one_pixel_minimum_keeps_oblique_lines_connected():
    # the reason for the 1-px minimum (module notes): at 0.001 x 288 px, oblique lines fall apart
    def pieces(width, deg):
        d = np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg))])
        line = np.array([[30.3, 30.7] - 25 * d, [30.3, 30.7] + 25 * d])
        ink = binarise(np.round(rasterise_polylines([line], (64, 64), width) * 255))
        return ndimage.label(ink, structure=np.ones((3, 3)))[1]

    angles = (0, 7, 23, 45, 61, 88)
    assert all(pieces(1.0, a) == 1 for a in angles)
    assert max(pieces(0.288, a) for a in angles) > 1


def test_rendered_ground_truth_matches_a_synthetic_drawing():
    from stages.synthetic import example_drawing

    d = example_drawing()
    params = RasterParams(1.0, 1.0, "cairo", None, 4, INK_THRESHOLD, (2, 4), (1, 2), "input")
    ink = render_ink(d.strokes, d.grey.shape, params)
    drawn = binarise(np.round(d.grey * 255))
    m = raster_metrics(ink, drawn, f1_pixels=[2])
    assert m["precision_2px"] == 1.0  # the thin rendering lies inside the 3-px strokes
    assert m["recall_2px"] > 0.99  # and is within 2 px of every ink pixel of them


def test_cairo_rendering_matches_an_svg_rendered_by_cairosvg(tmp_path):
    """Issue 18 item 18: the bench rasterises as the benchmark does — a normalised SVG (0.001·L wide,
    round caps and joins) rendered by cairo at long edge 1000 — not by an approximation: every 8-bit
    grey level equals cairosvg's rendering of the same SVG, so the ink masks are identical."""
    import io

    import cairosvg
    from PIL import Image

    from stages.evaluate.raster import rasterise_polylines_cairo
    from stages.evaluate.svg import parse_svg_polylines

    rng = np.random.default_rng(3)
    h, w = 750, 1000
    strokes = [np.cumsum(rng.normal(0, 9, (40, 2)), 0) + rng.uniform(150, 600, 2) for _ in range(12)]
    strokes.append(np.array([[500.25, 40.5], [500.25, 40.5]]))  # a dot (a lone M draws nothing in SVG)
    paths = "".join(f'<path d="M {" L ".join(f"{x:.3f} {y:.3f}" for x, y in np.round(p, 3))}"/>' for p in strokes)
    svg = tmp_path / "normalised.svg"
    svg.write_text(f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}">'
                   f'<rect width="{w}" height="{h}" fill="white"/><g fill="none" stroke="#000000" stroke-width="1" '
                   f'stroke-linecap="round" stroke-linejoin="round">{paths}</g></svg>')
    by_cairo = np.asarray(Image.open(io.BytesIO(cairosvg.svg2png(url=str(svg)))).convert("L"), np.float64)
    ours = np.round(rasterise_polylines_cairo(parse_svg_polylines(svg.read_text()), (h, w), 1.0) * 255)
    assert by_cairo.shape == ours.shape == (h, w)
    assert np.array_equal(ours, by_cairo)
    assert np.array_equal(binarise(ours), binarise(by_cairo)) and binarise(ours).sum() > 3000
    # the supersampled approximation it replaces darkens pixels the benchmark leaves white
    approx = binarise(np.round(rasterise_polylines(parse_svg_polylines(svg.read_text()), (h, w), 1.0) * 255))
    assert (approx & ~binarise(by_cairo)).sum() > 0.01 * binarise(by_cairo).sum()


def test_bench_scores_ground_truth_at_the_benchmark_long_edge():
    """The ground-truth comparison renders at long edge 1000 (1-px strokes, τ = 2 px for F1@2) whatever
    the image's size, and pixel tolerances stay in pixels of the image."""
    from stages.evaluate.score import gt_scale, score_raster

    params = RasterParams(1.0, 1.0, "cairo", 1000, 4, INK_THRESHOLD, (2,), (2,), "input")
    line = np.array([[10.0, 20.0], [200.0, 60.0]])
    shifted = line + [0.0, 1.5]                      # 1.5 px of the 256-px image = 5.9 px at 1000
    scale = gt_scale((256, 128), params)
    assert scale == 1000 / 256
    a, b = render_ink([line], (256, 128), params, scale), render_ink([shifted], (256, 128), params, scale)
    assert a.shape == (1000, 500)
    m = score_raster(a, b, params, scale=scale)
    assert m["f1_2"] < 0.2 and m["f1_2px"] == 1.0
