"""Stage ``keypoint_edits``: a user's keypoint corrections applied to the detector's keypoints.

The inspection page (``polyvec-inspect page``) lets a user add keypoints, retype or remove detected
ones, and saves the edits as ``<stem>.keypoints.json``::

    {"format": "polyvec-keypoint-edits", "version": 1, "image": "cat.png", "width": 700, "height": 700,
     "added":   [{"x": 120.5, "y": 88.0, "type": "junction"}],
     "removed": [{"x": 300.2, "y": 41.7}],
     "retyped": [{"x": 52.0, "y": 610.4, "type": "corner"}]}

Coordinates are pixels, (x, y) with the origin at the top-left corner of the top-left pixel
(stages/INTERFACES.md); a type is ``endpoint`` / ``junction`` / ``corner`` or its code 1 / 3 / 5.
``removed`` and ``retyped`` entries name the detected keypoint nearest to them within
``match_radius`` px (an entry that matches none is an error: the edits were made on other keypoints).

This stage sits between ``keypoints`` and ``topology`` and has a config section of its own, so the
detector's artifact keeps its key (a cache hit) and an edit recomputes only this stage, topology,
flow, select and export. With no edits it passes the points through unchanged. The engine reads the
file (``keypoint_edits.file``, or ``<stem>.keypoints.json`` beside the input) and hands its parsed
content to :func:`run` as ``cfg["edits"]``; the stage itself reads nothing from disk.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from stages.artifact import Artifact
from stages.errors import InputError
from stages.prep import internal_is_source, internal_scale, to_internal

FORMAT = "polyvec-keypoint-edits"
TYPE_NAMES = {1: "endpoint", 3: "junction", 5: "corner"}
TYPE_CODES = {v: k for k, v in TYPE_NAMES.items()}


def _type_code(value: Any, where: str) -> int:
    if isinstance(value, str) and value.lower() in TYPE_CODES:
        return TYPE_CODES[value.lower()]
    if isinstance(value, (int, float)) and not isinstance(value, bool) and int(value) in TYPE_NAMES \
            and int(value) == value:
        return int(value)
    raise InputError(f"{where}: type must be endpoint, junction or corner (or 1, 3, 5), got {value!r}")


def _xy(entry: Any, where: str) -> tuple[float, float]:
    if not isinstance(entry, dict):
        raise InputError(f"{where}: expected an object with x and y, got {entry!r}")
    try:
        x, y = float(entry["x"]), float(entry["y"])
    except KeyError as exc:
        raise InputError(f"{where}: missing {exc.args[0]!r}") from None
    except (TypeError, ValueError):
        raise InputError(f"{where}: x and y must be numbers") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise InputError(f"{where}: x and y must be finite")
    return x, y


def validate_edits(edits: Any) -> dict:
    """Check a parsed edits document and normalise it.

    Parameters
    ----------
    edits : object
        The parsed JSON of a ``<stem>.keypoints.json`` file.

    Returns
    -------
    dict
        ``{"width", "height", "added": [(x, y, code)], "removed": [(x, y)], "retyped": [(x, y, code)]}``
        (width and height are None when the file does not give them).

    Raises
    ------
    InputError
        With one line naming the first problem.
    """
    if not isinstance(edits, dict):
        raise InputError(f"expected a JSON object with added/removed/retyped lists, got {type(edits).__name__}")
    fmt = edits.get("format", FORMAT)
    if fmt != FORMAT:
        raise InputError(f"format must be {FORMAT!r}, got {fmt!r}")
    unknown = sorted(set(edits) - {"format", "version", "image", "width", "height", "added", "removed", "retyped"})
    if unknown:
        raise InputError(f"unknown field(s) {', '.join(unknown)} (expected added, removed, retyped)")
    if edits.get("version", 1) != 1:
        raise InputError(f"version must be 1, got {edits.get('version')!r}")
    out: dict = {"width": None, "height": None, "added": [], "removed": [], "retyped": []}
    for dim in ("width", "height"):
        v = edits.get(dim)
        if v is not None:
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise InputError(f"{dim} must be a positive integer, got {v!r}")
            out[dim] = v
    for name in ("added", "removed", "retyped"):
        items = edits.get(name, [])
        if not isinstance(items, list):
            raise InputError(f"{name} must be a list, got {type(items).__name__}")
        for i, e in enumerate(items):
            where = f"{name}[{i}]"
            x, y = _xy(e, where)
            if name == "removed":
                out[name].append((x, y))
            else:
                if "type" not in e:
                    raise InputError(f"{where}: missing 'type'")
                out[name].append((x, y, _type_code(e["type"], where)))
    return out


def apply_edits(points: np.ndarray, types: np.ndarray, scores: np.ndarray, edits: dict,
                match_radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict]]:
    """Apply normalised edits (:func:`validate_edits`) to detected keypoints.

    Parameters
    ----------
    points : numpy.ndarray
        (N, 2) detected keypoints (x, y).
    types : numpy.ndarray
        (N,) type codes.
    scores : numpy.ndarray
        (N,) detection scores; added points get score 1.
    edits : dict
        Output of :func:`validate_edits`.
    match_radius : float
        A removed / retyped entry names the nearest detected keypoint within this many px.

    Returns
    -------
    points, types, scores : numpy.ndarray
        The edited keypoints: the kept detections in their order, then the added points.
    log : list of dict
        One record per edit: ``{"op", "x", "y", "type", "keypoint"}`` (``keypoint`` = index among
        the detections, -1 for an added point).

    Raises
    ------
    InputError
        When a removed / retyped entry matches no detected keypoint, or two entries the same one.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    types = np.asarray(types).reshape(-1).astype(np.int8).copy()
    scores = np.asarray(scores, np.float32).reshape(-1)
    keep = np.ones(len(pts), bool)
    used: dict[int, str] = {}
    log: list[dict] = []

    def match(x: float, y: float, where: str) -> int:
        if len(pts) == 0:
            raise InputError(f"{where} at ({x:.1f}, {y:.1f}): the detector found no keypoints to edit")
        d = np.hypot(pts[:, 0] - x, pts[:, 1] - y)
        k = int(np.argmin(d))
        if d[k] > match_radius:
            raise InputError(f"{where} at ({x:.1f}, {y:.1f}): no detected keypoint within "
                             f"{match_radius:g} px (nearest {d[k]:.1f} px away)")
        if k in used:
            raise InputError(f"{where} at ({x:.1f}, {y:.1f}): keypoint {k} is already {used[k]}")
        return k

    for i, (x, y) in enumerate(edits["removed"]):
        k = match(x, y, f"removed[{i}]")
        used[k] = "removed"
        keep[k] = False
        log.append({"op": "removed", "x": x, "y": y, "type": int(types[k]), "keypoint": k})
    for i, (x, y, t) in enumerate(edits["retyped"]):
        k = match(x, y, f"retyped[{i}]")
        used[k] = "retyped"
        log.append({"op": "retyped", "x": x, "y": y, "type": t, "from": int(types[k]), "keypoint": k})
        types[k] = t
    for x, y, t in edits["added"]:
        log.append({"op": "added", "x": x, "y": y, "type": t, "keypoint": -1})
    add = np.array([(x, y) for x, y, _ in edits["added"]], np.float64).reshape(-1, 2)
    new_points = np.concatenate([pts[keep], add]).astype(np.float32)
    new_types = np.concatenate([types[keep], np.array([t for *_, t in edits["added"]], np.int8)]).astype(np.int8)
    new_scores = np.concatenate([scores[keep], np.ones(len(add), np.float32)]).astype(np.float32)
    return new_points, new_types, new_scores, log


