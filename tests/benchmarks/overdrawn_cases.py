"""Overdrawn and retraced versions of validation cases, for ``export.passes`` (not a test).

Re-renders both styles of every ``step``-th drawing of validation split folders (made by ``python -m
pipeline.validation_cases``, e.g. ``/work/q/val`` and the busy split) in the case's own style and width
(:func:`pipeline.validation_cases.render_case`), with some of their strokes drawn as a person sketching
draws them:

* **overdrawn** — the stroke drawn 2 or 3 times, the passes spread over ``d`` ∈ [0.3, 2] stroke widths
  (centre to centre) around the original, each with a slow drift of its offset, a small jitter and its
  own ends (trimmed or run on by up to 1.5 widths); in pencil each pass has its own ink level;
* **retraced** — the stroke doubling back on itself: one pen path along the stroke and back over
  30–80 % of it (from either end), the way back ``d`` ∈ [0.3, 1.5] widths aside after a hairpin;
* **sketched** (``--p-sketched``, 0 by default) — the stroke drawn as 2–4 short strokes one after the
  other, the way TU-Berlin's and the creative sketches draw a line: each piece runs on past the break
  by −0.5 to 2.5 widths (< 0: a small gap), lies up to one width aside and leaves the line at up to
  12° at its ends, with its own jitter.

The case JSON keeps the ORIGINAL single strokes (and their keypoints) as the ground truth, so the
acceptance scorer expects one curve where a person sees one line. Written as ``<name>_od.png`` +
``<name>_od.json``::

    python tests/benchmarks/overdrawn_cases.py OUT_DIR VALIDATION_DIR [VALIDATION_DIR …] [--step 3]
    polyvec OUT_DIR output=SVGS store.path=STORE
    python ../shared/tools/score_folder.py SVGS OUT_DIR

Only the validation splits' strokes are used (never realvec_dev). The cases are a pure function of the
inputs and the seed.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d

from stages.geometry import arc_length, point_at_arc, resample_uniform


def _normals(p: np.ndarray) -> np.ndarray:
    """Unit normals of a densely resampled polyline, from its tangent smoothed over a few pixels."""
    t = np.gradient(gaussian_filter1d(p, 2.0, axis=0, mode="nearest"), axis=0)
    t /= np.maximum(np.hypot(*t.T), 1e-9)[:, None]
    return np.column_stack([-t[:, 1], t[:, 0]])


def _wobble(rng: np.random.Generator, n: int, amplitude: float) -> np.ndarray:
    """A smooth random signal of ``n`` samples (1 px apart) with standard deviation ≈ ``amplitude``."""
    z = gaussian_filter1d(rng.normal(size=n + 40), 8.0, mode="wrap")[20:20 + n]
    return z / max(float(np.std(z)), 1e-9) * amplitude if n > 2 else np.zeros(n)


def _pass(rng: np.random.Generator, p: np.ndarray, s: np.ndarray, offset: float, w: float) -> np.ndarray:
    """One pass of the pen along ``p`` (resampled 1 px apart, arc ``s``): offset, drift, jitter, own ends."""
    length = float(s[-1])
    drift = rng.uniform(-0.25, 0.25) * w * (s / max(length, 1e-9) - 0.5) * 2
    off = offset + drift + _wobble(rng, len(p), 0.12 * w)
    q = p + _normals(p) * off[:, None]
    a, b = rng.uniform(-1.5, 1.5, 2) * w                  # > 0: trimmed, < 0: run on along the end tangent
    qs = arc_length(q)
    lo, hi = max(a, 0.0), qs[-1] - max(b, 0.0)
    if hi - lo < 2.0:
        return q
    inner = point_at_arc(q, qs, np.linspace(lo, hi, max(int(hi - lo), 2)))
    head, tail = [], []
    if a < 0:
        d0 = inner[0] - inner[min(3, len(inner) - 1)]
        head = [inner[0] + d0 / max(np.hypot(*d0), 1e-9) * -a]
    if b < 0:
        d1 = inner[-1] - inner[max(len(inner) - 4, 0)]
        tail = [inner[-1] + d1 / max(np.hypot(*d1), 1e-9) * -b]
    return np.vstack([*head, inner, *tail])


def overdrawn(rng: np.random.Generator, stroke: np.ndarray, w: float) -> list[np.ndarray]:
    """2 or 3 passes over one stroke, spread over 0.3–2 widths around it."""
    p, s = resample_uniform(np.asarray(stroke, np.float64), 1.0)
    k = int(rng.choice([2, 3], p=[0.6, 0.4]))
    d = rng.uniform(0.3, 2.0) * w
    offsets = np.linspace(-d / 2, d / 2, k) * rng.choice([-1, 1])
    return [_pass(rng, p, s, float(o), w) for o in offsets]


def retraced(rng: np.random.Generator, stroke: np.ndarray, w: float) -> list[np.ndarray]:
    """One pen path along the stroke and back over 30–80 % of it, ``d`` ∈ [0.3, 1.5] widths aside."""
    p, s = resample_uniform(np.asarray(stroke, np.float64), 1.0)
    if rng.random() < 0.5:
        p = p[::-1]
    back = max(int(len(p) * rng.uniform(0.3, 0.8)), 2)
    d = rng.uniform(0.3, 1.5) * w * rng.choice([-1, 1])
    ret = p[::-1][:back]                                   # from the tip backwards
    from_tip = np.arange(back, dtype=np.float64)
    off = d * np.minimum(1.0, from_tip / (1.5 * w)) + _wobble(rng, back, 0.1 * w)
    ret = ret - _normals(ret) * off[:, None]               # the same side of p for either direction
    return [np.vstack([p, ret[1:]])]


def sketched(rng: np.random.Generator, stroke: np.ndarray, w: float) -> list[np.ndarray]:
    """2–4 short pen strokes one after the other along the stroke, overlapping or just apart at the breaks."""
    p, s = resample_uniform(np.asarray(stroke, np.float64), 1.0)
    length = float(s[-1])
    k = min(int(rng.integers(2, 5)), max(int(length // (4 * w)), 1))
    if k < 2:
        return [p]
    cuts = np.sort(rng.uniform(0.15, 0.85, k - 1)) * length
    cuts = cuts[np.diff(np.concatenate([[0.0], cuts, [length]]))[:-1] >= 2 * w]
    bounds = np.concatenate([[0.0], cuts, [length]])
    normals = _normals(p)
    pieces = []
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        run_lo = rng.uniform(-0.5, 2.5) * w / 2 if lo > 0 else 0.0      # each side of a break takes half
        run_hi = rng.uniform(-0.5, 2.5) * w / 2 if hi < length else 0.0
        a, b = max(lo - run_lo, 0.0), min(hi + run_hi, length)
        if b - a < 2.0:
            continue
        at = np.linspace(a, b, max(int(b - a), 2))
        q = point_at_arc(p, s, at)
        n = point_at_arc(normals, s, at)
        # a lateral offset, each end turning off the line over its last 3 widths, a little jitter
        zone = 3.0 * w
        into = [np.maximum(zone - (at - a), 0.0), np.maximum(zone - (b - at), 0.0)]
        turn = np.tan(np.radians(rng.uniform(-12, 12, 2)))
        off = (rng.uniform(-1.0, 1.0) * w + sum(t * e * e / (2 * zone) for t, e in zip(turn, into))
               + _wobble(rng, len(at), 0.08 * w))
        pieces.append(q + n * off[:, None])
    return pieces or [p]


def main() -> int:
    import conf
    from pipeline.train import compose_plain
    from pipeline.validation_cases import render_case

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("cases", type=Path, nargs="+")
    ap.add_argument("--step", type=int, default=3, help="every step-th drawing of each folder")
    ap.add_argument("--p-overdrawn", type=float, default=0.45, help="share of strokes drawn 2-3 times")
    ap.add_argument("--p-retraced", type=float, default=0.2, help="share of strokes that double back")
    ap.add_argument("--p-sketched", type=float, default=0.0, help="share of strokes drawn as 2-4 short strokes")
    ap.add_argument("--truth", choices=("original", "drawn"), default="original",
                    help="ground truth: the original strokes (one line where a person sees one) or the pen "
                         "strokes as drawn (the convention of realvec_dev's human strokes)")
    ap.add_argument("--seed", type=int, default=55)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(a.seed)
    cfg = compose_plain(Path(conf.__file__).resolve().parent, [])     # once, not per case
    n, seen = 0, set()
    for folder in a.cases:
        drawings = sorted({p.stem.rsplit("_", 1)[0] for p in folder.glob("val_*.json")})[::a.step]
        for d in drawings:
            if d in seen:                                  # the busy split repeats some of the simpler's
                continue
            seen.add(d)
            for style in ("clean", "pencil"):
                path = folder / f"{d}_{style}.json"
                if not path.exists():
                    continue
                gt = json.loads(path.read_text())
                w, size = float(gt["width"]), int(gt.get("size", 512))
                strokes = [np.asarray(s, np.float64) for s in gt["strokes"]]
                drawn = []
                for st in strokes:
                    long_enough = len(st) >= 2 and np.hypot(*np.diff(st, axis=0).T).sum() >= 6 * w
                    u = rng.random()
                    if long_enough and u < a.p_overdrawn:
                        drawn += overdrawn(rng, st, w)
                    elif long_enough and u < a.p_overdrawn + a.p_retraced:
                        drawn += retraced(rng, st, w)
                    elif long_enough and u < a.p_overdrawn + a.p_retraced + a.p_sketched:
                        drawn += sketched(rng, st, w)
                    else:
                        drawn.append(st)
                image = render_case(rng, drawn, size, w, style, cfg).image
                truth = render_case(np.random.default_rng(0), strokes if a.truth == "original" else drawn,
                                    size, w, style, cfg).truth
                name = f"{d}_{style}_od"
                image.save(a.out / f"{name}.png")
                (a.out / f"{name}.json").write_text(json.dumps(dict(truth, source=path.name)))
                n += 1
    print(f"{n} cases in {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
