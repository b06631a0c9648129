"""Write the keypoint detector's validation split as scored cases (the realvec_dev format).

Usage::

    python -m pipeline.validation_cases OUT_DIR [--per-category 2] [--stroke3 24] [--min-strokes 1] [key=value …]

The human-stroke drawings of the categories that :func:`stages.keypoints.training.category_split` holds out of
training (``train.vector.holdout`` of ``train.vector.files``), and optionally the first symbols of
the stroke-3 files' ``valid`` split (Omniglot), are rendered on a 512×512 canvas in two styles —
``clean`` (dark anti-aliased ink) and ``pencil`` (the generator's grain, lighter ink) — at stroke
widths 2, 3 or 5 px (as realvec_dev), labelled by :mod:`stages.keypoints.training.labels`, and written as
``<name>.png`` + ``<name>.json`` (``size``, ``width``, ``style``, ``strokes``, ``endpoints``,
``junctions``, ``corners``). ``pipeline.eval_keypoints`` and ``polyvec-bench`` score such a folder,
and so does the acceptance scorer (``score_folder.py`` reads ``strokes`` and ``width``).

Every choice of the detector (thresholds, ensembling, typing, data mix) is made on this split;
realvec_dev is only reported. The cases are a pure function of the config and the seed.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

WIDTHS = (2.0, 3.0, 5.0)
SIZE = 512


def _style_config(gcfg, style: str):
    """The generator config of one case style (no width variation: one width per drawing)."""
    common = dict(width_vary_prob=0.0, pressure_prob=0.0, thin_prob=0.0)
    if style == "clean":
        return replace(gcfg, pencil_prob=0.0, blur_max=0.3, paper_noise_max=0.0, **common)
    return replace(gcfg, pencil_prob=1.0, **common)


def write_cases(cfg: dict, out: Path, per_category: int = 2, stroke3: int = 24, seed: int = 7,
                min_strokes: int = 1) -> list[str]:
    """Render the validation split into ``out`` (see the module docstring).

    Parameters
    ----------
    cfg : dict
        The ``train`` section's parent (``train.vector``, ``train.generator``, ``train.labels``).
    out : Path
        Folder to write (created).
    per_category : int
        Drawings taken from each held-out category (its first ones), each in both styles.
    min_strokes : int
        Only drawings of at least this many pen strokes count (1 = all). The default split's drawings
        have 3 strokes at the median; ``--min-strokes 6`` gives a split of busier drawings, with more
        junctions per drawing. Names keep the drawing's index in its category.
    stroke3 : int
        Symbols taken from the stroke-3 ``valid`` split, each in both styles (0 = none).
    seed : int
        Seed of the widths and the styling.

    Returns
    -------
    list of str
        The case names written.
    """
    from stages.keypoints.training import vector_pool, vector_split
    from stages.keypoints.training.human_strokes import fit_strokes, read_quickdraw_ndjson

    vcfg = cfg["train"].get("vector") or {}
    _, valid = vector_split(vcfg)
    drawings: list[tuple[str, list[np.ndarray]]] = []
    for f in valid:
        kept = [[s for s in d if len(s) >= 2] for d in read_quickdraw_ndjson(f)]
        kept = [d for d in kept if d]
        busy = [(i, d) for i, d in enumerate(kept) if len(d) >= min_strokes]
        for i, d in busy[:per_category]:
            drawings.append((f"val_qd_{Path(f).stem}_{i}", d))
    if stroke3 > 0:
        symbols = vector_pool(dict(vcfg, files=[]), "valid")["stroke3"]  # simplified as in training
        drawings += [(f"val_s3_{i}", d) for i, d in enumerate(symbols[:stroke3])]
    if not drawings:
        raise SystemExit("validation_cases: no held-out drawings (is train.vector.files reachable from here?)")
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    names = []
    for name, strokes in drawings:
        placed = fit_strokes(strokes, SIZE)
        for style in ("clean", "pencil"):
            width = float(rng.choice(WIDTHS))
            case = render_case(rng, placed, SIZE, width, style, cfg)
            case.image.save(out / f"{name}_{style}.png")
            (out / f"{name}_{style}.json").write_text(json.dumps(case.truth))
            names.append(f"{name}_{style}")
    return names


@dataclass
class RenderedCase:
    """One scored case: its drawing and its ground-truth JSON (the realvec_dev format)."""

    image: "Image.Image"
    truth: dict


def render_case(rng: np.random.Generator, strokes: list[np.ndarray], size: int, width: float, style: str,
                cfg: dict) -> RenderedCase:
    """Render placed strokes as one case of the split (``size``² canvas, one stroke ``width``, a style).

    Parameters
    ----------
    rng : numpy.random.Generator
        Styling randomness (grain, ink level, blur).
    strokes : list of numpy.ndarray
        (n, 2) polylines in the canvas's pixels.
    size : int
        Canvas side (px).
    width : float
        Stroke width (px).
    style : str
        ``clean`` or ``pencil``.
    cfg : dict
        The ``train`` section's parent (``train.generator``, ``train.labels``).

    Returns
    -------
    RenderedCase
        The grey PNG image and the JSON (``size``, ``width``, ``style``, ``strokes``, ``endpoints``,
        ``junctions``, ``corners``).
    """
    from PIL import Image

    from stages.config import from_section
    from stages.keypoints.training.generator import GeneratorConfig, drawing_from_strokes
    from stages.keypoints.training.labels import LabelRules

    tc = cfg["train"]
    gcfg = from_section(GeneratorConfig, tc["generator"], "train.generator")
    rules = from_section(LabelRules, tc["labels"], "train.labels")
    s = drawing_from_strokes(rng, strokes, (size, size), _style_config(gcfg, style), rules,
                             widths=[np.full(len(p), width) for p in strokes])
    image = Image.fromarray((np.clip(s.grey, 0, 1) * 255).round().astype(np.uint8))
    gt = {"size": size, "width": width, "style": style,
          "strokes": [np.round(p, 2).tolist() for p in strokes],
          "keypoint_rule": "stages/keypoints/training/labels.py (reference/metrics.md §4.2)"}
    for key, code in (("endpoints", 1), ("junctions", 3), ("corners", 5)):
        gt[key] = np.round(s.points[s.types == code], 2).tolist()
    return RenderedCase(image, gt)


def main(argv: list[str] | None = None) -> int:
    """``python -m pipeline.validation_cases OUT_DIR [options] [key=value …]`` (train config overrides)."""
    import conf
    from pipeline.train import compose_plain

    ap = argparse.ArgumentParser(prog="python -m pipeline.validation_cases", description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--per-category", type=int, default=2)
    ap.add_argument("--stroke3", type=int, default=24)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--min-strokes", type=int, default=1, help="only drawings of at least this many strokes")
    ap.add_argument("overrides", nargs="*", help="config overrides, e.g. train.vector.holdout=30")
    a = ap.parse_intermixed_args(argv)  # options and key=value overrides in any order
    cfg = compose_plain(Path(conf.__file__).resolve().parent, a.overrides)
    names = write_cases(cfg, a.out, a.per_category, a.stroke3, a.seed, a.min_strokes)
    print(f"{len(names)} validation cases written to {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
