"""stages.prep.specks: dust, small far clusters and the page's dark edge do not widen the crop's box."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from stages.prep.specks import (
    PAGE_EDGE_BAND_PX,
    count_left_out,
    kept_clusters,
    marks_and_strokes,
    page_edge,
)


def _labels(ink: np.ndarray) -> tuple[np.ndarray, int]:
    return ndimage.label(ink, structure=np.ones((3, 3)))


def test_the_pages_dark_edge_is_its_strip_along_the_sides():
    ink = np.zeros((300, 300), bool)
    ink[:10, :] = True                            # a dark band along the whole top
    ink[10:150, 148:151] = True                   # a stroke touching it, running down the page
    ink[200:210, 200:210] = True                  # a mark that touches no side
    labels, n = _labels(ink)
    edge = page_edge(labels, n, 0.25)
    assert edge[:10].all() and edge[10:PAGE_EDGE_BAND_PX, 148:151].all()
    assert not edge[PAGE_EDGE_BAND_PX:].any()     # the rest of the stroke stays a drawing
    assert page_edge(*_labels(ink[20:]), 0.25) is None


def test_marks_are_big_enough_for_the_band_and_strokes_bigger_than_dust():
    ink = np.zeros((100, 100), bool)
    ink[5:7, 5:7] = True                          # 4 px: below min_component_px
    ink[20:25, 20:25] = True                      # a 5×5 speck of dust
    ink[50:53, 10:90] = True                      # a stroke
    marks, bounds, strokes = marks_and_strokes(*_labels(ink), min_component_px=6, max_speck_px=16)
    np.testing.assert_array_equal(marks, [False, True, True])
    np.testing.assert_array_equal(strokes, [False, False, True])
    np.testing.assert_array_equal(bounds[2], [50, 53, 10, 90])


def test_a_small_cluster_far_from_the_drawing_is_left_out():
    ink = np.zeros((400, 400), bool)
    ink[50:150, 50:53] = ink[50:53, 50:150] = True          # the drawing: 594 px
    ink[350:353, 330:370] = True                            # a far 120-px stroke: 20 % of it
    ink[20:21, 330:340] = True                              # a far 10-px stroke: under 2 %
    labels, n = _labels(ink)
    strokes = np.ones(n, bool)
    padded, clusters, kept = kept_clusters(labels, strokes, gap_px=64, min_share=0.02)
    assert padded.shape == (400, 400) and clusters.shape == kept.shape == (25, 25)
    assert padded[50:150, 50:53].all() and padded[350:353, 330:370].all() and not padded[20, 330:340].any()


def test_left_out_counts_marks_outside_every_box_and_keeps_the_edge_it_was_given():
    bounds = np.array([[10, 20, 10, 20], [100, 110, 100, 110], [0, 5, 0, 200]])
    marks = np.array([True, True, False])
    edge = np.zeros((200, 200), bool)
    edge[:5] = True
    assert count_left_out(marks, bounds, [(0, 50, 0, 50)], edge) == (1, True)
    assert count_left_out(marks, bounds, [(0, 200, 0, 200)], edge) == (0, False)
    assert edge[:5].all()                         # not changed
    assert count_left_out(marks, bounds, [(0, 50, 0, 50), (90, 120, 90, 120)], None) == (0, False)
