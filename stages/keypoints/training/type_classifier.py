"""Training of the keypoint typing perceptron (:mod:`stages.keypoints.valence`) on the detections
of generated and human-stroke drawings run through the real prep and keypoints stages.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from stages.config import from_section
from stages.keypoints.training.data import _vector_files, vector_samples, vector_split
from stages.keypoints.training.generator import GeneratorConfig, generate
from stages.keypoints.training.labels import LabelRules
from stages.keypoints.training.checkpoints import say_weights
from stages.keypoints.training.class_branch import _class_weights

# ------------------------------------------------------------------------------------------------
# Keypoint typing by local valence (stages/keypoints/valence.py)


def _typing_samples(cfg: dict, count: int, seed: int, vector: bool):
    """Generated drawings (``count``), then (``vector``) the human strokes of ``train.vector``.

    Yields
    ------
    stages.keypoints.training.generator.Sample
    """
    rng = np.random.default_rng(seed)
    gcfg = from_section(GeneratorConfig, cfg["train"]["generator"], "train.generator")
    rules = from_section(LabelRules, cfg["train"]["labels"], "train.labels")
    for _ in range(count):
        yield generate(rng, gcfg, rules)
    if vector:
        limit = cfg["train"]["type_classifier"].get("vector_drawings")
        yield from vector_samples(cfg["train"].get("vector") or {}, rng, gcfg, rules,
                                  limit=None if limit is None else int(limit))




def type_classifier_data(cfg: dict, count: int, seed: int, vector: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Features and true types of the detected keypoints of generated (and vector) drawings.

    Every drawing goes through the real stages — its grey image is encoded as an 8-bit PNG and run by
    ``prep`` and ``keypoints`` (with ``typing=argmax``) exactly as a user's drawing would be — so the
    features are those the stage computes at inference. Detected points are matched one-to-one to the
    ground truth within 5 px; unmatched ones carry no label and are left out.

    Parameters
    ----------
    cfg : dict
        ``train``, ``keypoints`` and ``prep`` sections.
    count, seed : int
        Number of generated drawings and the seed of all randomness.
    vector : bool
        Also use the human strokes of ``train.vector`` (:func:`vector_samples`).

    Returns
    -------
    features : numpy.ndarray
        float32 (N, valence.FEATURES).
    labels : numpy.ndarray
        int64 (N,) class index 0, 1, 2 (endpoint, junction, corner).
    """
    import io

    from PIL import Image

    from stages import keypoints as kp_stage
    from stages import prep as prep_stage
    from stages.evaluate.matching import match_one_to_one
    from stages.keypoints.codes import TYPE_CODES
    from stages.keypoints.valence import class_scores_at, valence_features

    kcfg = dict(cfg["keypoints"], typing="argmax")
    feats, labels = [], []
    for s in _typing_samples(cfg, count, seed, vector):
        if not len(s.points):
            continue
        buf = io.BytesIO()
        Image.fromarray((np.clip(s.grey, 0, 1) * 255).round().astype(np.uint8)).save(buf, format="PNG")
        try:
            p = prep_stage.run(cfg["prep"], image_bytes=buf.getvalue(), image_name="generated.png")
        except Exception:  # a blank drawing after styling
            continue
        k = kp_stage.run(kcfg, prep=p)
        pts = np.asarray(k["points"])
        pairs = match_one_to_one(pts, s.points, 5.0)
        if not len(pairs):
            continue
        pi, gi = pairs[:, 0], pairs[:, 1]
        feats.append(valence_features(np.asarray(p["mask"]), pts[pi], class_scores_at(np.asarray(k["heatmaps"]), pts[pi])))
        labels.append([TYPE_CODES.index(int(t)) for t in s.types[gi]])
    return np.concatenate(feats).astype(np.float32), np.concatenate(labels).astype(np.int64)


