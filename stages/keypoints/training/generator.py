"""Procedural training drawings with exact vector ground truth (paper Appendix B "Dataset").

The authors trained on 927 k rasterised doodles (Quick, Draw!, Creative Birds) styled by Illustrator
brushes. Those data are not ours to ship, so the shipped model is trained on drawings made here from
random primitives — smooth open curves, polylines with sharp corners, closed loops, X-, T- and
Y-junctions, strokes meeting end to end with or without a turn, rounded bends — with hand jitter, pressure-modulated
widths of 1–12 px, clean ink or pencil-like grain, blur, paper noise, random rotation and scale. The
keypoints are derived from the final centre lines by :func:`stages.keypoints.training.labels.label_keypoints`
(the rules of reference/metrics.md §4.2), never placed by hand, so the labels follow the same rules
as the evaluation set.

Users who have vector data can mix it in: the readers of :mod:`stages.keypoints.training.human_strokes`
turn Quick, Draw! ndjson, stroke-3 and SVG files into strokes, which :func:`drawing_from_strokes`
styles and labels exactly like the procedural ones.

Points are (x, y), pixel units, origin at the top-left corner of the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import ndimage

from stages.keypoints.training.config import GeneratorConfig, LabelRules
from stages.keypoints.training.labels import label_keypoints


@dataclass
class Sample:
    """One rendered drawing and its labels.

    Attributes
    ----------
    grey : numpy.ndarray
        float32 (H, W), 1 = white paper.
    strokes : list of numpy.ndarray
        Centre lines (n, 2) in (x, y).
    widths : list of numpy.ndarray
        Per-vertex widths (n,) of each stroke.
    points : numpy.ndarray
        (N, 2) keypoints in (x, y).
    types : numpy.ndarray
        int8 (N,) keypoint codes 1, 3, 5.
    """

    grey: np.ndarray
    strokes: list
    widths: list
    points: np.ndarray
    types: np.ndarray


# ------------------------------------------------------------------------------------------------
# Rendering


@njit(cache=True)
def _render_segments(h, w, ax, ay, bx, by, wa, wb, dark, ink):  # pragma: no cover - numba
    """Max-composite anti-aliased capsules (segment a→b, width interpolated) into ``ink``."""
    for k in range(ax.shape[0]):
        half = 0.5 * max(wa[k], wb[k]) + 1.0
        x0 = max(int(np.floor(min(ax[k], bx[k]) - half)), 0)
        x1 = min(int(np.ceil(max(ax[k], bx[k]) + half)), w - 1)
        y0 = max(int(np.floor(min(ay[k], by[k]) - half)), 0)
        y1 = min(int(np.ceil(max(ay[k], by[k]) + half)), h - 1)
        dx, dy = bx[k] - ax[k], by[k] - ay[k]
        ll = dx * dx + dy * dy
        for i in range(y0, y1 + 1):
            py = i + 0.5
            for j in range(x0, x1 + 1):
                px = j + 0.5
                t = 0.0
                if ll > 0:
                    t = ((px - ax[k]) * dx + (py - ay[k]) * dy) / ll
                    t = min(max(t, 0.0), 1.0)
                qx = px - ax[k] - t * dx
                qy = py - ay[k] - t * dy
                d = np.sqrt(qx * qx + qy * qy)
                ww = wa[k] + t * (wb[k] - wa[k])
                c = min(max(0.5 * ww + 0.5 - d, 0.0), 1.0) * dark[k]
                if c > ink[i, j]:
                    ink[i, j] = c


def render_strokes(shape: tuple[int, int], strokes: list[np.ndarray], widths: list[np.ndarray],
                   darkness: list[float] | None = None) -> np.ndarray:
    """Anti-aliased ink coverage of strokes with per-vertex widths.

    Parameters
    ----------
    shape : (H, W)
    strokes : list of numpy.ndarray
        Centre lines (n, 2) in (x, y).
    widths : list of numpy.ndarray
        Per-vertex widths (n,).
    darkness : list of float, optional
        Per-stroke ink darkness in [0, 1] (default 1).

    Returns
    -------
    numpy.ndarray
        float64 (H, W) ink in [0, 1] (0 = paper).
    """
    h, w = shape
    parts = []
    for k, (s, wd) in enumerate(zip(strokes, widths)):
        s = np.asarray(s, np.float64)
        wd = np.broadcast_to(np.asarray(wd, np.float64), (len(s),))
        if len(s) == 1:
            s, wd = np.repeat(s, 2, axis=0), np.repeat(wd, 2)
        dk = 1.0 if darkness is None else float(darkness[k])
        parts.append(np.column_stack([s[:-1], s[1:], wd[:-1], wd[1:], np.full(len(s) - 1, dk)]))
    ink = np.zeros((h, w))
    if parts:
        a = np.concatenate(parts)
        _render_segments(h, w, *[np.ascontiguousarray(a[:, c]) for c in range(7)], ink)
    return ink


def stylise(ink: np.ndarray, rng: np.random.Generator, cfg: GeneratorConfig, pencil: bool) -> np.ndarray:
    """Turn ink coverage into a grey image: grain, blur, paper tone and noise.

    Returns
    -------
    numpy.ndarray
        float32 (H, W), 1 = white.
    """
    h, w = ink.shape
    if pencil:
        # Pencil grain: ink deposits vary at the scale of a pixel or two.
        grain = ndimage.gaussian_filter(rng.random((h, w)), rng.uniform(0.5, 1.2))
        grain = (grain - grain.mean()) / (grain.std() + 1e-9)
        ink = ink * np.clip(1.0 - rng.uniform(0.1, 0.35) * grain, 0.0, 1.0)
    blur = rng.uniform(0.0, cfg.blur_max)
    if blur > 0.15:
        ink = ndimage.gaussian_filter(ink, blur)
    paper = rng.uniform(0.85, 1.0) if rng.random() < 0.5 else 1.0
    if rng.random() < 0.3:  # uneven lighting / paper tone
        yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
        paper = paper - rng.uniform(0, 0.08) * (np.cos(rng.uniform(0, 6.3)) * xx + np.sin(rng.uniform(0, 6.3)) * yy)
    grey = paper * (1.0 - ink)
    noise = rng.uniform(0.0, cfg.paper_noise_max)
    if noise > 0.005:
        grey = grey + rng.normal(0.0, noise, (h, w))
    if rng.random() < 0.1:  # salt and pepper specks
        m = rng.random((h, w)) < rng.uniform(0.0005, 0.003)
        grey[m] = rng.random(int(m.sum()))
    return np.clip(grey, 0.0, 1.0).astype(np.float32)


# ------------------------------------------------------------------------------------------------
# Primitives (all in a unit-free frame; lengths in px at the final scale)


def _smooth_noise(rng, n: int, scale: float, amp: float) -> np.ndarray:
    """Low-frequency 1-D noise of ``n`` samples with correlation length ``scale`` samples."""
    if amp <= 0 or n < 2:
        return np.zeros(n)
    k = max(int(n / max(scale, 1.0)) + 2, 3)
    knots = rng.normal(0, amp, k)
    return np.interp(np.linspace(0, k - 1, n), np.arange(k), knots)


def _curve(rng, start, heading, length, curvature, wiggle, step=1.5) -> np.ndarray:
    """A smooth open curve: heading integrates a curvature that drifts slowly."""
    n = max(int(length / step), 2)
    kappa = curvature + _smooth_noise(rng, n, n / rng.uniform(1, 4), wiggle)
    ang = heading + np.cumsum(kappa * step)
    pts = np.cumsum(np.stack([np.cos(ang), np.sin(ang)], 1) * step, axis=0)
    return np.vstack([start, start + pts])


def _polyline(rng, start, heading, n_seg, seg_len, sharp_prob) -> np.ndarray:
    """A polyline whose turns are sharp (60–170°) or mild (<30°) at random."""
    pts = [np.asarray(start, float)]
    ang = heading
    for k in range(n_seg):
        L = rng.uniform(*seg_len)
        pts.append(pts[-1] + L * np.array([np.cos(ang), np.sin(ang)]))
        # Sharp and mild turns overlap around the 45° corner threshold: the label rule decides.
        turn = rng.uniform(30, 170) if rng.random() < sharp_prob else rng.uniform(0, 50)
        ang += np.radians(turn) * rng.choice([-1, 1])
    pts = np.array(pts)
    # Densify so that jitter bends segments.
    out = [pts[0]]
    for a, b in zip(pts[:-1], pts[1:]):
        m = max(int(np.hypot(*(b - a)) / 2.0), 1)
        out.extend(a + (b - a) * t for t in np.linspace(0, 1, m + 1)[1:])
    return np.array(out)


def _bend(rng, start, heading, length, turn_deg, radius) -> np.ndarray:
    """Two straight legs joined by a rounded bend (Gaussian smoothing of ``radius`` px)."""
    pts = _polyline(rng, start, heading, 2, (length * 0.3, length * 0.6), 0.0)
    a, c, b = pts[0], pts[len(pts) // 2], pts[-1]
    d1 = np.array([np.cos(heading), np.sin(heading)])
    ang = heading + np.radians(turn_deg) * rng.choice([-1, 1])
    c = a + d1 * rng.uniform(0.3, 0.6) * length
    b = c + np.array([np.cos(ang), np.sin(ang)]) * rng.uniform(0.3, 0.6) * length
    out = []
    for p, q in ((a, c), (c, b)):
        m = max(int(np.hypot(*(q - p))), 1)
        out.extend(p + (q - p) * t for t in np.linspace(0, 1, m + 1)[:-1])
    out.append(b)
    out = np.array(out)
    if radius > 0.3:
        sm = ndimage.gaussian_filter1d(out, radius, axis=0, mode="nearest")
        sm[0], sm[-1] = out[0], out[-1]
        out = sm
    return out


def _loop(rng, centre, radius, polygon: bool) -> np.ndarray:
    """A closed loop: a wobbly ellipse or a polygon."""
    if polygon:
        k = rng.integers(3, 7)
        ang = np.sort(rng.uniform(0, 2 * np.pi, k))
        r = radius * rng.uniform(0.6, 1.0, k)
        v = centre + np.stack([r * np.cos(ang), r * np.sin(ang)], 1)
        v = np.vstack([v, v[:1]])
        out = [v[0]]
        for a, b in zip(v[:-1], v[1:]):
            m = max(int(np.hypot(*(b - a)) / 2.0), 1)
            out.extend(a + (b - a) * t for t in np.linspace(0, 1, m + 1)[1:])
        return np.array(out)
    n = max(int(2 * np.pi * radius / 1.5), 24)
    t = np.linspace(0, 2 * np.pi, n + 1)
    ecc = rng.uniform(0.5, 1.0)
    r = radius * (1 + _smooth_noise(rng, n + 1, n / 5, 0.08))
    r[-1] = r[0]
    rot = rng.uniform(0, np.pi)
    x, y = r * np.cos(t), ecc * r * np.sin(t)
    return centre + np.stack([x * np.cos(rot) - y * np.sin(rot), x * np.sin(rot) + y * np.cos(rot)], 1)


def _point_on(rng, strokes) -> tuple[np.ndarray, np.ndarray]:
    """A random interior point of a random stroke and the stroke's unit tangent there."""
    s = strokes[rng.integers(len(strokes))]
    if len(s) < 5:
        return s[0], np.array([1.0, 0.0])
    i = rng.integers(2, len(s) - 2)
    t = s[i + 2] - s[i - 2]
    return s[i], t / (np.linalg.norm(t) + 1e-9)


