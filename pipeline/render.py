"""Render stored artifacts over their drawing (PNG), for ``polyvec-inspect render``.

Each stage package may expose its own renderer (``render_field``, ``render_keypoints``,
``render_graph``, ``render_topology``); curves of flow/select/export are drawn here.
"""

from __future__ import annotations

import numpy as np

from pipeline.engine.store import ArtifactStore
from stages.artifact import unpack_ragged
from stages.prep import to_internal

PALETTE = np.array([[230, 25, 75], [60, 180, 75], [0, 130, 200], [245, 130, 48], [145, 30, 180],
                    [70, 160, 160], [240, 50, 230], [128, 128, 0], [0, 0, 128], [170, 110, 40]], np.uint8)


def grey_to_rgb(grey: np.ndarray, scale: int = 1, fade: float = 0.5) -> np.ndarray:
    """The drawing as a faded RGB background, upscaled by ``scale`` (nearest)."""
    g = (255 * (1 - fade * (1 - np.clip(grey, 0, 1)))).astype(np.uint8)
    if scale > 1:
        g = np.repeat(np.repeat(g, scale, 0), scale, 1)
    return np.stack([g, g, g], axis=-1)


def draw_polylines(rgb: np.ndarray, polylines, scale: int, colors=None, dots: bool = True) -> np.ndarray:
    """Draw (x, y) polylines (pixel-corner origin) onto an image upscaled by ``scale``."""
    from skimage.draw import disk, line_aa

    h, w = rgb.shape[:2]
    out = rgb.astype(np.float64)
    for k, pts in enumerate(polylines):
        pts = np.asarray(pts, dtype=np.float64) * scale
        if len(pts) == 0:
            continue
        color = np.asarray(colors[k] if colors is not None else PALETTE[k % len(PALETTE)], np.float64)
        for a, b in zip(pts[:-1], pts[1:]):
            rr, cc, val = line_aa(int(round(a[1])), int(round(a[0])), int(round(b[1])), int(round(b[0])))
            ok = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
            rr, cc, val = rr[ok], cc[ok], val[ok][:, None]
            out[rr, cc] = out[rr, cc] * (1 - val) + color * val
        if dots:
            for p in (pts[0], pts[-1]):
                rr, cc = disk((p[1], p[0]), max(2, scale), shape=(h, w))
                out[rr, cc] = color
    return out.astype(np.uint8)


def _curves(store: ArtifactStore, stage: str, key: str, manifest: dict, prep_data: dict | None = None):
    """Polylines and their labels for flow / select / export artifacts, in prep's pixels.

    ``prep_data``: prep's ``data`` (its scale and crop origin, :func:`~stages.prep.to_internal`);
    exported curves are in the drawing's pixels, the others (and the picture) in prep's.
    """
    if stage == "export":
        art = store.load(stage, key)
        return [to_internal(c["points"], prep_data or {}) for c in art.data["curves"]]
    if stage == "flow":
        art = store.load(stage, key)
        return unpack_ragged(art["curve_xy"], art["curve_xy_offsets"])
    if stage == "select":
        flow_key = manifest["inputs"]["flow"]
        flow = store.load("flow", flow_key)
        curves = unpack_ragged(flow["curve_xy"], flow["curve_xy_offsets"])
        chosen = store.load(stage, key).data["chosen"]
        return [curves[i] for i in chosen]
    raise ValueError(stage)


def render_artifact(store: ArtifactStore, stage: str, key: str, scale: int = 2) -> np.ndarray:
    """RGB uint8 image of one artifact drawn over its drawing.

    Parameters
    ----------
    store : ArtifactStore
    stage, key : str
        The artifact.
    scale : int
        Upscaling of the drawing, so thin curves stay visible (every stage's picture is
        ``scale`` × the drawing's size).
    """
    manifest = store.manifest(stage, key)
    prep_key = key if stage == "prep" else _find_input(store, manifest, "prep")
    prep = store.load("prep", prep_key)
    grey = prep["grey"]
    if stage == "prep":
        rgb = grey_to_rgb(grey, 1, fade=0.3)
        rgb[prep["mask"]] = (0.5 * rgb[prep["mask"]] + np.array([0, 0, 120])).astype(np.uint8)
        return np.repeat(np.repeat(rgb, scale, 0), scale, 1)
    art = store.load(stage, key)
    if stage == "field":
        from stages.field import render_field

        return render_field(grey, art["roots"], prep["mask"], scale=scale)
    if stage == "extension":   # the directions carried into the ring (tinted: band and ring)
        from stages.field import polyvector_roots, render_field

        c0, c2 = np.asarray(art["c0_ext"]), np.asarray(art["c2_ext"])
        return render_field(grey, polyvector_roots(c0, c2), (c0 != 0) | (c2 != 0), scale=scale)
    if stage == "keypoints":
        from stages.keypoints import render_keypoints

        rgb = render_keypoints(grey, art["heatmaps"], art["points"], art["types"])
        return np.repeat(np.repeat(rgb, scale, 0), scale, 1)
    if stage == "graph":
        from stages.graph import render_graph

        return render_graph(grey, art.arrays, scale=scale)
    if stage == "topology":
        from stages.topology import render_topology

        return render_topology(grey, art, scale=scale)
    rgb = grey_to_rgb(grey, scale)
    return draw_polylines(rgb, _curves(store, stage, key, manifest, prep.data), scale)


def _find_input(store: ArtifactStore, manifest: dict, stage: str) -> str:
    """Key of an upstream artifact, following the manifests' input keys."""
    inputs = manifest.get("inputs", {})
    if stage in inputs:
        return inputs[stage]
    for name, key in inputs.items():
        if name != "image" and store.exists(name, key):
            found = _find_input(store, store.manifest(name, key), stage)
            if found:
                return found
    raise KeyError(f"no {stage} artifact upstream of {manifest.get('stage')}/{manifest.get('key')}")
