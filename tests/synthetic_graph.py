"""Graph, field, prep and keypoints artifacts built from known centre lines (tests and benchmarks).

The topology stage consumes the graph stage's artifact.  To test it on drawings with known answers
(and independently of the tracer), this module builds artifacts in exactly the graph stage's format
(stages/INTERFACES.md "graph") from the strokes of a :class:`stages.synthetic.Drawing`, imitating how
the traced graph represents each configuration (reference b19-frame-field-and-graph.md §A.3):

* every stroke is one *chain*: vertices about 1 px apart along the centre line (corners kept),
  consecutive vertices joined by an edge, width = the stroke width, root = the local tangent;
* **X**: two crossing strokes are two chains that overlap at the crossing and share no vertex;
* **T**: a stroke ending on another stroke's interior (the stem) runs on past the bar's centre line by
  half a stroke width (the traced curves stop at the bar's far edge) and shares no vertex with it;
* **Y**: strokes ending at a common point share one vertex there (valence 3), flagged next to a
  singularity;
* a closed stroke closes its chain with an edge from its last to its first vertex (its first vertex can
  be shared with other strokes' ends, like a Y).

Each chain carries three streamline ids (a bundle), so ``vertex_members`` looks like the real thing.
"""

from __future__ import annotations

import numpy as np

from stages.artifact import Artifact, pack_ragged

INK_THRESHOLD = 165.0 / 255.0   # the authors' band: grey < 165 (authors-implementation.md §3)


def _resample_polyline(pts: np.ndarray, spacing: float) -> np.ndarray:
    """Points about ``spacing`` apart along each segment, keeping every original vertex."""
    out = [pts[:1]]
    for a, b in zip(pts[:-1], pts[1:]):
        n = max(1, int(np.ceil(np.hypot(*(b - a)) / spacing)))
        t = np.arange(1, n + 1)[:, None] / n
        out.append(a + t * (b - a))
    return np.concatenate(out)


