"""Polylines from SVG text (ground-truth SVGs, reference outputs), for scoring.

Reads ``<polyline>``, ``<polygon>``, ``<line>`` and ``<path>`` (commands M, L, H, V, C, S, Q, T, Z,
absolute and relative; curves flattened into short chords). ``<image>`` underlays and everything
else are ignored. A ``transform`` attribute anywhere raises ``ValueError``: scoring geometry that was
silently misplaced would be worse than not scoring it. Coordinates are returned as written, in user
units (callers scale by the viewBox when it differs from the image size; see :func:`svg_size`).
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

import numpy as np

__all__ = ["parse_svg_polylines", "svg_size"]

_NUM = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_TOKEN = re.compile(r"[MmLlHhVvCcSsQqTtAaZz]|[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _floats(text: str | None) -> list[float]:
    return [float(v) for v in _NUM.findall(text or "")]


def svg_size(text: str) -> tuple[float, float, tuple[float, float, float, float] | None]:
    """Width, height (user units, from width/height or the viewBox) and the viewBox if present."""
    root = ET.fromstring(text)
    vb = _floats(root.get("viewBox"))
    viewbox = tuple(vb) if len(vb) == 4 else None

    def dim(name: str, idx: int) -> float:
        v = root.get(name, "")
        if v and not v.strip().endswith("%"):
            f = _floats(v)
            if f:
                return f[0]
        return float(viewbox[idx]) if viewbox else float("nan")

    return dim("width", 2), dim("height", 3), viewbox


def _bezier(p: list[np.ndarray], n: int) -> np.ndarray:
    t = np.linspace(0.0, 1.0, n + 1)[1:, None]
    if len(p) == 3:
        return (1 - t) ** 2 * p[0] + 2 * (1 - t) * t * p[1] + t**2 * p[2]
    return (1 - t) ** 3 * p[0] + 3 * (1 - t) ** 2 * t * p[1] + 3 * (1 - t) * t**2 * p[2] + t**3 * p[3]


def _path_polylines(d: str, chord_px: float) -> list[np.ndarray]:
    toks = _TOKEN.findall(d)
    out: list[np.ndarray] = []
    cur: list[np.ndarray] = []
    pos = np.zeros(2)
    start = np.zeros(2)
    last_ctrl = None
    cmd = None
    i = 0

    def nums(k: int) -> list[float]:
        nonlocal i
        vals = [float(v) for v in toks[i:i + k]]
        if len(vals) < k or any(re.fullmatch(r"[A-Za-z]", v) for v in toks[i:i + k]):
            raise ValueError(f"malformed path data near {' '.join(toks[i:i + k])!r}")
        i += k
        return vals

    def flush():
        nonlocal cur
        if len(cur) >= 1:
            out.append(np.array(cur))
        cur = []

    while i < len(toks):
        if re.fullmatch(r"[A-Za-z]", toks[i]):
            cmd = toks[i]
            i += 1
            if cmd in "Zz":
                if cur:
                    cur.append(start.copy())
                pos = start.copy()
                flush()
                last_ctrl = None
                continue
        if cmd is None:
            raise ValueError("path data must start with a command")
        rel = cmd.islower()
        base = pos if rel else np.zeros(2)
        c = cmd.upper()
        if c == "M":
            flush()
            pos = base + nums(2)
            start = pos.copy()
            cur = [pos.copy()]
            cmd = "l" if rel else "L"  # implicit lineto after the first pair
            last_ctrl = None
        elif c in "LHV":
            if c == "L":
                pos = base + nums(2)
            elif c == "H":
                pos = np.array([(pos[0] if rel else 0.0) + nums(1)[0], pos[1]])
            else:
                pos = np.array([pos[0], (pos[1] if rel else 0.0) + nums(1)[0]])
            cur = cur or [start.copy()]
            cur.append(pos.copy())
            last_ctrl = None
        elif c in "CSQT":
            # last_ctrl = (control point next to the current point, "C" or "Q") for reflections
            if c == "C":
                v = nums(6)
                ctrl = [pos, base + v[0:2], base + v[2:4], base + v[4:6]]
            elif c == "S":
                v = nums(4)
                c1 = 2 * pos - last_ctrl[0] if last_ctrl is not None and last_ctrl[1] == "C" else pos
                ctrl = [pos, c1, base + v[0:2], base + v[2:4]]
            elif c == "Q":
                v = nums(4)
                ctrl = [pos, base + v[0:2], base + v[2:4]]
            else:
                v = nums(2)
                c1 = 2 * pos - last_ctrl[0] if last_ctrl is not None and last_ctrl[1] == "Q" else pos
                ctrl = [pos, c1, base + v[0:2]]
            poly_len = sum(np.hypot(*(b - a)) for a, b in zip(ctrl[:-1], ctrl[1:]))
            pts = _bezier([np.asarray(q, dtype=np.float64) for q in ctrl], max(2, int(np.ceil(poly_len / chord_px))))
            cur = cur or [pos.copy()]
            cur.extend(pts)
            pos = pts[-1].copy()
            last_ctrl = (ctrl[-2], "C" if len(ctrl) == 4 else "Q")
        elif c == "A":
            v = nums(7)  # arcs approximated by their chord: rare in line-drawing SVGs
            pos = base + v[5:7]
            cur = cur or [start.copy()]
            cur.append(pos.copy())
            last_ctrl = None
        else:
            raise ValueError(f"unsupported path command {cmd!r}")
    flush()
    return out


def parse_svg_polylines(text: str, chord_px: float = 0.5) -> list[np.ndarray]:
    """The drawn strokes of an SVG document as polylines.

    Parameters
    ----------
    text : str
        SVG document.
    chord_px : float
        Length of the chords that flatten Bézier segments (user units).

    Returns
    -------
    list of numpy.ndarray
        (n, 2) arrays in the SVG's user coordinates (x right, y down).

    Raises
    ------
    ValueError
        On malformed XML or path data, or when an element carries a ``transform``.
    """
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ValueError(f"not an SVG document: {exc}") from None
    out: list[np.ndarray] = []
    for el in root.iter():
        tag = _local(el.tag)
        if tag in ("image", "defs", "clipPath", "mask", "pattern", "symbol"):
            continue
        if el.get("transform"):
            raise ValueError(f"SVG element <{tag}> has a transform, which is not supported")
        if tag in ("polyline", "polygon"):
            v = _floats(el.get("points"))
            p = np.array(v[: len(v) // 2 * 2], dtype=np.float64).reshape(-1, 2)
            if tag == "polygon" and len(p):
                p = np.vstack([p, p[:1]])
            if len(p):
                out.append(p)
        elif tag == "line":
            out.append(np.array([[float(el.get(k, 0)) for k in ("x1", "y1")],
                                 [float(el.get(k, 0)) for k in ("x2", "y2")]]))
        elif tag == "path":
            out.extend(_path_polylines(el.get("d", ""), chord_px))
    return out
