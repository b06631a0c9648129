"""Readers of human strokes for training: Quick, Draw! ndjson, sketch-rnn stroke-3 (Omniglot) and SVG
paths, and :func:`fit_strokes`, which places a drawing on a square canvas.

The strokes are styled and labelled like the procedural drawings by
:func:`stages.keypoints.training.generator.drawing_from_strokes`. Points are (x, y), pixel units,
origin at the top-left corner of the image.
"""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np


def read_quickdraw_ndjson(path: str | Path, limit: int | None = None) -> list[list[np.ndarray]]:
    """Read Quick, Draw! drawings (raw or simplified ndjson).

    Parameters
    ----------
    path : str or Path
        An ``.ndjson`` file; each line is a JSON object whose ``drawing`` is a list of strokes
        ``[xs, ys]`` or ``[xs, ys, ts]``.
    limit : int, optional
        Read at most this many drawings.

    Returns
    -------
    list of list of numpy.ndarray
        Per drawing, its strokes as (n, 2) arrays in the file's (x, y) units.
    """
    out = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            line = line.strip()
            if not line:
                continue
            rec = json.loads(line)
            strokes = [np.stack([np.asarray(s[0], float), np.asarray(s[1], float)], 1)
                       for s in rec["drawing"] if len(s[0]) > 0]
            if strokes:
                out.append(strokes)
            if limit is not None and len(out) >= limit:
                break
    return out


_NUM = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_CMD = re.compile(r"([MmLlHhVvCcSsQqTtAaZz])([^MmLlHhVvCcSsQqTtAaZz]*)")


def read_stroke3(path: str | Path, split: str) -> list[list[np.ndarray]]:
    """Read stroke-3 drawings (sketch-rnn format: rows ``[dx, dy, pen_lifted]``) from an ``.npz``.

    Parameters
    ----------
    path : str or Path
        An ``.npz`` with one object array per split (Omniglot: ``train``, ``valid``, ``test``).
    split : str
        Which array to read.

    Returns
    -------
    list of list of numpy.ndarray
        Per drawing, its strokes as (n, 2) arrays of absolute (x, y); a stroke ends at a row whose
        ``pen_lifted`` is 1.
    """
    with np.load(path, allow_pickle=True, encoding="latin1") as data:
        if split not in data.files:
            raise ValueError(f"{path}: no split {split!r} (has {', '.join(data.files)})")
        arrays = data[split]
    out = []
    for a in arrays:
        a = np.asarray(a, float)
        if len(a) == 0:
            continue
        xy = np.cumsum(a[:, :2], axis=0)
        ends = np.flatnonzero(a[:, 2] > 0) + 1
        strokes = [s for s in np.split(xy, ends) if len(s)]
        if strokes:
            out.append(strokes)
    return out


def _parse_transform(text: str | None) -> np.ndarray:
    """SVG transform attribute → 3×3 matrix."""
    m = np.eye(3)
    if not text:
        return m
    for name, args in re.findall(r"(\w+)\s*\(([^)]*)\)", text):
        v = [float(x) for x in _NUM.findall(args)]
        t = np.eye(3)
        if name == "matrix" and len(v) == 6:
            t[:2] = [[v[0], v[2], v[4]], [v[1], v[3], v[5]]]
        elif name == "translate":
            t[0, 2], t[1, 2] = v[0], (v[1] if len(v) > 1 else 0.0)
        elif name == "scale":
            t[0, 0], t[1, 1] = v[0], (v[1] if len(v) > 1 else v[0])
        elif name == "rotate":
            a = np.radians(v[0])
            r = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
            if len(v) == 3:
                c1, c2 = np.eye(3), np.eye(3)
                c1[:2, 2], c2[:2, 2] = v[1:], [-v[1], -v[2]]
                r = c1 @ r @ c2
            t = r
        m = m @ t
    return m


def _bezier(p: np.ndarray, n: int = 12) -> np.ndarray:
    """Sample a Bézier curve of control points ``p`` (k, 2) at ``n`` + 1 points."""
    t = np.linspace(0, 1, n + 1)[:, None]
    pts = p.copy()
    out = np.zeros((len(t), 2))
    # de Casteljau, vectorised over t
    q = np.repeat(pts[None], len(t), axis=0)
    for k in range(len(p) - 1, 0, -1):
        q = (1 - t[:, :, None]) * q[:, :k] + t[:, :, None] * q[:, 1:k + 1]
    out[:] = q[:, 0]
    return out