def _compose(rng, cfg: GeneratorConfig, size: float, scale: float) -> list[np.ndarray]:
    """A random drawing: a list of centre lines inside a ``size``×``size`` frame."""
    strokes: list[np.ndarray] = []
    n = rng.integers(cfg.primitives_min, cfg.primitives_max + 1)
    margin = 0.1 * size

    def rnd_pt():
        return rng.uniform(margin, size - margin, 2)

    def length():
        return rng.uniform(0.15, 0.7) * size

    for _ in range(n):
        kind = rng.choice(["curve", "polyline", "loop", "cross", "tee", "wye", "meet", "scribble", "bend"],
                          p=[0.15, 0.14, 0.10, 0.12, 0.17, 0.07, 0.10, 0.07, 0.08])
        h = rng.uniform(0, 2 * np.pi)
        if kind == "curve":
            strokes.append(_curve(rng, rnd_pt(), h, length(), rng.normal(0, 0.01) / scale,
                                  rng.uniform(0, 0.03) / scale))
        elif kind == "polyline":
            strokes.append(_polyline(rng, rnd_pt(), h, rng.integers(2, 6), (0.06 * size, 0.25 * size),
                                     rng.uniform(0.3, 0.9)))
        elif kind == "bend":
            strokes.append(_bend(rng, rnd_pt(), h, length(), rng.uniform(15, 150), rng.uniform(0, 5)))
        elif kind == "loop":
            strokes.append(_loop(rng, rnd_pt(), rng.uniform(0.05, 0.25) * size, rng.random() < 0.35))
        elif kind == "cross":
            c = rnd_pt()
            a = _curve(rng, c, h, length() / 2, 0, rng.uniform(0, 0.02) / scale)
            b = _curve(rng, c, h + np.pi, length() / 2, 0, rng.uniform(0, 0.02) / scale)
            strokes.append(np.vstack([b[::-1], a[1:]]))
            h2 = h + np.radians(rng.uniform(40, 140))
            a = _curve(rng, c, h2, length() / 2, 0, rng.uniform(0, 0.02) / scale)
            b = _curve(rng, c, h2 + np.pi, length() / 2, 0, rng.uniform(0, 0.02) / scale)
            strokes.append(np.vstack([b[::-1], a[1:]]))
        elif kind == "tee" and strokes:
            p, t = _point_on(rng, strokes)
            side = rng.choice([-1, 1])
            ang = np.arctan2(t[1], t[0]) + side * np.radians(rng.uniform(45, 135))
            d = np.array([np.cos(ang), np.sin(ang)])
            # The stem stops short of, or overshoots, the other stroke's centre line a little.
            gap = rng.uniform(-1, 1) * cfg.gap_max * rng.uniform(1, 4)
            stem = _curve(rng, p + d * gap, ang, length() * 0.7, rng.normal(0, 0.01) / scale,
                          rng.uniform(0, 0.02) / scale)
            strokes.append(stem[::-1] if rng.random() < 0.5 else stem)
        elif kind == "wye":
            c = rnd_pt()
            base = rng.uniform(0, 2 * np.pi)
            angs = base + np.cumsum(np.radians(rng.uniform(70, 150, 3)))
            for a in angs[:3]:
                strokes.append(_curve(rng, c, a, length() / 2, rng.normal(0, 0.01) / scale, 0))
        elif kind == "meet":
            # Two strokes drawn end to end: a corner if they turn, nothing if they continue.
            c = rnd_pt()
            turn = rng.uniform(60, 160) if rng.random() < 0.6 else rng.uniform(0, 25)
            a = _curve(rng, c, h, length() / 2, 0, rng.uniform(0, 0.02) / scale)
            # People rarely hit the other stroke's end exactly: a small gap or overlap.
            b = _curve(rng, c + rng.normal(0, 0.8, 2), h + np.pi - np.radians(turn) * rng.choice([-1, 1]),
                       length() / 2, 0, rng.uniform(0, 0.02) / scale)
            strokes += [a[::-1], b]
        else:  # scribble: a long wandering curve that may cross itself, or a tee fallback
            strokes.append(_curve(rng, rnd_pt(), h, length() * 1.5, rng.normal(0, 0.03) / scale,
                                  rng.uniform(0.02, 0.08) / scale))
    return strokes


