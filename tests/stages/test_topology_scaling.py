"""Cost per ink pixel on a page of many drawings (issue #54): per-keypoint and per-component work of
the topology stage stays within its own component, and its page-sized arrays stay small."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import yaml
from synthetic_graph import synthetic_inputs

from stages import synthetic
from stages.synthetic import Drawing, render
from stages.topology import candidates, run
from stages.topology.coverage import band_capsule_members
from stages.topology.work_graph import build_work_graph

ROOT = Path(__file__).resolve().parents[2]
CFG = yaml.safe_load((ROOT / "conf" / "topology" / "default.yaml").read_text())


def _page_of_crosses(n: int = 3, size: int = 64) -> Drawing:
    """n × n X junctions side by side: 2 n² graph components, each X keypoint on two of them."""
    one = synthetic.cross(size=size)
    strokes, kps = [], []
    for i in range(n):
        for j in range(n):
            off = np.array([j * size, i * size], float)
            strokes += [s + off for s in one.strokes]
            kps += [(x + off[0], y + off[1], t) for x, y, t in one.keypoints]
    return Drawing(render((n * size, n * size), strokes, one.width), strokes, one.width, kps)


def test_keypoint_branches_search_only_the_keypoints_own_components(monkeypatch):
    searched = []
    real = candidates.dijkstra

    def spy(graph, *args, **kwargs):
        if kwargs.get("limit") == CFG["junction_zone_px"]:
            searched.append(graph.shape[0])
        return real(graph, *args, **kwargs)

    monkeypatch.setattr(candidates, "dijkstra", spy)
    art = run(CFG, **synthetic_inputs(_page_of_crosses()))
    n_vertices = art.data["counts"]["vertices"]
    assert art.data["counts"]["components"] == 18
    assert searched and max(searched) <= n_vertices // 9        # one component (of 18), not the page
    centres = {k for k, (*_, t) in enumerate(_page_of_crosses().keypoints) if t == 3}
    branches = {b["keypoint"]: b["branches"] for b in art.data["keypoint_branches"]}
    assert {branches[k] for k in centres} == {4}                # an X: four branches over two components


def test_work_graph_valence_is_computed_once():
    g = build_work_graph(np.array([[0, 0], [1, 0], [2, 0.]]), np.ones(3), np.ones(3), np.array([[0, 1], [1, 2]]))
    assert g.degree is g.degree
    np.testing.assert_array_equal(g.degree, [1, 2, 1])


def test_band_coverage_of_a_large_page_needs_little_more_than_its_pixel_index():
    mask = np.zeros((3000, 3000), bool)
    mask[100:104, 100:2900] = True                              # one long stroke on a large page
    x = np.linspace(100, 2900, 700)
    a = np.stack([x[:-1], np.full(699, 102.0)], 1)
    b = np.stack([x[1:], np.full(699, 102.0)], 1)
    r = np.full(699, 2.5)
    tracemalloc.start()
    flat, off = band_capsule_members(mask, a, b, r, r)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 5 * mask.size                                 # an int32 index, not an int64 one
    assert flat.dtype == np.int64 and off[-1] == len(flat)
    small_chunks = band_capsule_members(mask, a, b, r, r, chunk=1000)
    np.testing.assert_array_equal(flat, small_chunks[0])
    np.testing.assert_array_equal(off, small_chunks[1])
