"""Picture of the graph artifact over the drawing (for ``polyvec-inspect`` and for looking at results)."""

from __future__ import annotations

import numpy as np

from stages.artifact import unpack_ragged

_STREAMLINE = (250, 222, 120)
_EDGE = (30, 90, 230)
_ADDED_EDGE = (0, 170, 0)
_VERTEX = (220, 30, 60)
_SINGULAR = (150, 0, 200)


def render_graph(grey: np.ndarray, artifact_arrays: dict, scale: int | None = None,
                 draw_streamlines: bool = True, max_streamline_points: int = 400_000) -> np.ndarray:
    """Draw streamlines, vertices (circles of diameter = stroke width) and edges over the drawing.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) in [0, 1], 1 = white (the prep artifact's ``grey``).
    artifact_arrays : dict
        The graph artifact's arrays (``vertex_xy``, ``vertex_width``, ``vertex_flags``, ``edges``,
        ``edge_curve``, ``streamline_xy``, ``streamline_xy_offsets``); missing entries are skipped.
    scale : int, optional
        Integer magnification; default: the largest of 1..4 keeping the long side ≤ 2400 px.
    draw_streamlines : bool
        Draw the traced curves (thin yellow) under the graph.
    max_streamline_points : int
        Subsample the streamlines beyond this many points so huge drawings stay quick to draw.

    Returns
    -------
    numpy.ndarray
        uint8 (H·scale, W·scale, 3) RGB.  Edges are blue (green: edges added by the clean-up),
        vertices red circles (purple: next to a singularity).
    """
    from PIL import Image, ImageDraw

    g = np.clip(np.asarray(grey, dtype=np.float64), 0, 1)
    h, w = g.shape
    if scale is None:
        scale = int(max(1, min(4, 2400 // max(h, w, 1))))
    scale = max(1, int(scale))
    base = (255 - 0.45 * (255 - g * 255)).astype(np.uint8)  # faded drawing
    img = Image.fromarray(np.repeat(base[..., None], 3, axis=2)).resize((w * scale, h * scale), Image.NEAREST)
    draw = ImageDraw.Draw(img)
    a = artifact_arrays

    def pt(p):
        return (float(p[0]) * scale, float(p[1]) * scale)

    if draw_streamlines and "streamline_xy" in a and "streamline_xy_offsets" in a:
        flat = np.asarray(a["streamline_xy"])
        stride = max(1, int(np.ceil(len(flat) / max_streamline_points)))
        for c in unpack_ragged(flat, np.asarray(a["streamline_xy_offsets"])):
            c = c[::stride] if len(c) > 2 * stride else c
            if len(c) >= 2:
                draw.line([pt(p) for p in c], fill=_STREAMLINE, width=1)
    xy = np.asarray(a.get("vertex_xy", np.zeros((0, 2))), dtype=np.float64)
    width = np.asarray(a.get("vertex_width", np.zeros(len(xy))), dtype=np.float64)
    flags = np.asarray(a.get("vertex_flags", np.zeros(len(xy), np.uint8)))
    edges = np.asarray(a.get("edges", np.zeros((0, 2), np.int32)))
    ecurve = np.asarray(a.get("edge_curve", np.zeros(len(edges), np.int32)))
    # stroke discs (diameter = width) as a translucent layer, then edges and vertex dots on top
    discs = Image.new("RGBA", img.size, (0, 0, 0, 0))
    ddraw = ImageDraw.Draw(discs)
    for p, wd, f in zip(xy, width, flags):
        r = max(0.5, wd / 2) * scale
        cx, cy = pt(p)
        ddraw.ellipse([cx - r, cy - r, cx + r, cy + r], fill=(*(_SINGULAR if f & 1 else _VERTEX), 28))
    img = Image.alpha_composite(img.convert("RGBA"), discs).convert("RGB")
    draw = ImageDraw.Draw(img)
    lw = max(1, scale // 3)
    for (i, j), c in zip(edges, ecurve):
        draw.line([pt(xy[i]), pt(xy[j])], fill=_ADDED_EDGE if c < 0 else _EDGE, width=lw)
    rd = max(1.0, scale / 3)
    for p, f in zip(xy, flags):
        cx, cy = pt(p)
        draw.ellipse([cx - rd, cy - rd, cx + rd, cy + rd], fill=_SINGULAR if f & 1 else _VERTEX)
    return np.asarray(img, dtype=np.uint8)