def _jitter(rng, s: np.ndarray, amp: float) -> np.ndarray:
    """Hand tremor: smooth normal displacement, a fraction of a pixel to a pixel."""
    if amp <= 0 or len(s) < 3:
        return s
    n = len(s)
    return s + np.stack([_smooth_noise(rng, n, rng.uniform(4, 15), amp),
                         _smooth_noise(rng, n, rng.uniform(4, 15), amp)], 1)


def _widths(rng, cfg: GeneratorConfig, strokes: list[np.ndarray]) -> list[np.ndarray]:
    """Per-vertex widths: a base width per drawing, varied per stroke and by pen pressure."""
    base = float(np.clip(np.exp(rng.normal(cfg.width_log_mean, cfg.width_log_std)), cfg.width_min, cfg.width_max))
    vary = rng.random() < cfg.width_vary_prob
    pressure = rng.random() < cfg.pressure_prob
    out = []
    for s in strokes:
        w = base * (rng.uniform(0.6, 1.5) if vary else 1.0)
        wv = np.full(len(s), w)
        if pressure and len(s) > 4:
            wv = wv * (1 + _smooth_noise(rng, len(s), len(s) / 3, 0.2))
            taper = np.minimum(1.0, np.minimum(np.arange(len(s)), np.arange(len(s))[::-1]) / max(len(s) * 0.15, 1))
            wv = wv * (0.5 + 0.5 * taper)
        out.append(np.clip(wv, cfg.width_min, cfg.width_max))
    return out


