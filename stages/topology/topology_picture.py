"""Picture of a topology artifact over its drawing (for ``polyvec-inspect render``)."""

from __future__ import annotations

import colorsys

import numpy as np

#: key vertex colours by keypoint type (paper Fig. 5: endpoints blue, junctions orange, corners green)
TYPE_COLOURS = {1: (30, 90, 255), 3: (255, 140, 0), 5: (0, 170, 60), 0: (120, 120, 120)}


def _distinct_colour(k: int) -> tuple[int, int, int]:
    h = (0.13 + 0.618033988749895 * k) % 1.0
    r, g, b = colorsys.hsv_to_rgb(h, 0.85, 0.85)
    return int(255 * r), int(255 * g), int(255 * b)


def render_topology(grey: np.ndarray, topology, scale: int | None = None) -> np.ndarray:
    """Draw key vertices, Steiner trees and candidate paths over the drawing.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) in [0, 1], 1 = white.
    topology : stages.artifact.Artifact
        The topology artifact (data ``paths``, ``key_vertices``; array ``steiner_segments``).
    scale : int, optional
        Magnification; default makes the longer side about 1200 px (at least 1).

    Returns
    -------
    numpy.ndarray
        uint8 (H·scale, W·scale, 3).  Faded drawing; Steiner tree edges as broad pale-red bands;
        every candidate path as a thin line in its own colour, offset sideways by a fraction of a
        pixel per path so that overlapping candidates stay distinguishable; key vertices as discs
        (blue endpoint, orange junction, green corner, grey synthetic), black-rimmed.
    """
    from PIL import Image, ImageDraw

    g = np.clip(np.asarray(grey, np.float64), 0, 1)
    h, w = g.shape
    if scale is None:
        scale = max(1, int(round(1200 / max(h, w, 1))))
    scale = max(1, int(scale))
    base = (255 * (1 - 0.35 * (1 - g))).astype(np.uint8)
    base = np.repeat(np.repeat(base, scale, 0), scale, 1)
    img = Image.fromarray(np.stack([base] * 3, axis=-1), "RGB")
    draw = ImageDraw.Draw(img)
    seg = np.asarray(topology.arrays.get("steiner_segments", np.zeros((0, 4))), np.float64).reshape(-1, 4)
    for x0, y0, x1, y1 in seg * scale:
        draw.line([x0, y0, x1, y1], fill=(255, 170, 170), width=max(3, 2 * scale))
    paths = topology.data.get("paths", [])
    line_w = max(1, scale // 3)
    for k, p in enumerate(paths):
        xy = np.asarray(p["xy"], np.float64).reshape(-1, 2)
        if len(xy) < 2:
            continue
        shift = ((k % 5) - 2) * 0.12 * scale
        xy = xy * scale + shift
        draw.line([tuple(q) for q in xy], fill=_distinct_colour(k), width=line_w)
    rad = max(2.5, 0.9 * scale)
    for kv in topology.data.get("key_vertices", []):
        x, y = kv["xy"][0] * scale, kv["xy"][1] * scale
        col = TYPE_COLOURS.get(int(kv["type"]), (0, 0, 0))
        draw.ellipse([x - rad, y - rad, x + rad, y + rad], fill=col, outline=(0, 0, 0))
    return np.asarray(img)
