"""Training data of the keypoint network: generated and human-stroke drawings as the stage sees them.

Procedural drawings come from :mod:`stages.keypoints.training.generator`; human strokes (``train.vector``:
Quick, Draw! categories split by :func:`category_split`, Omniglot stroke-3 symbols) are restyled by
the same generator at every draw. Both go through prep's contrast normalisation and narrow band
and the network-input normalisation of inference, so the network sees what it is run on.
"""

from __future__ import annotations

import glob
from pathlib import Path

import numpy as np
import torch
from skimage.measure import approximate_polygon

from stages.config import from_section
from stages.errors import InputError
from stages.keypoints.codes import TYPE_CODES
from stages.keypoints.inference import dilate_band, network_input
from stages.keypoints.training.generator import GeneratorConfig, drawing_from_strokes, generate
from stages.keypoints.training.human_strokes import fit_strokes, read_quickdraw_ndjson, read_stroke3
from stages.keypoints.training.labels import LabelRules
from stages.keypoints.training.targets import gaussian_heatmaps
from stages.prep import narrow_band, normalise_contrast

# ------------------------------------------------------------------------------------------------
# Data


def prepare_sample(sample, cfg: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Network input, targets and loss band of one generated drawing, as the stage would see it.

    Parameters
    ----------
    sample : stages.keypoints.training.generator.Sample
    cfg : dict
        The composed config (``train``, ``keypoints``, ``prep`` sections).

    Returns
    -------
    x : numpy.ndarray
        float32 (H, W) network input (1 = ink).
    target : numpy.ndarray
        float32 (4, H, W) Gaussian heatmaps.
    band : numpy.ndarray
        float32 (H, W), 1 inside the dilated narrow band.
    """
    pc = cfg["prep"]
    grey = sample.grey
    try:
        grey = normalise_contrast(grey.astype(np.float64), pc["contrast"]["low_percentile"],
                                  pc["contrast"]["high_percentile"], pc["contrast"]["min_contrast"])
    except Exception:  # blank drawing after styling: leave it as is
        grey = grey.astype(np.float32)
    mask = narrow_band(grey, pc["threshold"], pc["repair_passes"], pc["repair_neighbours"], pc["min_component_px"])
    band = dilate_band(mask, int(cfg["train"]["band_dilation"])).astype(np.float32)
    x = network_input(grey, float(cfg["keypoints"]["contrast_floor"]))
    target = gaussian_heatmaps(grey.shape, sample.points, sample.types, float(cfg["train"]["sigma"]))
    return x, target, band


class DrawingStream(torch.utils.data.IterableDataset):
    """Endless crops of training drawings; worker ``k`` draws from seed (seed, start, k).

    A share ``train.vector_prob`` of the drawings are human strokes (:func:`vector_pool`, restyled
    by :func:`render_vector` every time one is drawn; Quick, Draw! drawings weighted by their stroke
    count to the power ``train.vector.stroke_count_power``); the rest are procedural.
    """

    def __init__(self, cfg: dict, crop: int, start: int):
        self.cfg, self.crop, self.start = cfg, crop, start

    def __iter__(self):
        info = torch.utils.data.get_worker_info()
        wid = info.id if info is not None else 0
        tc = self.cfg["train"]
        rng = np.random.default_rng([int(tc["seed"]), self.start, wid])
        gcfg = from_section(GeneratorConfig, tc["generator"], "train.generator")
        rules = from_section(LabelRules, tc["labels"], "train.labels")
        c = self.crop
        kp_prob = float(tc["keypoint_crop_prob"])
        type_w = np.asarray(tc["keypoint_crop_type_weights"], float)
        if type_w.shape != (3,) or (type_w < 0).any() or type_w.sum() <= 0:
            raise ValueError(f"train.keypoint_crop_type_weights must be three weights >= 0, got {type_w.tolist()}")
        uniform = bool(np.all(type_w == type_w[0]))
        vprob = float(tc.get("vector_prob") or 0.0)
        vcfg = tc.get("vector") or {}
        pool = vector_pool(vcfg, "train") if vprob > 0 else {}
        busy = stroke_count_cdf(pool.get("ndjson") or [], stroke_count_power(vcfg))
        while True:
            sample = (draw_vector(rng, pool, vcfg, gcfg, rules, ndjson_cdf=busy)
                      if pool and rng.random() < vprob else None)
            if sample is not None:
                per = int(tc["vector_crops_per_image"])
            else:
                sample = generate(rng, gcfg, rules)
                per = int(tc["crops_per_image"])
            x, t, b = prepare_sample(sample, self.cfg)
            pts = sample.points
            h, w = x.shape
            ph, pw = max(c - h, 0), max(c - w, 0)
            if ph or pw:
                x = np.pad(x, ((0, ph), (0, pw)))
                t = np.pad(t, ((0, 0), (0, ph), (0, pw)))
                b = np.pad(b, ((0, ph), (0, pw)))
                h, w = x.shape
            for _ in range(per):
                if len(pts) and rng.random() < kp_prob:
                    # Centre-ish on a keypoint: positives are rare, and this is where learning is.
                    if uniform:
                        k = rng.integers(len(pts))
                    else:
                        # Over-sample the centres of the rarer, harder types (junction knots).
                        tw = type_w[np.searchsorted(TYPE_CODES, sample.types)]
                        k = rng.choice(len(pts), p=tw / tw.sum()) if tw.sum() > 0 else rng.integers(len(pts))
                    px, py = pts[k]
                    m = min(8, c // 4)
                    i0 = int(np.clip(int(py) - rng.integers(m, c - m), 0, h - c))
                    j0 = int(np.clip(int(px) - rng.integers(m, c - m), 0, w - c))
                else:
                    # Any crop with some ink.
                    for _try in range(4):
                        i0, j0 = rng.integers(0, h - c + 1), rng.integers(0, w - c + 1)
                        if b[i0:i0 + c, j0:j0 + c].mean() > 0.01:
                            break
                yield (torch.from_numpy(np.ascontiguousarray(x[None, i0:i0 + c, j0:j0 + c])),
                       torch.from_numpy(np.ascontiguousarray(t[:, i0:i0 + c, j0:j0 + c])),
                       torch.from_numpy(np.ascontiguousarray(b[None, i0:i0 + c, j0:j0 + c])))


def validation_set(cfg: dict, part: str = "generated") -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Fixed validation drawings: (x, band, points, types).

    ``part="generated"``: ``val.count`` procedural drawings. ``part="vector"``: ``val.vector_count``
    human-stroke drawings of the held-out categories (``vector_pool(…, "valid")``), restyled with a
    fixed seed; empty when the vector data are absent.
    """
    v = cfg["train"]["val"]
    rng = np.random.default_rng(int(v["seed"]))
    gcfg = from_section(GeneratorConfig, cfg["train"]["generator"], "train.generator")
    rules = from_section(LabelRules, cfg["train"]["labels"], "train.labels")
    if part == "generated":
        samples = [generate(rng, gcfg, rules) for _ in range(int(v["count"]))]
    else:
        vcfg, n = cfg["train"].get("vector") or {}, int(v.get("vector_count", 0))
        pool = vector_pool(vcfg, "valid") if n > 0 else {}
        samples = [s for _ in range(n) if (s := draw_vector(rng, pool, vcfg, gcfg, rules)) is not None]
    out = []
    for s in samples:
        x, _, band = prepare_sample(s, cfg)
        out.append((x, band > 0, s.points, s.types))
    return out



def _vector_files(vcfg: dict, key: str = "files") -> list[str]:
    """The files matched by the glob patterns ``vcfg[key]``, sorted, each once."""
    return sorted({f for pat in vcfg.get(key) or [] for f in glob.glob(str(pat))})


def category_split(files: list[str], holdout: int, seed: int) -> tuple[list[str], list[str]]:
    """Split category files (one Quick, Draw! category per file) into training and validation.

    Whole categories are held out, so validation drawings come from categories training never saw.
    The held-out categories are the ``holdout`` names with the smallest hash of ``seed`` and the name:
    the split depends only on the names, never on their order or their folder.

    Returns
    -------
    train, valid : list of str
        Disjoint, each sorted.
    """
    import hashlib

    def rank(f: str) -> str:
        return hashlib.sha256(f"{seed}:{Path(f).stem}".encode()).hexdigest()

    order = sorted(files, key=rank)
    valid = sorted(order[:max(int(holdout), 0)])
    return sorted(set(files) - set(valid)), valid


def vector_split(vcfg: dict) -> tuple[list[str], list[str]]:
    """(training, held-out) ndjson files of ``train.vector`` (:func:`category_split` of ``files``)."""
    return category_split(_vector_files(vcfg), int(vcfg.get("holdout", 0)), int(vcfg.get("split_seed", 0)))


def _canvas(vcfg: dict, source: str) -> list[int]:
    """[min, max] canvas side for a drawing of ``source`` ("ndjson" or "stroke3")."""
    return vcfg.get("size", [384, 512]) if source == "ndjson" else vcfg.get("stroke3_size", [160, 320])


def vector_pool(vcfg: dict, part: str = "train") -> dict[str, list[list[np.ndarray]]]:
    """The human-stroke drawings of ``vcfg`` (``train.vector``) for one part of the split.

    ``files`` are Quick, Draw! ndjson glob patterns relative to the working directory, one category
    per file; :func:`category_split` holds ``holdout`` categories out for ``part="valid"``. The first
    ``skip`` drawings of every file are left out (the first five of each file of
    ``../shared/data/vector/quickdraw`` made realvec_dev). ``stroke3`` are sketch-rnn ``.npz`` files
    (Omniglot) read with their own ``train`` / ``valid`` split, simplified by Douglas-Peucker at
    ``stroke3_simplify`` file units. Strokes of fewer than two points are
    dropped, and drawings left empty with them.

    Returns
    -------
    dict
        ``{"ndjson": [...], "stroke3": [...]}``, each a list of drawings (lists of (n, 2) strokes).
    """
    if part not in ("train", "valid"):
        raise ValueError(f"part must be 'train' or 'valid', not {part!r}")
    train_files, valid_files = vector_split(vcfg)
    pool: dict[str, list] = {"ndjson": [], "stroke3": []}

    def keep(strokes):
        strokes = [s for s in strokes if len(s) >= 2]
        return strokes or None

    for f in train_files if part == "train" else valid_files:
        for strokes in read_quickdraw_ndjson(f)[int(vcfg.get("skip", 0)):]:
            if (strokes := keep(strokes)) is not None:
                pool["ndjson"].append(strokes)
    eps = float(vcfg.get("stroke3_simplify", 0.0))
    for f in _vector_files(vcfg, "stroke3"):
        for strokes in read_stroke3(f, part):
            if eps > 0:
                # Omniglot's coordinates lie on a coarse grid: its diagonals are one-cell staircases
                # that the label rules would call corners. Douglas-Peucker at one cell removes them.
                strokes = [approximate_polygon(s, eps) for s in strokes]
            if (strokes := keep(strokes)) is not None:
                pool["stroke3"].append(strokes)
    return pool


def stroke_count_power(vcfg: dict) -> float:
    """``train.vector.stroke_count_power`` (0 when absent), checked: a negative power is an InputError."""
    power = float(vcfg.get("stroke_count_power", 0.0))
    if not power >= 0:
        raise InputError(f"train.vector.stroke_count_power must be >= 0, got {power}")
    return power


def stroke_count_cdf(drawings: list[list[np.ndarray]], power: float) -> np.ndarray | None:
    """Cumulative draw weights ∝ (number of strokes)^``power`` of ``drawings`` (None: uniform).

    The detector misses end-to-end junctions on busy drawings (the validation split's drawings of 6+
    strokes, MODEL_CARD "Busy drawings"), while the training categories have 3 strokes at the median;
    ``power`` 1 makes every stroke of the pool, not every drawing, equally likely. ``power`` 0 keeps the
    uniform draw and its random stream.
    """
    if power == 0 or not drawings:
        return None
    return np.cumsum(np.array([len(d) for d in drawings], float) ** power)


#: ``train.vector.compose_scale`` where a config has none (conf/train/default.yaml's value).
COMPOSE_SCALE = (0.4, 0.7)


def compose_settings(vcfg: dict) -> tuple[float, tuple[float, float]]:
    """``train.vector.compose_prob`` and ``compose_scale`` (0 and :data:`COMPOSE_SCALE` when absent), checked.

    A probability outside [0, 1] or a scale range outside (0, 1] is an InputError.
    """
    prob = float(vcfg.get("compose_prob", 0.0))
    if not 0.0 <= prob <= 1.0:
        raise InputError(f"train.vector.compose_prob must be within [0, 1], got {prob}")
    lo, hi = (float(v) for v in vcfg.get("compose_scale", COMPOSE_SCALE))
    if not 0.0 < lo <= hi <= 1.0:
        raise InputError(f"train.vector.compose_scale must be [lo, hi] with 0 < lo <= hi <= 1, got {[lo, hi]}")
    return prob, (lo, hi)


def draw_vector(rng: np.random.Generator, pool: dict, vcfg: dict, gcfg: GeneratorConfig, rules: LabelRules,
                ndjson_cdf: np.ndarray | None = None):
    """One styled, labelled rendering of a random drawing of ``pool`` (None when the pool is empty).

    A share ``stroke3_prob`` of the draws come from the stroke-3 symbols (on a ``stroke3_size``
    canvas: they are single characters), the rest from the Quick, Draw! drawings (``size``), uniformly
    or by the cumulative weights ``ndjson_cdf`` (:func:`stroke_count_cdf`). A share ``compose_prob``
    of the Quick, Draw! draws get a second drawing laid over them (:func:`compose_strokes`).
    """
    nd, s3 = pool.get("ndjson") or [], pool.get("stroke3") or []
    if not nd and not s3:
        return None
    source = "stroke3" if s3 and (not nd or rng.random() < float(vcfg.get("stroke3_prob", 0.0))) else "ndjson"
    drawings = pool[source]

    def pick() -> int:
        if source == "ndjson" and ndjson_cdf is not None:
            return min(int(np.searchsorted(ndjson_cdf, rng.random() * ndjson_cdf[-1], side="right")),
                       len(drawings) - 1)
        return int(rng.integers(len(drawings)))

    k = pick()
    prob, scale = compose_settings(vcfg)
    # The draw for composing is made only when it can happen, so that compose_prob 0 keeps the old stream.
    over = drawings[pick()] if source == "ndjson" and prob > 0 and rng.random() < prob else None
    return render_vector(rng, drawings[k], _canvas(vcfg, source), gcfg, rules, over=over, scale=scale)


def compose_strokes(rng: np.random.Generator, first: list[np.ndarray], second: list[np.ndarray], size: int,
                    scale: tuple[float, float]) -> list[np.ndarray]:
    """``first`` fitted to a ``size`` canvas with ``second`` laid over it, smaller, turned and moved.

    The second drawing fills a square of side ``scale`` × ``size`` (uniform in the range), turned by a
    uniform angle about its centre, which lies uniformly where that square stays on the canvas. Its
    strokes cross and touch the first drawing's at places and angles no single drawing has, so a
    drawing of either category teaches junctions between unrelated strokes — the busy drawings'
    knots — from the same 8 k human drawings (the label rules then see all strokes together).
    """
    base = fit_strokes(first, size)
    side = max(float(rng.uniform(*scale)) * size, 8.0)
    over = fit_strokes(second, int(round(side)), margin=min(16.0, side / 8))
    a = rng.uniform(0.0, 2 * np.pi)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    centre = rng.uniform(side / 2, size - side / 2, 2)
    return base + [(s - side / 2) @ rot.T + centre for s in over]


def render_vector(rng: np.random.Generator, strokes: list[np.ndarray], size_range, gcfg: GeneratorConfig,
                  rules: LabelRules, over: list[np.ndarray] | None = None, scale: tuple[float, float] = COMPOSE_SCALE):
    """One styled, labelled rendering of a human-stroke drawing on a square canvas of side in ``size_range``,
    with the drawing ``over`` laid over it when given (:func:`compose_strokes`, its side ``scale`` of the canvas)."""
    lo, hi = (int(v) for v in size_range)
    size = int(rng.integers(lo, hi + 1))
    placed = fit_strokes(strokes, size) if over is None else compose_strokes(rng, strokes, over, size, scale)
    return drawing_from_strokes(rng, placed, (size, size), gcfg, rules)


def vector_samples(vcfg: dict, rng: np.random.Generator, gcfg: GeneratorConfig, rules: LabelRules,
                   part: str = "train", limit: int | None = None):
    """Human strokes, styled and labelled like the generated drawings.

    ``vcfg`` (``train.vector``): the pool (:func:`vector_pool`), ``renders`` (styled copies per
    drawing, each with its own width, style and canvas size) and the canvas ranges. The strokes keep
    their hand jitter, overdraw and near-touching ends — what the procedural generator lacks — and
    their keypoints come from the same label rules. With ``limit``, that many drawings are drawn at
    random instead (:func:`draw_vector`, the detector's mix): the whole pool is 37 k drawings.

    Yields
    ------
    stages.keypoints.training.generator.Sample
    """
    pool = vector_pool(vcfg, part)
    if limit is not None:
        for _ in range(limit):
            if (s := draw_vector(rng, pool, vcfg, gcfg, rules)) is None:
                return
            yield s
        return
    for source in ("ndjson", "stroke3"):
        for strokes in pool[source]:
            for _ in range(int(vcfg.get("renders", 1))):
                yield render_vector(rng, strokes, _canvas(vcfg, source), gcfg, rules)

