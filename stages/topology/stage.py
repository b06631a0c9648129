"""Keypoint-driven topology: key vertices, Steiner trees, coverage, allowed paths (paper §4.2–4.3).

Per connected component of the drawing graph:

1. **Key vertices** — each keypoint maps to one key vertex per frame-field branch (two at an X or T),
   nearest within ``keypoint_radius_px`` with the segment to it inside the band; near duplicates on
   one stroke merge; key vertices move onto their keypoints — corner and junction keypoints only as
   far as the ink's centre region allows (:mod:`.key_vertices`).
2. **Steiner tree** over the key vertices, Mehlhorn (default) or Kou (:mod:`.steiner`).
3. **Coverage** — loop A adds constrained shortest walks between key vertices that visit ≥ 4 uncovered
   vertices and cover ≥ 3 new band pixels; loop B turns far uncovered vertices into synthetic key
   vertices; components without keypoints start from their farthest vertices (:mod:`.candidates`).
4. **Allowed paths** between key vertices: containing no other key vertex, taking only allowed turns
   at valence-≥3 vertices (Y-junction test) (:mod:`.allowed_paths`).

The artifact follows stages/INTERFACES.md "topology";
:func:`~stages.topology.topology_picture.render_topology` draws it.

Choices made on purpose (vs. the paper and the authors' code; measurements in stages/DECISIONS.md)
------------------------------------------------------------
* **Constrained path search** (the authors' bottleneck: it gives up above 200 terminals and crashes on
  big components, their issue #10).  The resource "uncovered vertices visited" is capped at the
  threshold, so the search is one multi-source Dijkstra over (arc, capped count) states,
  numba-compiled: O(A·(N+1)·log) per added walk whatever the number of terminals.  Arcs as states
  forbid immediate reversal (no padding the count in a dead-end spur) and make the Y-junction test a
  transition rule.  Walks need not be simple; the accepted walk must still visit ≥ N *distinct*
  uncovered vertices and cover ≥ M new pixels, else its uncovered vertices stop counting and the
  search repeats, so the loop ends.  We take the cheapest qualifying walk (the authors accept
  greedily among labels).
* **Loop B** keeps going after a failed candidate (the path to it is marked rejected) instead of
  stopping at the first failure, searches only walks *from* the new terminal, and accepts shorter
  branches than the authors' (``robust_far_px`` 5 px instead of 7, ``robust_min_new_vertices`` 5
  instead of 10): overshoots of 7–10 px past a junction carry no keypoint and were being lost.
* **Coverage** of a path = band pixels whose centre lies within ``width/2 + coverage_margin_px`` of it
  (tapered capsules, ends included), and the same region decides vertex coverage.  The authors use
  ``width/2``, but their widths run between pixel *centres*, so that misses the outer half pixel of
  every stroke.
* **Y-junction test** on motion: step displacements projected on the vertices' frame-field roots,
  summed over ``turn_probe_px`` on each side of the valence-≥3 vertex; the turn is allowed when the
  two motions' cosine is ≥ ``turn_min_cos`` (0 = the paper's "positive dot product").  Probing a few
  pixels away avoids the unreliable cross-sections among a Y's singularities, and it does not depend
  on ``edge_curve`` (the authors' test passes blindly across added edges).  The probe measures
  *sliding*, not arc length (``turn_probe_max_px``, not in the paper): it runs on until the steps
  have slid ``turn_probe_px`` along the traced curves, up to ``turn_probe_max_px`` of arc, because
  edges *across* a shared band (an acute Λ) project to nothing and would allow a U-turn the test
  exists to forbid.  Allowed paths take the test at every valence-≥3 vertex (paper); the coverage
  search only next to a singularity (authors' search), and searches again without it when that finds
  no walk: coverage first (the strict version left whole strokes of scans uncovered); the
  enumeration then ends paths at such a junction (promoted synthetic key vertex) instead of turning.
* **Junction key vertices.**  A junction keypoint prefers a graph vertex of valence ≥ 3 within the
  radius (per branch class) over a nearer valence-2 one, and a path whose interior comes within
  ``junction_zone_px`` of a junction key vertex must end there, pass through it, or end inside that
  zone: through the real graph a Y keypoint otherwise lands a pixel down one branch and the two
  other branches join into a path bypassing it.
* **Pass-through at X/T.**  The paper wants X and T junctions "vectorized into two overlapping paths
  that pass through the keypoint" while allowed paths contain no other key vertex.  We emit both:
  paths end at every key vertex, and (``pass_through_junctions``) also run straight through junction
  key vertices of valence 2 — an X gives its four halves and its two full strokes, a T its two bar
  halves, the full bar and the stem.  Each path lists them in ``through_keypoints`` (an addition to
  the INTERFACES contract): a through path contributes valence 2 at each of them.  It must go
  *straight on, unambiguously* (:func:`stages.topology.candidates.straight_pass_through`): turn ≤
  ``pass_through_max_turn_deg`` over ``pass_through_probe_px``, every other branch turning off by
  ``pass_through_margin_deg`` more — else a Y traced as a chain through two branches would be
  crossed by a turning path, which the paper forbids.
* **Endpoints** get one key vertex, a graph tip (valence 1) when one is within the radius
  (:mod:`.key_vertices`); when it still lies on a passing stroke, paths may run through it
  (``pass_through_endpoints``), keeping their own position there, and the selection counts no
  valence for them: otherwise two or three curves end on such endpoints.
* ``keypoint_branches`` (data, an addition to the contract): per keypoint, the covering-subgraph
  edges leaving the zone of ``junction_zone_px`` around its key vertices — what the selection may
  cap the required valence by (``select.cap_branches``).
* **Closed paths** (a key vertex back to itself around a loop) are allowed paths, so a loop with a
  single keypoint is representable.
* **No big-component fallback and no terminal cap.**  Everything above scales with the component.
* Subgraph chains that no allowed path can use (a forbidden turn, or the enumeration budget) get
  their non-key ends promoted to synthetic key vertices, and a chain that only paths past the
  per-pair cap (``max_paths_per_pair``) use keeps the shortest of them, so the candidates always cover
  the subgraph (without it a spiral's outer ring between two key vertices lost every candidate).
  A chain whose every path the pass-through test then rejects (they turned through a junction) is
  offered on its own between its nodes (``offer_uncovered_chains``; a teardrop's long side was lost).
* A vertex claimed by two keypoints keeps the nearer keypoint.
* **Corner and junction keypoints at the ink's edge** (``keypoint_min_depth``, not in the paper:
  the authors move every key vertex exactly onto its keypoint).  Where two strokes share one band,
  the graph has one chain down its middle and a corner or junction keypoint of one stroke lies near
  the band's edge; moving the key vertex onto it drags the curves against that side, away from the
  other stroke.  So such a key vertex moves towards its keypoint only while the segment stays ≥
  ``keypoint_min_depth`` × half the stroke width inside the band (:func:`.key_vertices.snap_position`;
  depth = the band's distance transform, from pixel centres), keeping the curves inside the ink;
  deeper keypoints (most corners) are reached exactly, so sharp corners stay sharp.  Endpoint
  keypoints keep the authors' rule (a stroke's tip is at the ink's edge by nature).  A stopped
  junction lies farther from the true junction; we prefer curves that stay on the ink.

References
----------
.. [1] I. Puhachov, W. Neveu, E. Chien, M. Bessmeltsev, "Keypoint-Driven Line Drawing Vectorization
   via PolyVector Flow", ACM TOG 40(6), 2021, §4.2–4.3.
"""

from __future__ import annotations

import numpy as np

from stages.artifact import Artifact, pack_ragged
from stages.config import from_section
from stages.errors import InputError
from stages.topology import TopologyConfig
from stages.topology.candidates import candidate_paths


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
        data ``paths``, ``key_vertices``, ``edited_keypoints``, ``steiner_edges``, ``counts``, ``timings``; arrays
        ``coverage`` + ``coverage_offsets`` (flat pixel indices per path) and ``steiner_segments``
        (S, 4) ``[x0, y0, x1, y1]`` for rendering.
    """
    conf = from_section(TopologyConfig, cfg, "topology")
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
    out = candidate_paths(conf, mask, roots, _array(graph, "vertex_xy", "graph"),
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
              # keypoints the user added or retyped (keypoint_edits): the export keeps curve ends there
              "edited_keypoints": [i for i, p in enumerate(keypoints.data.get("points") or []) if p.get("edited")],
              "keypoint_branches": out["keypoint_branches"], "steiner_edges": out["steiner_edges"],
              "counts": out["counts"], "timings": out["timings"]})
