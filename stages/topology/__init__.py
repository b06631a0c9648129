"""Keypoint-driven topology: key vertices, Steiner trees, coverage, allowed paths (paper §4.2–4.3).

Per connected component of the drawing graph:

1. **Key vertices** — each keypoint maps to one key vertex per frame-field branch (two at an X or T),
   nearest within ``keypoint_radius_px`` with the segment to it inside the band; near duplicates on
   one stroke merge; key vertices move onto their keypoints — corner and junction keypoints only as
   far as the ink's centre region allows (:mod:`.key_vertices`).
2. **Steiner tree** over the key vertices, Mehlhorn (default) or Kou (:mod:`.steiner`).
3. **Coverage** — loop A adds constrained shortest walks between key vertices that visit ≥ 4 uncovered
   vertices and cover ≥ 3 new band pixels; loop B turns far uncovered vertices into synthetic key
   vertices; components without keypoints start from their farthest vertices (:mod:`.extract`).
4. **Allowed paths** between key vertices: containing no other key vertex, taking only allowed turns
   at valence-≥3 vertices (Y-junction test) (:mod:`.allowed_paths`).

The artifact follows stages/INTERFACES.md "topology"; :func:`render_topology` draws it.

Choices made on purpose (vs. the paper and the authors' code)
------------------------------------------------------------
* **Constrained path search** (the authors' bottleneck; it gives up above 200 terminals and crashes on
  big components, their issue #10).  We cap the resource "uncovered vertices visited" at the
  threshold, so the search is one multi-source Dijkstra over (arc, capped count) states, numba-compiled:
  O(A·(N+1)·log) per added walk whatever the number of terminals.  Arcs as states forbid immediate
  reversal (no padding the count in a dead-end spur) and make the Y-junction test a transition rule.
  Walks need not be simple; the accepted walk must still visit ≥ N *distinct* uncovered vertices and
  cover ≥ M new pixels, otherwise its uncovered vertices stop counting (they are redundant) and the
  search repeats — so each round removes uncovered vertices and the loop ends.  The authors accept
  greedily among labels; we take the cheapest qualifying walk.
* **Loop B** keeps going after a failed candidate (the path to it is marked rejected) instead of
  stopping at the first failure, and searches only walks *from* the new terminal.
* **Coverage** of a path = band pixels whose centre lies within ``width/2 + coverage_margin_px`` of it
  (tapered capsules around the edges, ends included).  The authors use ``width/2`` with strict
  inequality and projections inside segments (+ squares round vertices); their widths are
  cross-section diameters between the outermost traced curves, i.e. between pixel *centres*, so
  ``width/2`` misses the outer half pixel of every stroke.  The same thickened region decides vertex
  coverage (authors: perpendicular distance < radius).
* **Y-junction test.**  The paper compares the average motion over the traced curves shared by
  consecutive vertices.  We measure motion as the step displacements projected on the vertices'
  frame-field roots (the traced curves' directions) summed over ``turn_probe_px`` of arc length on
  each side of the valence-≥3 vertex, and allow the turn when the two motions' cosine is
  ≥ ``turn_min_cos`` (0 = "positive dot product").  Probing a few pixels away matters because the
  graph's Y vertices sit among singularities where single cross-sections are unreliable, and it
  does not depend on ``edge_curve`` (the authors' test passes blindly across added edges).
  **The probe measures sliding, not arc length** (``turn_probe_max_px``, not in the paper): it
  runs on until the steps have slid ``turn_probe_px`` *along* the traced curves (the sum of their
  projected lengths), up to ``turn_probe_max_px`` of arc.  Where two strokes share one band (the
  arms of an acute Λ below its tip, a stroke running into another) the graph reaches the Y vertex
  over edges *across* the band, whose steps project to almost nothing; measured over 3 px of arc
  the motion was ~0, read as "no information", and every turn there was allowed — so a path
  could run up one arm, cross the band and come down the other (a U-turn the paper's test exists
  to forbid).  Chosen to cover both arms, such a candidate ran along a stroke that another curve
  also took (duplicated run + three curve ends at the tip: cr_test_193_pencil's two Λ tips, its
  worst Hausdorff pixel 5.7 → 3.2 px).  Measured on realvec_dev (tests/benchmarks/
  quality_realvec.py, detector keypoints; 20 of 106 drawings change): endpoint F1 median
  0.857 → 0.872 (mean 0.838 → 0.850), junction F1 median 0.704 → 0.708 (mean 0.699 → 0.699),
  Hausdorff median 3.00 both (≤ 3 px in 54 → 55 drawings, mean 3.81 → 3.67), dangling 21 → 19,
  F1@2 0.9933 → 0.9936, duplicated length mean 136 → 113 px (median 36.8 → 39.8); output false
  junctions 343 → 340.  Ground-truth keypoints: endpoint F1 median 0.909 both (mean 0.871 →
  0.891), junction F1 0.857 → 0.861, dangling 24 → 21 (0.23 → 0.198 per drawing), Hausdorff
  ≤ 3 px in 57 → 58.  Probe caps of 6 and 24 px measured the same as 12.
  Where a false junction has duplicated curves, the duplicate is mostly *not* this: both paths are needed for the valence of their other ends (a side stroke or a
  spurious endpoint/corner keypoint reached only along another stroke, with no junction keypoint
  where it branches off; the ground truth mostly draws such merges as overlapping strokes with no
  junction where they part, so making those branch points synthetic key vertices removed the
  duplicates (mean 113 → 26 px) but tripled the false junctions with nothing in the ground
  truth); making valences soft or coverage centre-line-only in the selection was measured and not
  adopted.
  Allowed paths take the test at every valence-≥3 vertex (paper).  The coverage search applies it
  only at vertices flagged next to a singularity (authors' search), and when that finds no walk it
  searches again without it: on the scanned drawings the strict version left whole strokes
  uncovered (banana tree: 78 % of the band instead of 99.6 %) because the only way to reach them
  turned sharply at a graph junction.  Coverage first; the enumeration then ends paths at such a
  junction (promoted synthetic key vertex) instead of turning.
* **Junction key vertices.**  A junction keypoint prefers a graph vertex of valence ≥ 3 within the
  radius (per branch class) over a nearer valence-2 one, and a path whose interior comes within
  ``junction_zone_px`` of a junction key vertex must end there, pass through it, or end inside that
  zone.  Through the real graph a Y keypoint otherwise lands a pixel down one branch and the two
  other branches join into a path bypassing it.
* **Pass-through at X/T.**  The paper wants X and T junctions "vectorized into two overlapping paths
  that pass through the keypoint" while allowed paths contain no other key vertex.  We emit both:
  paths end at every key vertex, and (``pass_through_junctions``) also run straight through junction
  key vertices of valence 2 — an X gives its four halves and its two full strokes, a T its two bar
  halves, the full bar and the stem.  Each path lists them in ``through_keypoints`` (an addition to
  the INTERFACES contract): a through path contributes valence 2 at each of them.
  A path through a junction keypoint must go *straight on, unambiguously*
  (:func:`stages.topology.extract.straight_pass_through`): turn ≤ ``pass_through_max_turn_deg``
  over ``pass_through_probe_px``, and every other branch there turning off by
  ``pass_through_margin_deg`` more.  The graph traces many Y junctions as a chain through two
  branches plus the third apart, and the path turning from branch to branch through the chain's
  key vertex was otherwise chosen (it is shorter once flowed): the paper allows no such turn.
* **Endpoints** get one key vertex, a graph tip (valence 1) when one is within the radius
  (:mod:`.key_vertices`); when it still lies on a passing stroke, paths may run through it
  (``pass_through_endpoints``), keeping their own position there, and the selection counts no
  valence for them.  On realvec_dev with ground-truth keypoints 15 % of the endpoints had two or
  three chosen curves ending on them before.
* **Loop B** accepts shorter branches than the authors' (farther than ``robust_far_px`` = 5 px
  instead of 7, ≥ ``robust_min_new_vertices`` = 5 uncovered vertices instead of 10, and
  ≥ ``robust_min_new_pixels`` new pixels): stroke ends that
  overshoot a junction by 7–10 px carry no keypoint in the ground truth (its rule drops endpoints
  within 2 widths of a junction) and were left out, the largest Hausdorff misses on realvec_dev.
* ``keypoint_branches`` (data, an addition to the contract): per keypoint, the covering-subgraph
  edges leaving the zone of ``junction_zone_px`` around its key vertices — what the selection may
  cap the required valence by (``select.cap_branches``).
* **Closed paths** (a key vertex back to itself around a loop) are allowed paths, so a loop with a
  single keypoint is representable.
* **No big-component fallback and no terminal cap.**  Everything above scales with the component.
* Subgraph chains that no allowed path can use (a forbidden turn, or the enumeration budget) get
  their non-key ends promoted to synthetic key vertices, so the candidates always cover the subgraph.
* A vertex claimed by two keypoints keeps the nearer keypoint.
* **Corner and junction keypoints at the ink's edge** (``keypoint_min_depth``, not in the paper:
  the authors move every key vertex exactly onto its keypoint).  Where two strokes run side by side
  in one band (a merged band, an acute vee, a stroke ending against another) the graph has one chain
  down the band's middle, and a corner keypoint of one of the strokes lies near the band's edge.
  Moving the key vertex onto it drags every curve ending at or running through the corner against
  that side, leaving the other stroke 3–4 px from any curve: the worst Hausdorff pixel of
  qd_dog_01_pencil, tu_angel_163_pencil, qd_bear_01_clean, qd_cat_00_clean and qd_rabbit_00_clean on
  realvec_dev (detector keypoints).  A junction keypoint at the edge of a blob makes a curve end
  stick out of the stroke the same way (qd_giraffe_00_clean, qd_squirrel_02_pencil).  Such
  detections are mostly *right* (shallow corners lie 0.7 px, median, from a ground-truth keypoint,
  shallow junctions 1.1 px): the fault is the single chain, which the selection cannot fix.  So a
  corner's or junction's key vertex moves towards its keypoint only while the segment stays ≥
  ``keypoint_min_depth`` (0.8) × half the stroke width inside the band
  (:func:`.key_vertices.snap_position`; depth = the band's distance transform, which counts from
  pixel centres, ~0.5 px more than the ink depth), keeping the curves inside the ink.  Keypoints
  deeper than that — 80–90 % of the detected corners — are reached exactly, so sharp corners stay
  sharp.  Endpoint keypoints keep the authors' rule (a stroke's tip is at the ink's edge by nature).
  The cost, and why junctions are included anyway: a stopped junction lies farther from the
  ground-truth junction (shallow ones 1.1 px → 2.0 px), which changes the junction F1 of some
  drawings; we prefer curves that stay on the ink.  Measured on realvec_dev
  (tests/benchmarks/quality_realvec.py, detector keypoints, with the export and typing of this
  commit): corners only — Hausdorff ≤ 3 px in 51 cases, median 3.16; corners and junctions — 54
  cases, median 3.00 (mean 3.83 → 3.81), junction F1 median 0.708 → 0.704 (mean 0.700 → 0.699),
  endpoint F1 median 0.861 → 0.857 (mean 0.838 both), dangling 0.198 both, F1@2 unchanged.  (Before
  this session's typing and export changes: corners only moved the Hausdorff median 3.16 → 3.08,
  53 cases ≤ 3 px; ground-truth keypoints 3.08 → 3.00.)

References
----------
.. [1] I. Puhachov, W. Neveu, E. Chien, M. Bessmeltsev, "Keypoint-Driven Line Drawing Vectorization
   via PolyVector Flow", ACM TOG 40(6), 2021, §4.2–4.3.
"""