def _path_strokes(d: str) -> list[np.ndarray]:
    """Polylines of an SVG path's subpaths (curves sampled, arcs as chords)."""
    strokes, cur = [], []
    pos = np.zeros(2)
    start = np.zeros(2)
    last_ctrl = None
    for cmd, args in _CMD.findall(d):
        v = [float(x) for x in _NUM.findall(args)]
        rel = cmd.islower()
        c = cmd.upper()
        if c == "Z":
            if cur:
                cur.append(start.copy())
                strokes.append(np.array(cur))
            cur, pos, last_ctrl = [], start.copy(), None
            continue
        step = {"M": 2, "L": 2, "H": 1, "V": 1, "C": 6, "S": 4, "Q": 4, "T": 2, "A": 7}[c]
        for k in range(0, len(v) - step + 1, step):
            a = np.array(v[k:k + step])
            base = pos if rel else np.zeros(2)
            if c == "M" and k == 0:
                if len(cur) > 1:
                    strokes.append(np.array(cur))
                pos = base + a
                start = pos.copy()
                cur = [pos.copy()]
                last_ctrl = None
                continue
            if c in ("M", "L", "T", "A"):
                new = base + a[-2:]
                cur.append(new.copy())
                last_ctrl = None
            elif c == "H":
                new = np.array([(pos[0] if rel else 0) + a[0], pos[1]])
                cur.append(new.copy())
            elif c == "V":
                new = np.array([pos[0], (pos[1] if rel else 0) + a[0]])
                cur.append(new.copy())
            else:
                if c == "C":
                    ctrl = np.array([pos, base + a[0:2], base + a[2:4], base + a[4:6]])
                elif c == "S":
                    c1 = 2 * pos - last_ctrl if last_ctrl is not None else pos
                    ctrl = np.array([pos, c1, base + a[0:2], base + a[2:4]])
                else:  # Q
                    ctrl = np.array([pos, base + a[0:2], base + a[2:4]])
                cur.extend(_bezier(ctrl)[1:])
                new = ctrl[-1]
                last_ctrl = ctrl[-2]
            pos = new
    if len(cur) > 1:
        strokes.append(np.array(cur))
    return strokes


def read_svg_strokes(path: str | Path) -> tuple[list[np.ndarray], tuple[float, float]]:
    """Read the strokes of an SVG file (paths, polylines, lines), with nested transforms applied.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    strokes : list of numpy.ndarray
        Polylines (n, 2) in the SVG's user units.
    size : (width, height)
        From the viewBox (or width/height attributes; the strokes' extent when both are absent).
    """
    root = ET.parse(path).getroot()
    strokes: list[np.ndarray] = []

    def visit(el, m):
        m = m @ _parse_transform(el.get("transform"))
        tag = el.tag.rsplit("}", 1)[-1]
        local: list[np.ndarray] = []
        if tag == "path" and el.get("d"):
            local = _path_strokes(el.get("d"))
        elif tag in ("polyline", "polygon") and el.get("points"):
            v = np.array([float(x) for x in _NUM.findall(el.get("points"))]).reshape(-1, 2)
            local = [np.vstack([v, v[:1]]) if tag == "polygon" else v]
        elif tag == "line":
            local = [np.array([[float(el.get(k, 0)) for k in ("x1", "y1")], [float(el.get(k, 0)) for k in ("x2", "y2")]])]
        elif tag in ("image", "defs", "clipPath", "mask", "pattern", "style"):
            return
        for s in local:
            if len(s) >= 2:
                strokes.append(s @ m[:2, :2].T + m[:2, 2])
        for ch in el:
            visit(ch, m)

    visit(root, np.eye(3))
    vb = root.get("viewBox")
    if vb:
        v = [float(x) for x in _NUM.findall(vb)]
        size = (v[2], v[3])
    elif root.get("width") and root.get("height"):
        size = (float(_NUM.findall(root.get("width"))[0]), float(_NUM.findall(root.get("height"))[0]))
    else:
        allp = np.concatenate(strokes) if strokes else np.zeros((1, 2))
        size = tuple(float(x) for x in allp.max(axis=0))
    return strokes, size


def fit_strokes(strokes: list[np.ndarray], size: int, margin: float = 16.0) -> list[np.ndarray]:
    """Translate and scale strokes to fill a ``size``×``size`` canvas with ``margin`` px on each side.

    The authors normalise their doodles the same way (longer side to 255 px inside a 288 canvas).
    """
    allp = np.concatenate(strokes)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    span = max(float((hi - lo).max()), 1e-6)
    k = (size - 2 * margin) / span
    off = (size - k * (hi - lo)) / 2
    return [(s - lo) * k + off for s in strokes]