def _point_segment_distance(p: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Distance from (x, y) point ``p`` to every segment of polyline ``pts``; also the parameters."""
    a, b = pts[:-1], pts[1:]
    d = b - a
    ll = np.maximum((d * d).sum(1), 1e-12)
    t = np.clip(((p - a) * d).sum(1) / ll, 0, 1)
    return np.hypot(*(p - a - t[:, None] * d).T), t


def synthetic_field_roots(shape: tuple[int, int], strokes: list[np.ndarray], mask: np.ndarray,
                          width: float) -> np.ndarray:
    """A stand-in for the field stage's ``roots`` from exact centre lines.

    Root 0 is the tangent of the nearest stroke segment; root 1 the tangent of the nearest segment
    (of any stroke) running in a different direction (> 20°) within ``width/2 + 1.5`` px, else the
    normal.  complex64 (H, W, 2), 0 off the band.
    """
    h, w = shape
    ii, jj = np.nonzero(mask)
    pix = np.stack([jj + 0.5, ii + 0.5], axis=1)
    dists, dirs = [], []
    for s in strokes:
        for a, b in zip(s[:-1], s[1:]):
            d = b - a
            ll = max(float(d @ d), 1e-12)
            t = np.clip(((pix - a) @ d) / ll, 0, 1)
            dists.append(np.hypot(*(pix - a - t[:, None] * d).T))
            dirs.append(complex(*(d / np.sqrt(ll))))
    dists = np.array(dists)                     # (segments, pixels)
    dirs = np.array(dirs)
    order = np.argsort(dists, axis=0)
    r0 = dirs[order[0]]
    r1 = 1j * r0
    found = np.zeros(len(pix), bool)
    for k in range(1, len(dirs)):
        cand = dirs[order[k]]
        near = dists[order[k], np.arange(len(pix))] < width / 2 + 1.5
        differ = np.abs((np.conj(r0) * cand).real) < np.cos(np.deg2rad(20))
        take = near & differ & ~found
        r1[take] = cand[take]
        found |= take
    roots = np.zeros((h, w, 2), np.complex64)
    roots[ii, jj, 0] = r0
    roots[ii, jj, 1] = 0.9 * r1
    return roots


def synthetic_inputs(drawing, spacing: float = 1.0, keypoints=None, join_tol: float = 0.5) -> dict:
    """Artifacts ``prep``, ``field``, ``graph``, ``keypoints`` for a synthetic drawing.

    Parameters
    ----------
    drawing : stages.synthetic.Drawing
        Grey image, centre lines (x, y) and width; its ``keypoints`` are used unless given.
    spacing : float
        Vertex spacing along the chains (px).
    keypoints : list of (x, y, type), optional
        Overrides ``drawing.keypoints`` (e.g. an empty list, or a Y without its centre).
    join_tol : float
        Stroke ends closer than this to another stroke's end share a vertex (Y); closer than this to
        another stroke's interior they overshoot it (T).

    Returns
    -------
    dict of str to Artifact
        Keyword arguments for :func:`stages.topology.run`.
    """
    grey = np.asarray(drawing.grey, np.float32)
    shape = grey.shape
    mask = grey < INK_THRESHOLD
    strokes = [np.asarray(s, np.float64) for s in drawing.strokes]
    width = float(drawing.width)
    kps = drawing.keypoints if keypoints is None else keypoints

    xy: list[np.ndarray] = []
    roots: list[complex] = []
    members: list[set] = []
    flags: list[int] = []
    edges: list[tuple[int, int, int]] = []
    shared_ends: list[tuple[np.ndarray, int]] = []   # (point, vertex id) of stroke ends, for Y joins

    def vertex_at(p, root, ids):
        for q, vid in shared_ends:
            if np.hypot(*(p - q)) < join_tol:
                members[vid] |= set(ids)
                flags[vid] = 1
                return vid
        xy.append(p)
        roots.append(root)
        members.append(set(ids))
        flags.append(0)
        return len(xy) - 1

    for c, s in enumerate(strokes):
        closed = len(s) > 2 and np.hypot(*(s[0] - s[-1])) < 1e-9
        pts = s.copy()
        # T: an end on another stroke's interior overshoots it by half a width (the stem's traced
        # curves stop at the bar's far edge).
        for end, nxt in ((0, 1), (-1, -2)):
            if closed:
                break
            for o, other in enumerate(strokes):
                if o == c:
                    continue
                dist, t = _point_segment_distance(pts[end], other)
                k = int(np.argmin(dist))
                at_other_end = np.hypot(*(pts[end] - other[0])) < join_tol or np.hypot(*(pts[end] - other[-1])) < join_tol
                if dist[k] < join_tol and not at_other_end:
                    d = pts[end] - pts[nxt]
                    pts = np.insert(pts, len(pts) if end == -1 else 0, pts[end] + d / np.hypot(*d) * width / 2, axis=0)
                    break
        dense = _resample_polyline(pts, spacing)
        if closed:
            dense = dense[:-1]
        tang = np.gradient(dense, axis=0) if len(dense) > 1 else np.array([[1.0, 0.0]])
        tang /= np.maximum(np.hypot(*tang.T), 1e-12)[:, None]
        ids = (3 * c, 3 * c + 1, 3 * c + 2)
        vids = []
        for k, p in enumerate(dense):
            r = complex(*tang[k])
            is_end = k == 0 or (k == len(dense) - 1 and not closed)   # a closed stroke joins at its start
            vid = vertex_at(p, r, ids) if is_end else None
            if vid is None:
                xy.append(p)
                roots.append(r)
                members.append(set(ids))
                flags.append(0)
                vid = len(xy) - 1
            if is_end:
                shared_ends.append((p, vid))
            vids.append(vid)
        for a, b in zip(vids[:-1], vids[1:]):
            edges.append((a, b, 3 * c + 1))
        if closed:
            edges.append((vids[-1], vids[0], 3 * c + 1))

    e = np.array([(min(a, b), max(a, b)) for a, b, _ in edges], np.int32).reshape(-1, 2)
    e_curve = np.array([cid for _, _, cid in edges], np.int32)
    e, first = np.unique(e, axis=0, return_index=True)
    e_curve = e_curve[first]
    vm, vm_off = pack_ragged([np.array(sorted(m), np.int32) for m in members], np.int32)
    sl = []
    for c, s in enumerate(strokes):
        sl += [s.astype(np.float32)] * 3
    sl_xy, sl_off = pack_ragged(sl, np.float32)
    vxy = np.array(xy, np.float64).reshape(-1, 2)
    graph = Artifact(arrays={
        "vertex_xy": vxy,
        "vertex_width": np.full(len(vxy), width),
        "vertex_width_raw": np.full(len(vxy), width),
        "vertex_root": np.array(roots, np.complex64),
        "vertex_flags": np.array(flags, np.uint8),
        "edges": e,
        "edge_curve": e_curve,
        "vertex_members": vm, "vertex_members_offsets": vm_off,
        "streamline_xy": sl_xy.reshape(-1, 2), "streamline_xy_offsets": sl_off,
    }, data={"vertices": len(vxy), "edges": len(e)})
    field = Artifact(arrays={"roots": synthetic_field_roots(shape, strokes, mask, width),
                             "singular": np.zeros(shape, bool)})
    prep = Artifact(arrays={"grey": grey, "mask": mask}, data={"height": shape[0], "width": shape[1]})
    pts = np.array([(x, y) for x, y, _ in kps], np.float32).reshape(-1, 2)
    types = np.array([t for _, _, t in kps], np.int8)
    keypoints = Artifact(arrays={"points": pts, "types": types, "scores": np.ones(len(pts), np.float32)},
                         data={"points": [{"x": float(x), "y": float(y), "type": int(t), "score": 1.0}
                                          for x, y, t in kps]})
    return {"prep": prep, "field": field, "graph": graph, "keypoints": keypoints}


def ladder(n_rungs: int, gap: float = 8.0, height: float = 24.0, width: float = 2.0):
    """Two rails and ``n_rungs`` rungs meeting at shared ends: one component with ``n_rungs`` cycles.

    Keypoints only at the four rail ends, so every cycle must come from the coverage loop — the kind
    of component on which the authors' constrained path search gives up.
    """
    from stages.synthetic import Drawing, render

    xs = 10 + gap * np.arange(n_rungs + 2)
    top, bot = 10.0, 10.0 + height
    strokes = []
    for a, b in zip(xs[:-1], xs[1:]):
        strokes += [np.array([[a, top], [b, top]]), np.array([[a, bot], [b, bot]])]
    strokes += [np.array([[x, top], [x, bot]]) for x in xs[1:-1]]
    shape = (int(bot + 12), int(xs[-1] + 12))
    kps = [(xs[0], top, 1), (xs[-1], top, 1), (xs[0], bot, 1), (xs[-1], bot, 1)]
    return Drawing(render(shape, strokes, width), strokes, width, kps)