from __future__ import annotations

import numpy as np

from stages.artifact import Artifact, pack_ragged
from stages.errors import InputError
from stages.topology.config import TopologyConfig
from stages.topology.extract import extract_topology
from stages.topology.render import render_topology

STAGE_VERSION = "4"

__all__ = ["STAGE_VERSION", "run", "render_topology", "TopologyConfig", "extract_topology"]


def _array(art: Artifact, name: str, stage: str) -> np.ndarray:
    if name not in art.arrays:
        raise InputError(f"topology: the {stage} artifact has no '{name}' array")
    return np.asarray(art.arrays[name])


def run(cfg: dict, **inputs: Artifact) -> Artifact:
    """Stage entry: candidate (allowed) paths of a drawing.

    Parameters
    ----------
    cfg : dict
        The ``topology`` config section (keys of :class:`TopologyConfig`).
    prep, field, graph, keypoints : Artifact
        Upstream artifacts (stages/INTERFACES.md): ``mask``; ``roots``; the graph arrays; ``points``
        and ``types``. The engine passes the keypoints as ``keypoint_edits`` (the detector's
        keypoints after the user's edits, same arrays).

    Returns
    -------
    Artifact
        data ``paths``, ``key_vertices``, ``steiner_edges``, ``counts``, ``timings``; arrays
        ``coverage`` + ``coverage_offsets`` (flat pixel indices per path) and ``steiner_segments``
        (S, 4) ``[x0, y0, x1, y1]`` for rendering.
    """
    conf = TopologyConfig.from_dict(cfg)
    if "keypoint_edits" in inputs:  # the engine's input: the detector's keypoints after the user's edits
        inputs["keypoints"] = inputs.pop("keypoint_edits")
    missing = [n for n in ("prep", "field", "graph", "keypoints") if n not in inputs]
    if missing:
        raise InputError(f"topology stage needs the {', '.join(missing)} artifact(s)")
    prep, field, graph, keypoints = (inputs[n] for n in ("prep", "field", "graph", "keypoints"))
    mask = _array(prep, "mask", "prep").astype(bool)
    roots = _array(field, "roots", "field")
    if mask.ndim != 2 or roots.shape[:2] != mask.shape:
        raise InputError(f"topology: mask {mask.shape} and field roots {roots.shape} do not match")
    points = _array(keypoints, "points", "keypoints").astype(np.float64).reshape(-1, 2)
    types = _array(keypoints, "types", "keypoints").reshape(-1)
    if len(types) != len(points):
        raise InputError("topology: keypoint points and types differ in length")
    if not np.all(np.isfinite(points)):
        raise InputError("topology: keypoint positions are not finite")
    out = extract_topology(conf, mask, roots, _array(graph, "vertex_xy", "graph"),
                           _array(graph, "vertex_width", "graph"), _array(graph, "vertex_root", "graph"),
                           _array(graph, "edges", "graph"), points, types,
                           graph.arrays.get("vertex_flags"))
    cov, cov_off = pack_ragged(out["coverage"], np.int32)
    notes = []
    if out["counts"].get("enumeration_budget_hit"):
        # The guard on the path search (best-first, so a cut drops the longest paths); the chains no
        # path reached get synthetic key vertices and are still covered.
        notes.append(f"path search cut at topology.max_enumeration_steps ({conf.max_enumeration_steps}) from "
                     f"{out['counts']['enumeration_budget_hit']} key vertices: the longest candidate paths are missing")
    return Artifact(notes=notes,
        arrays={"coverage": cov.astype(np.int32), "coverage_offsets": cov_off,
                "steiner_segments": np.asarray(out["steiner_segments"], np.float64)},
        data={"paths": out["paths"], "key_vertices": out["key_vertices"],
              "keypoint_branches": out["keypoint_branches"], "steiner_edges": out["steiner_edges"],
              "counts": out["counts"], "timings": out["timings"]})
