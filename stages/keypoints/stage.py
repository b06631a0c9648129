"""Stage ``keypoints``: CNN heatmaps, peaks and keypoint types (paper §3, Appendix B).

``run(cfg, prep=Artifact)`` normalises the prep stage's grey image the authors' way, runs the
keypoint network (:mod:`stages.keypoints.network`) — in overlapping blended tiles when the drawing
is large — and extracts keypoints from the detection heatmap H1 by non-maximum suppression; each
keypoint's type is, with ``typing: argmax`` (the paper), the argmax of the three class heatmaps, or
with ``typing: valence`` (the default) the decision of a small perceptron over those class values and
the ring profile of the narrow band around the point (:mod:`stages.keypoints.valence`; why: our
CPU-trained class maps confuse the types on real drawings — both are measured in the model card). See
:mod:`stages.keypoints.inference` for the other choices made.

The network weights ship inside the package (``weights/keypoints.pt``, see ``weights/MODEL_CARD.md``)
and are trained by ``polyvec-train`` on procedural drawings (:mod:`stages.keypoints.training.generator`) and
held-out human strokes. ``STAGE_VERSION`` (:mod:`stages.keypoints`) carries a short hash of every shipped
file, so new weights invalidate cached results.

Detection ensemble (``detection_ensemble``, an option; off by default since phase 16): H1 is the mean
of the main network's H1 and that of the listed networks, e.g. the procedural-only detector
(``packaged_procedural``, ``weights/keypoints_procedural.pt``); the class maps stay the main network's,
and each listed network costs a pass of its trunk. Phases 7–15 shipped with it, because those
fine-tuned networks fired false corners alone. Why off now: phase 16 (trained on busy drawings) alone
ties the pair at the keypoint level and beats it end to end over both validation splits, in one pass
(numbers: MODEL_CARD.md, phase 16). ``detection_ensemble: []`` runs the main network alone.

Test-time views (``test_time_views``, an option, off by default): the main network's four maps are
averaged over the drawing and mirror images of it (:func:`~stages.keypoints.inference.predict_views`).
Why off: on both validation splits the transpose lifts the keypoint-level F1 but not the curves'
junction F1, for a second network pass (MODEL_CARD.md, "Test-time views").
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.artifact import Artifact
from stages.config import from_section
from stages.errors import InputError
from stages.keypoints import (PACKAGED_PROCEDURAL, PACKAGED_TYPE_CLASSIFIER, PACKAGED_WEIGHTS, KeypointsConfig,
                              _file_hash)
from stages.keypoints.codes import JUNCTION, TYPE_CODES
from stages.keypoints.valence import TypeClassifier, class_scores_at, valence_features
from stages.prep import internal_frame, piece_windows, source_size

# torch and the modules that need it are imported inside load_model/run, not here: rendering keypoints
# (polyvec-inspect) and typing them from stored heatmaps need no torch, and neither does the engine's
# check of this module before it hands a batch to dask workers (~2 s for importing torch).

_PACKAGED_NETWORKS = {"packaged": PACKAGED_WEIGHTS, "packaged_procedural": PACKAGED_PROCEDURAL}

_MODELS: dict[str, tuple["KeypointNet", str]] = {}


def load_model(weights: str | Path | None = None) -> tuple[KeypointNet, str]:
    """Load (and cache in this process) the keypoint network.

    Parameters
    ----------
    weights : str or Path, optional
        A checkpoint written by ``polyvec-train`` (``{"network": ..., "state_dict": ...}``);
        ``None`` or ``"packaged"`` for the weights shipped with the package, ``"packaged_procedural"``
        for the shipped procedural-only detector; a training checkpoint (``last.pt``) loads too.

    Returns
    -------
    model : KeypointNet
        In eval mode, float32, on the CPU.
    name : str
        ``<file name>@<sha256 prefix>``.

    Raises
    ------
    InputError
        The weights file (packaged or given) does not exist or is not a checkpoint.
    """
    import torch

    from stages.keypoints.network import (KeypointNet, NetConfig, fold_batch_norms, split_concatenations,
                                          use_onednn_pointwise)

    path = _PACKAGED_NETWORKS.get(weights or "packaged") or Path(weights)
    key = str(path)
    if key in _MODELS:
        return _MODELS[key]
    if not path.is_file():
        # Never a randomly initialised network: its keypoints would look like results.
        if path in _PACKAGED_NETWORKS.values():
            raise InputError(f"keypoints.weights: the packaged weights file {path} is missing; reinstall polyvec "
                             "or give a checkpoint from polyvec-train")
        raise InputError(f"keypoints.weights: no such file {path}")
    else:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
        # keypoints.pt (exported) keeps "state_dict"; a training checkpoint (last.pt) keeps "model".
        sd = ckpt.get("state_dict", ckpt.get("model")) if isinstance(ckpt, dict) else None
        try:
            net_cfg = NetConfig.from_dict(ckpt["network"]) if sd is not None else None
        except (KeyError, TypeError):
            net_cfg = None
        if net_cfg is None:
            raise InputError(f"keypoints.weights: {path} is not a polyvec-train checkpoint")
        model = KeypointNet(net_cfg)
        model.load_state_dict({k: v.float() for k, v in sd.items()})
        name = f"{path.name}@{_file_hash(path)}"
    model.eval()
    fold_batch_norms(model)
    # Channels-last convolutions run the full network about 30 % faster on one CPU thread (same
    # heatmaps to 1e-5; tests/benchmarks/bench_keypoints.py). Inference only: with bf16 training it
    # gives NaN gradients (train.channels_last).
    model.to(memory_format=torch.channels_last)
    split_concatenations(model)  # no concatenated tensors: the stem's is 95 MB at 704²
    use_onednn_pointwise(model)  # 1×1 convolutions by oneDNN: 2.06 -> 1.73 s at 700² on a CPU without bf16
    _MODELS[key] = (model, name)
    return model, name


_TYPE_CLASSIFIERS: dict[str, TypeClassifier] = {}


def load_type_classifier(path: str | Path | None = None) -> TypeClassifier:
    """Load (and cache in this process) the valence type classifier.

    Parameters
    ----------
    path : str or Path, optional
        An ``.npz`` written by ``python -m pipeline.train --type-classifier``; ``None`` or
        ``"packaged"`` for the one shipped with the package.
    """
    p = PACKAGED_TYPE_CLASSIFIER if path in (None, "", "packaged") else Path(path)
    if str(p) not in _TYPE_CLASSIFIERS:
        if not p.is_file():
            raise InputError(f"keypoints.type_classifier: no such file {p}")
        _TYPE_CLASSIFIERS[str(p)] = TypeClassifier.load(p)
    return _TYPE_CLASSIFIERS[str(p)]


def preload(cfg: dict | None) -> None:
    """Import torch and load the networks and typing that :func:`run` with ``cfg`` uses, into this
    process's caches; ``cfg`` None: the imports only (a child started before the config is known).

    For a process that will run keypoints tasks and has time before the first: the engine's keypoints
    child calls it at start, while the driver checks the stages' code and runs prep (torch's import
    and the weights were ~1.1 s of the first task; stages/DECISIONS.md, engine).

    Parameters
    ----------
    cfg : dict
        The ``keypoints`` config section.
    """
    import torch

    import stages.keypoints.inference  # noqa: F401 - its import (torch's submodules) is what takes long

    if cfg is None:
        return
    c = from_section(KeypointsConfig, cfg, "keypoints")
    torch.set_num_threads(c.torch_threads)
    for weights in (c.weights, *c.detection_ensemble):
        load_model(weights)
    if c.typing == "valence":
        load_type_classifier(c.type_classifier)


def run(cfg: dict, prep: Artifact) -> Artifact:
    """Detect and classify keypoints.

    Parameters
    ----------
    cfg : dict
        The ``keypoints`` config section (keys of :class:`KeypointsConfig`).
    prep : Artifact
        The prep artifact (``grey`` float32 (H, W), 1 = white; ``mask`` bool (H, W) narrow band).

    Returns
    -------
    Artifact
        ``heatmaps`` float32 (4, H, W) in [0, 1] [detection, endpoint, junction, corner], zero off the
        dilated band when ``restrict_to_band``; ``points`` float32
        (N, 2) (x, y); ``types`` int8 (N,); ``scores`` float32 (N,); data ``points`` and ``weights``.
    """
    import torch

    from stages.keypoints.inference import dilate_band, network_input, predict_heatmaps, predict_views, use_bf16

    c = from_section(KeypointsConfig, cfg, "keypoints")
    torch.set_num_threads(c.torch_threads)
    grey = np.asarray(prep["grey"], np.float32)
    if grey.ndim != 2 or min(grey.shape) < 1:
        raise InputError(f"keypoints: expected a 2-D grey image, got shape {grey.shape}")
    model, name = load_model(c.weights)
    windows = piece_windows(prep.data, grey.shape)
    x = network_input(grey, c.contrast_floor) if windows is None else None
    tiles = c.tile_size, c.tile_overlap
    mask = np.asarray(prep["mask"], bool) if "mask" in prep.arrays else None
    # Tiles with no pixel of the dilated band are not run: keypoints_from_heatmaps zeroes them anyway.
    needed = dilate_band(mask, c.band_dilation) if (c.restrict_to_band and mask is not None) else None
    bf16 = use_bf16(c.precision)

    def over_pieces(predict, channels: int) -> np.ndarray:
        # A mosaic of far-apart parts: the network runs on each piece's window, normalised on its own, as
        # on that part cropped alone, and not on the paper laid between them (zero in the maps anyway).
        if windows is None:
            return predict(x, needed)
        out = np.zeros((channels,) + grey.shape, np.float32)
        for win in windows:
            out[(slice(None), *win)] = predict(network_input(grey[win], c.contrast_floor),
                                               None if needed is None else np.ascontiguousarray(needed[win]))
        return out

    heatmaps = over_pieces(lambda xs, ns: predict_views(model, xs, list(c.test_time_views), *tiles, needed=ns,
                                                        single_pass_max=c.single_pass_max, bf16=bf16), 4)
    ensemble = list(c.detection_ensemble)
    if ensemble:
        # Detection ensemble: H1 is the mean over the networks; the class maps (H2..H4), which the
        # typing perceptron was trained on, stay the main network's.
        h1 = heatmaps[0].copy()
        for w in ensemble:
            other, other_name = load_model(w)
            h1 += over_pieces(lambda xs, ns: predict_heatmaps(other, xs, *tiles, detection_only=True, needed=ns,
                                                              single_pass_max=c.single_pass_max, bf16=bf16), 1)[0]
            name += "+" + other_name
        heatmaps[0] = h1 / (1 + len(ensemble))
    heatmaps, points, types, scores = keypoints_from_heatmaps(cfg, heatmaps, mask, band=needed)
    notes = []
    cap = c.max_keypoints
    if len(points) > cap:
        # A guard: the topology's search grows with the keypoints (paths between pairs of key
        # vertices), so a noise field of peaks keeps only its strongest ones, in their order.
        keep = np.sort(np.argsort(-scores, kind="stable")[:cap])
        notes.append(f"{len(points)} keypoints, more than keypoints.max_keypoints ({cap}): kept the {cap} "
                     "strongest")
        points, types, scores = points[keep], types[keep], scores[keep]
    height, width = source_size(prep.data, grey.shape)    # the drawing's: keypoint edits are checked against it
    data_points = [{"x": float(p[0]), "y": float(p[1]), "type": int(t), "score": float(s)}
                   for p, t, s in zip(points, types, scores)]
    return Artifact(arrays={"heatmaps": heatmaps.astype(np.float32), "points": points, "types": types,
                            "scores": scores},
                    data={"points": data_points, "weights": name, "count": len(data_points),
                          "precision": "bf16" if bf16 else "fp32", **internal_frame(prep.data),
                          "height": height, "width": width}, notes=notes)


def keypoints_from_heatmaps(cfg: dict, heatmaps: np.ndarray, mask: np.ndarray | None,
                            band: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Peaks of H1 on the band and their types: the stage after the network(s).

    Parameters
    ----------
    cfg : dict
        The ``keypoints`` section (``restrict_to_band``, ``band_dilation``, ``threshold``, ``junction_threshold``,
        ``min_distance``, ``subpixel``, ``typing``, ``type_classifier``).
    heatmaps : numpy.ndarray
        (4, H, W) network output (H1 possibly an ensemble mean).
    mask : numpy.ndarray or None
        bool (H, W) narrow band of the prep stage.
    band : numpy.ndarray, optional
        ``mask`` dilated by ``band_dilation`` (:func:`~stages.keypoints.inference.dilate_band`) when
        the caller has it already.

    Returns
    -------
    heatmaps : numpy.ndarray
        Zero off the dilated band (when ``restrict_to_band``), clipped to [0, 1].
    points, types, scores : numpy.ndarray
        As in :func:`run`.
    """
    from stages.keypoints.inference import dilate_band, find_keypoints

    if not (cfg["restrict_to_band"] and mask is not None):
        band = None
    elif band is None:
        band = dilate_band(mask, int(cfg["band_dilation"]))
    if band is not None:
        heatmaps = heatmaps * band[None]  # untrained off the band (the loss is masked to it)
    threshold = float(cfg["threshold"])
    jt = cfg.get("junction_threshold")
    junction_threshold = threshold if jt is None else float(jt)
    points, types, scores = find_keypoints(heatmaps, min(threshold, junction_threshold), int(cfg["min_distance"]),
                                           band, bool(cfg["subpixel"]))
    heatmaps = np.clip(heatmaps, 0.0, 1.0)  # tanh heads: negative values mean "no", as 0 does
    if cfg["typing"] == "valence" and len(points) and mask is not None:
        clf = load_type_classifier(cfg["type_classifier"])
        feats = valence_features(mask, points, class_scores_at(heatmaps, points))
        types = np.asarray(TYPE_CODES, np.int8)[clf.predict(feats)]
    if junction_threshold != threshold:
        # Peaks are found at the lower threshold and typed; each then keeps its own type's threshold.
        need = np.where(types == JUNCTION, junction_threshold, threshold)
        keep = scores >= need
        points, types, scores = points[keep], types[keep], scores[keep]
    return heatmaps, points, types, scores