def fit_type_classifier(features: np.ndarray, labels: np.ndarray, tc: dict):
    """Fit the perceptron of :class:`stages.keypoints.valence.TypeClassifier` (full-batch Adam).

    Parameters
    ----------
    features, labels : numpy.ndarray
        From :func:`type_classifier_data`.
    tc : dict
        ``train.type_classifier``: ``hidden``, ``epochs``, ``lr``, ``weight_decay``, ``balance_power``, ``seed``.

    Returns
    -------
    stages.keypoints.valence.TypeClassifier
    """
    from stages.keypoints.valence import TypeClassifier

    torch.manual_seed(int(tc["seed"]))
    mean = features.mean(0)
    std = features.std(0) + 1e-6
    x = torch.tensor((features - mean) / std, dtype=torch.float32)
    y = torch.tensor(labels)
    cw = _class_weights(torch.bincount(y, minlength=3).double(), float(tc["balance_power"]))
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], int(tc["hidden"])), torch.nn.ReLU(),
                              torch.nn.Linear(int(tc["hidden"]), 3))
    opt = torch.optim.Adam(net.parameters(), lr=float(tc["lr"]), weight_decay=float(tc["weight_decay"]))
    for _ in range(int(tc["epochs"])):
        opt.zero_grad(set_to_none=True)
        F.cross_entropy(net(x), y, weight=cw).backward()
        opt.step()
    w1, w2 = net[0], net[2]
    return TypeClassifier({"mean": mean, "std": std, "w1": w1.weight.detach().numpy().T, "b1": w1.bias.detach().numpy(),
                           "w2": w2.weight.detach().numpy().T, "b2": w2.bias.detach().numpy()})


def train_type_classifier(cfg: dict) -> dict:
    """Train the valence type classifier on generated drawings (``train.type_classifier``).

    Writes ``type_classifier.npz`` and ``type_classifier.json`` (record) into ``train.out_dir``; copy
    the ``.npz`` to stages/keypoints/weights/ to ship it.

    Returns
    -------
    dict
        The record: sizes, class counts, accuracy of argmax and of the classifier on separate
        generated validation drawings.
    """
    tc = cfg["train"]["type_classifier"]
    torch.set_num_threads(int(cfg["train"]["cpu_threads"]))
    out = Path(cfg["train"]["out_dir"])
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    use_vector = bool(tc.get("vector", True))
    x, y = type_classifier_data(cfg, int(tc["drawings"]), int(tc["seed"]), vector=use_vector)
    vx, vy = type_classifier_data(cfg, int(tc["val_drawings"]), int(tc["val_seed"]), vector=False)
    t_data = time.time() - t0
    clf = fit_type_classifier(x, y, tc)
    # Class scores are the first three features: their argmax is the paper's typing.
    vcfg = cfg["train"].get("vector") or {}
    vfiles = vector_split(vcfg)[0] + _vector_files(vcfg, "stroke3") if use_vector else []
    record = {"mode": "type_classifier", "keypoints": int(len(y)), "val_keypoints": int(len(vy)),
              "vector_files": [Path(f).name for f in vfiles],
              "class_counts": np.bincount(y, minlength=3).tolist(), "data_seconds": t_data,
              "seconds": time.time() - t0,
              "train_accuracy": float((clf.predict(x) == y).mean()),
              "val_accuracy": float((clf.predict(vx) == vy).mean()),
              "val_accuracy_argmax": float((np.argmax(vx[:, :3], 1) == vy).mean()),
              "config": tc, "torch": str(torch.__version__)}
    clf.save(out / "type_classifier.npz")
    say_weights(out / "type_classifier.npz")
    (out / "type_classifier.json").write_text(json.dumps(record, indent=2))
    print(f"type classifier: {record['keypoints']} keypoints ({len(vfiles)} vector files), generated validation accuracy "
          f"{record['val_accuracy']:.3f} (class-map argmax {record['val_accuracy_argmax']:.3f}), "
          f"{record['seconds']:.0f} s", flush=True)
    return record