def run(cfg: dict, keypoints: Artifact) -> Artifact:
    """Apply the edits in ``cfg["edits"]`` to the keypoints artifact.

    Parameters
    ----------
    cfg : dict
        ``match_radius`` (px) and ``edits``: the parsed edits document, or None for no edits (the
        engine fills it from ``keypoint_edits.file`` / ``<stem>.keypoints.json``; see
        conf/keypoint_edits/default.yaml).
    keypoints : Artifact
        The detector's artifact (``points``, ``types``, ``scores``; ``heatmaps`` for the image size).

    Returns
    -------
    Artifact
        ``points`` float32 (M, 2), ``types`` int8 (M,), ``scores`` float32 (M,) as the keypoints stage
        has them; data ``points`` (list of ``{"x", "y", "type", "score", "edited"}``), ``count``,
        ``edits`` (the log of :func:`apply_edits`) and ``edit_counts``.
    """
    points = np.asarray(keypoints["points"], np.float32).reshape(-1, 2)
    types = np.asarray(keypoints["types"]).reshape(-1)
    scores = np.asarray(keypoints.arrays.get("scores", np.ones(len(points), np.float32))).reshape(-1)
    raw = cfg.get("edits")
    log: list[dict] = []
    if raw is not None:
        edits = validate_edits(raw)
        # Edits are in the drawing's pixels; a supersampled, downsampled or cropped prep put the keypoints
        # at `scale` × (those − origin).
        scale = internal_scale(keypoints.data)
        h, w = keypoints.data.get("height"), keypoints.data.get("width")
        if h is not None and w is not None:
            if (edits["width"], edits["height"]) != (None, None) and (edits["width"], edits["height"]) != (w, h):
                raise InputError(f"the edits are for a {edits['width']}×{edits['height']} drawing, "
                                 f"this one is {w}×{h}")
        if not internal_is_source(keypoints.data):
            edits = dict(edits, **{op: [tuple(map(float, to_internal((x, y), keypoints.data)[0])) + tuple(rest)
                                        for x, y, *rest in edits[op]] for op in ("added", "removed", "retyped")})
        points, types, scores, log = apply_edits(points, types, scores, edits, float(cfg["match_radius"]) * scale)
    n_det = len(points) - sum(e["op"] == "added" for e in log)
    edited = {e["keypoint"] for e in log if e["op"] == "retyped"}
    kept_index = [k for k in range(len(np.asarray(keypoints["points"]).reshape(-1, 2)))
                  if not any(e["op"] == "removed" and e["keypoint"] == k for e in log)]
    data_points = []
    for i, (p, t, s) in enumerate(zip(points, types, scores)):
        how = "added" if i >= n_det else ("retyped" if kept_index[i] in edited else "")
        data_points.append({"x": float(p[0]), "y": float(p[1]), "type": int(t), "score": float(s), "edited": how})
    counts = {op: sum(e["op"] == op for e in log) for op in ("added", "removed", "retyped")}
    return Artifact(arrays={"points": points.astype(np.float32), "types": types.astype(np.int8),
                            "scores": scores.astype(np.float32)},
                    data={"points": data_points, "count": len(data_points), "edits": log, "edit_counts": counts})