def drawing_from_strokes(rng: np.random.Generator, strokes: list[np.ndarray], shape: tuple[int, int],
                         cfg: GeneratorConfig, rules: LabelRules,
                         widths: list[np.ndarray] | None = None) -> Sample:
    """Style, render and label given centre lines.

    Parameters
    ----------
    rng : numpy.random.Generator
    strokes : list of numpy.ndarray
        Centre lines (n, 2) in (x, y), already placed in the image frame.
    shape : (H, W)
    cfg : GeneratorConfig
    rules : LabelRules
    widths : list of numpy.ndarray, optional
        Per-vertex widths; drawn at random when omitted.

    Returns
    -------
    Sample
    """
    if cfg.thin_prob > 0 and rng.random() < cfg.thin_prob:
        return _thin_aliased(rng, strokes, shape, cfg, rules)
    if widths is None:
        widths = _widths(rng, cfg, strokes)
    pencil = rng.random() < cfg.pencil_prob
    if pencil:
        dark = rng.uniform(cfg.ink_min, 0.85) * rng.uniform(0.85, 1.0, len(strokes))
    else:
        dark = np.full(len(strokes), rng.uniform(0.75, 1.0))
    ink = render_strokes(shape, strokes, widths, dark)
    grey = stylise(ink, rng, cfg, pencil)
    pts, types = label_keypoints(strokes, [float(np.mean(w)) for w in widths], rules)
    h, w = shape
    inside = (pts[:, 0] >= 0) & (pts[:, 0] < w) & (pts[:, 1] >= 0) & (pts[:, 1] < h) if len(pts) else np.zeros(0, bool)
    return Sample(grey, strokes, widths, pts[inside], types[inside])