_COLOURS = {1: (40, 90, 255), 3: (255, 150, 0), 5: (0, 180, 60)}  # endpoint, junction, corner


def render_keypoints(grey: np.ndarray, heatmaps: np.ndarray | None, points: np.ndarray,
                     types: np.ndarray) -> np.ndarray:
    """Draw keypoints (and the detection heatmap) over the drawing.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) in [0, 1], 1 = white.
    heatmaps : numpy.ndarray or None
        (4, H, W); H1 is overlaid in red where it is high.
    points : numpy.ndarray
        (N, 2) in (x, y).
    types : numpy.ndarray
        (N,) codes: endpoints blue, junctions orange, sharp corners green (paper Fig. 2 colours).

    Returns
    -------
    numpy.ndarray
        uint8 (H, W, 3) RGB.
    """
    from skimage.draw import circle_perimeter, disk

    g = np.clip(np.asarray(grey, np.float32), 0, 1)
    rgb = np.repeat((0.35 + 0.65 * g)[..., None], 3, axis=2)
    if heatmaps is not None:
        a = np.clip(np.asarray(heatmaps[0], np.float32), 0, 1)[..., None] * 0.7
        rgb = rgb * (1 - a) + a * np.array([1.0, 0.0, 0.0])
    img = (rgb * 255).round().astype(np.uint8)
    h, w = g.shape
    rad = max(3, int(round(min(h, w) / 120)))
    for (x, y), t in zip(np.asarray(points).reshape(-1, 2), np.asarray(types).reshape(-1)):
        c = _COLOURS.get(int(t), (255, 0, 255))
        r, cc = int(np.floor(y)), int(np.floor(x))
        for rr_ in (rad, rad + 1):
            pr, pc = circle_perimeter(r, cc, rr_, shape=(h, w))
            img[pr, pc] = c
        pr, pc = disk((r, cc), 1.5, shape=(h, w))
        img[pr, pc] = c
    return img