def _thin_aliased(rng: np.random.Generator, strokes: list[np.ndarray], shape: tuple[int, int],
                  cfg: GeneratorConfig, rules: LabelRules) -> Sample:
    """Thin (1–2 px) grey ink with hard or poor anti-aliasing: the staircase of cheap drawing tools.

    Its smooth curves must give no corner: the labels come from the centre lines as always, so the
    network learns that the aliasing steps are not keypoints.
    """
    wd = rng.uniform(1.0, 2.2)
    widths = [np.full(len(s), wd) for s in strokes]
    cover = render_strokes(shape, strokes, widths)
    mode = rng.integers(3)
    if mode == 0:    # no anti-aliasing: a pixel is ink or paper
        cover = (cover >= rng.uniform(0.35, 0.6)).astype(np.float64)
    elif mode == 1:  # coarse anti-aliasing: coverage quantised to a few levels
        levels = int(rng.integers(2, 5))
        cover = np.round(cover * levels) / levels
    dark = rng.uniform(0.3, 0.9)  # grey strokes: low contrast
    ink = cover * dark
    blur = rng.uniform(0.0, 0.6)
    if blur > 0.2:
        ink = ndimage.gaussian_filter(ink, blur)
    grey = rng.uniform(0.92, 1.0) * (1.0 - ink)
    if rng.random() < 0.3:
        grey = grey + rng.normal(0.0, rng.uniform(0.0, 0.02), shape)
    pts, types = label_keypoints(strokes, [wd] * len(strokes), rules)
    h, w = shape
    inside = (pts[:, 0] >= 0) & (pts[:, 0] < w) & (pts[:, 1] >= 0) & (pts[:, 1] < h) if len(pts) else np.zeros(0, bool)
    return Sample(np.clip(grey, 0.0, 1.0).astype(np.float32), strokes, widths, pts[inside], types[inside])


def generate(rng: np.random.Generator, cfg: GeneratorConfig, rules: LabelRules) -> Sample:
    """One procedural drawing with its keypoints.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness (the drawing is a pure function of its state).
    cfg : GeneratorConfig
    rules : LabelRules

    Returns
    -------
    Sample
    """
    size = int(rng.integers(cfg.size_min, cfg.size_max + 1))
    scale = size / 256.0
    strokes = [_jitter(rng, s, rng.uniform(0, cfg.jitter_px)) for s in _compose(rng, cfg, size, scale)]
    # Random rotation, then fit the drawing into the canvas at a random fill (the geometry stays
    # exact: labels are computed afterwards, from the final centre lines).
    ang = rng.uniform(0, 2 * np.pi)
    rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    strokes = [s @ rot.T for s in strokes if len(s) >= 2]
    allp = np.concatenate(strokes)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    span = max(float((hi - lo).max()), 1e-6)
    fill = rng.uniform(0.6, 0.95) * size
    k = min(fill / span, 1.3)
    off = rng.uniform(0, 1, 2) * (size - k * (hi - lo) - 8) + 4
    clipped = [(s - lo) * k + off for s in strokes]
    return drawing_from_strokes(rng, clipped, (size, size), cfg, rules)
