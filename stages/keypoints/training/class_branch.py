"""Training of the class branch of a trained keypoint detector, the detector frozen (``train.class_branch``).

:func:`train_class_branch` (``python -m pipeline.train --class-branch``) keeps the trunk and H1..H6 of
``train.init_weights`` as they are, so detection is unchanged bit for bit, and trains the class branch
alone from fresh parameters on cached trunk features around keypoints: the ground-truth keypoints of
generated drawings and their classes (:func:`class_patches`), or, with ``distill: true``, the teacher's
own detections and class maps (:func:`distill_patches`).  The trunk runs once per drawing, so a run
takes minutes on one CPU thread.  Apart from the detector's loop (:mod:`stages.keypoints.training.loop`),
with which it shares the validation (:mod:`stages.keypoints.training.validation`) and the weights
export (:mod:`stages.keypoints.training.checkpoints`).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from stages.config import from_section
from stages.errors import InputError
from stages.keypoints.inference import find_keypoints
from stages.keypoints.network import KeypointNet, NetConfig, count_parameters
from stages.keypoints.training.checkpoints import export_weights
from stages.keypoints.training.data import (draw_vector, prepare_sample, stroke_count_cdf, stroke_count_power,
                                            validation_set, vector_pool)
from stages.keypoints.training.generator import GeneratorConfig, generate
from stages.keypoints.training.labels import LabelRules
from stages.keypoints.training.validation import evaluate


def _class_weights(counts: torch.Tensor, power: float) -> torch.Tensor:
    """Cross-entropy class weights ∝ frequency^-power (0 = none, 1 = balanced), mean 1."""
    cw = (counts.sum() / counts.clamp_min(1)) ** power
    return (cw / cw.mean()).float()


def _padded_trunk(model: KeypointNet, x: np.ndarray, r: int):
    """``model.trunk`` of drawing ``x`` padded by ``r`` (so that a patch of radius ``r`` around any pixel lies
    inside the computed features; zeros beyond the drawing, as the stage's padding), then to the
    network's multiple; the feature maps start at pixel (-r, -r) of the drawing."""
    m = model.multiple
    h, w = x.shape
    xp = np.pad(x, ((r, r + m - (h + 2 * r) % m), (r, r + m - (w + 2 * r) % m)))
    return model.trunk(torch.from_numpy(xp)[None, None])


def class_patches(model: KeypointNet, cfg: dict, count: int, seed: int, patch: int
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Frozen decoder features around the keypoints of ``count`` generated drawings.

    The trunk (everything that feeds H1) runs once per drawing; a ``patch``-pixel square of its
    full-resolution features is cut around every ground-truth keypoint, with the class of each of its
    pixels (argmax of Ĥ2..Ĥ4) and whether the pixel counts for the loss (Ĥ1 > 0.5, in the band).

    Returns
    -------
    feats : torch.Tensor
        float16 (N, C, patch, patch).
    cls : torch.Tensor
        int64 (N, patch, patch) class index 0..2.
    near : torch.Tensor
        bool (N, patch, patch).
    """
    rng = np.random.default_rng(seed)
    gcfg = from_section(GeneratorConfig, cfg["train"]["generator"], "train.generator")
    rules = from_section(LabelRules, cfg["train"]["labels"], "train.labels")
    r = patch // 2
    feats, classes, nears = [], [], []
    model.eval()
    with torch.inference_mode():
        for _ in range(count):
            s = generate(rng, gcfg, rules)
            if not len(s.points):
                continue
            x, t, b = prepare_sample(s, cfg)
            f = _padded_trunk(model, x, r)[0][0]
            tp = np.pad(t, ((0, 0), (r, r), (r, r)))
            bp = np.pad(b, ((r, r), (r, r)))
            for px, py in s.points:
                i, j = int(py) + r, int(px) + r
                feats.append(f[:, i - r:i + r + 1, j - r:j + r + 1].half())
                tt = tp[:, i - r:i + r + 1, j - r:j + r + 1]
                classes.append(torch.from_numpy(tt[1:4].argmax(0)))
                nears.append(torch.from_numpy((tt[0] > 0.5) & (bp[i - r:i + r + 1, j - r:j + r + 1] > 0)))
    return torch.stack(feats), torch.stack(classes).long(), torch.stack(nears)


def _fit_class_branch(head: torch.nn.Module, tensors: list[torch.Tensor], loss_of, cb: dict, after_epoch) -> list[dict]:
    """Train ``head`` from fresh parameters: Adam, cosine rate from ``cb["lr"]``, ``cb["epochs"]`` passes over
    ``tensors`` (rows together) in batches of ``cb["batch_size"]``, each batch mirrored or not and turned by
    a quarter turn (the same for all its tensors: the branch should not learn an orientation the trunk
    lacks). ``loss_of(*batch)`` gives the loss; ``after_epoch(epoch, mean loss)`` the epoch's record.
    """
    for mod in head.modules():
        if hasattr(mod, "reset_parameters"):
            mod.reset_parameters()
    opt = torch.optim.Adam(head.parameters(), lr=float(cb["lr"]))
    n, bs, epochs = len(tensors[0]), int(cb["batch_size"]), int(cb["epochs"])
    total = epochs * math.ceil(n / bs)
    step, history = 0, []
    head.train()
    for ep in range(epochs):
        perm = torch.randperm(n)
        tot = 0.0
        for k in range(0, n, bs):
            idx = perm[k:k + bs]
            batch = [t[idx] for t in tensors]
            if bool(torch.randint(0, 2, ())):
                batch = [torch.flip(t, (-1,)) for t in batch]
            q = int(torch.randint(0, 4, ()))
            batch = [torch.rot90(t, q, (-2, -1)) for t in batch]
            loss = loss_of(*batch)
            for g in opt.param_groups:
                g["lr"] = 0.5 * float(cb["lr"]) * (1 + math.cos(math.pi * step / total))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            step += 1
            tot += float(loss.detach()) * len(idx)
        history.append(after_epoch(ep, tot / n))
    return history


def distill_patches(teacher: KeypointNet, cfg: dict, count: int, seed: int, patch: int, margin: int,
                    part: str = "train") -> tuple[torch.Tensor, torch.Tensor]:
    """Frozen decoder features and the teacher's class maps around the teacher's own detections.

    ``count`` drawings of the detector's mix (a share ``train.vector_prob`` drawn from the human strokes
    of ``part`` of the split, the rest procedural) run through the whole ``teacher``; a ``patch``-pixel
    square of its full-resolution decoder features is cut around every peak of its H1 at least
    ``train.class_branch.peak_threshold`` on the dilated band — the pixels whose class values the
    stage reads (:func:`~stages.keypoints.valence.class_scores_at`), true and false keypoints alike —
    with the teacher's class maps (tanh of its class logits, unclipped) on the central square that lies
    ``margin`` pixels inside the patch. No label is used: the student learns what the teacher says.

    Returns
    -------
    feats : torch.Tensor
        float16 (N, C, patch, patch).
    targets : torch.Tensor
        float16 (N, 3, patch - 2 margin, patch - 2 margin).
    """
    tc, kc = cfg["train"], cfg["keypoints"]
    rng = np.random.default_rng(seed)
    gcfg = from_section(GeneratorConfig, tc["generator"], "train.generator")
    rules = from_section(LabelRules, tc["labels"], "train.labels")
    vprob = float(tc.get("vector_prob") or 0.0)
    vcfg = tc.get("vector") or {}
    pool = vector_pool(vcfg, part) if vprob > 0 else {}
    busy = stroke_count_cdf(pool.get("ndjson") or [], stroke_count_power(vcfg))
    thr = float(tc["class_branch"]["peak_threshold"])
    r = patch // 2
    feats, targets = [], []
    teacher.eval()
    with torch.inference_mode():
        for _ in range(count):
            s = (draw_vector(rng, pool, vcfg, gcfg, rules, ndjson_cdf=busy)
                 if pool and rng.random() < vprob else None) or generate(rng, gcfg, rules)
            x, _t, band = prepare_sample(s, cfg)
            h, w = x.shape
            f = _padded_trunk(teacher, x, r)[0]
            h1 = torch.tanh(teacher.side[0](f))[0, 0, r:r + h, r:r + w].numpy()
            cls = torch.tanh(teacher.class_head(f))[0]
            pts, _, _ = find_keypoints(np.broadcast_to(h1, (4, h, w)), thr, int(kc["min_distance"]), band > 0, False)
            for px, py in pts:
                i, j = int(py) + r, int(px) + r
                feats.append(f[0, :, i - r:i + r + 1, j - r:j + r + 1].half())
                targets.append(cls[:, i - r + margin:i + r + 1 - margin, j - r + margin:j + r + 1 - margin].half())
    if not feats:
        raise InputError(f"train.class_branch: no teacher peak >= {thr} in {count} drawings")
    return torch.stack(feats), torch.stack(targets)


def _distill_class_branch(model: KeypointNet, cfg: dict, out: Path, t0: float) -> dict:
    """The class branch of ``model`` trained to reproduce ``train.init_weights``' own (``distill: true``).

    The student (``train.network.class_width`` / ``class_dilations``) minimises the squared difference
    of its tanh class maps from the teacher's on the centre of each patch of :func:`distill_patches`;
    the trunk is the teacher's, so detection is unchanged bit for bit. Used to make the branch cheaper.
    """
    from stages.keypoints.stage import load_model

    tc, cb = cfg["train"], cfg["train"]["class_branch"]
    teacher, _ = load_model(tc["init_weights"])  # BatchNorms folded, as the stage runs it
    patch, margin = int(cb["patch"]), int(cb["supervised_margin"])
    feats, targ = distill_patches(teacher, cfg, int(cb["drawings"]), int(cb["seed"]), patch, margin)
    vfeats, vtarg = distill_patches(teacher, cfg, int(cb["val_drawings"]), int(cb["val_seed"]), patch, margin,
                                    part="valid")
    t_data = time.time() - t0
    head = model.class_head
    c = patch // 2 - margin  # the patch centre in the target square

    def centre(fe: torch.Tensor) -> torch.Tensor:
        return torch.tanh(head(fe.float())[:, :, margin:patch - margin, margin:patch - margin])

    def fidelity(fe: torch.Tensor, tg: torch.Tensor) -> dict:
        head.eval()
        with torch.inference_mode():
            pred = torch.cat([centre(fe[k:k + 512])[:, :, c, c] for k in range(0, len(fe), 512)])
        head.train()
        want = tg[:, :, c, c].float()
        return {"agreement": float((pred.argmax(1) == want.argmax(1)).float().mean()),
                "mean_abs": float((pred.clamp(0, 1) - want.clamp(0, 1)).abs().mean())}

    def after_epoch(ep: int, loss: float) -> dict:
        rec = {"epoch": ep + 1, "loss": loss, "val": fidelity(vfeats, vtarg), "elapsed_s": time.time() - t0}
        print(f"epoch {ep + 1} loss {rec['loss']:.5f} val agreement {rec['val']['agreement']:.4f} "
              f"mean |diff| {rec['val']['mean_abs']:.4f} ({rec['elapsed_s']:.0f} s)", flush=True)
        return rec

    n = len(feats)
    history = _fit_class_branch(head, [feats, targ], lambda fe, tg: F.mse_loss(centre(fe), tg.float()), cb,
                                after_epoch)
    record = {"mode": "class_branch_distill", "patches": n, "val_patches": len(vfeats), "data_seconds": t_data,
              "seconds": time.time() - t0, "history": history, "parameters_class_branch": count_parameters(head),
              "init_weights": str(tc["init_weights"]), "torch": str(torch.__version__)}
    export_weights(model, out / "keypoints.pt", record | {"config": tc})
    (out / "record.json").write_text(json.dumps(record, indent=2))
    return record


def train_class_branch(cfg: dict) -> dict:
    """Re-train only the class branch of a trained detector (``train.class_branch`` settings).

    The detector (trunk and H1..H6) is loaded from ``train.init_weights`` and frozen, so detection is
    unchanged bit for bit; the class branch (``train.network.class_width`` / ``class_dilations``) is
    trained from scratch with a class-weighted softmax cross-entropy on cached trunk features around
    the keypoints of generated drawings (:func:`class_patches`). Only the centre of each patch, where
    the branch's receptive field lies inside the patch, is supervised. The class maps are then tanh
    of the logits, so the argmax read by the stage is the argmax of the logits.

    Returns
    -------
    dict
        The record (counts, losses, validation accuracy on a separate set of drawings).
    """
    tc, cb = cfg["train"], cfg["train"]["class_branch"]
    torch.set_num_threads(int(tc["cpu_threads"]))
    torch.manual_seed(int(tc["seed"]))
    out = Path(tc["out_dir"])
    out.mkdir(parents=True, exist_ok=True)
    ck = torch.load(tc["init_weights"], map_location="cpu", weights_only=False)
    net_cfg = from_section(NetConfig, tc["network"], "train.network")
    old = NetConfig.from_dict(ck["network"])
    if (old.stem_mid, old.level_channels, old.bottleneck_blocks) != (net_cfg.stem_mid, net_cfg.level_channels,
                                                                     net_cfg.bottleneck_blocks):
        raise SystemExit(f"init_weights {tc['init_weights']} has network {ck['network']}")
    model = KeypointNet(net_cfg)
    sd = {k: v.float() for k, v in ck.get("state_dict", ck.get("model")).items() if not k.startswith("class_head.")}
    missing, _ = model.load_state_dict(sd, strict=False)
    if any(not k.startswith("class_head.") for k in missing):
        raise SystemExit(f"init_weights lacks {missing}")
    t0 = time.time()
    if cb["distill"]:
        return _distill_class_branch(model, cfg, out, t0)
    patch, margin = int(cb["patch"]), int(cb["supervised_margin"])
    feats, cls, near = class_patches(model, cfg, int(cb["drawings"]), int(cb["seed"]), patch)
    vfeats, vcls, vnear = class_patches(model, cfg, int(cb["val_drawings"]), int(cb["val_seed"]), patch)
    t_data = time.time() - t0
    # Only pixels at least `margin` from the patch border: there the branch sees real features, not padding.
    inner = torch.zeros(patch, patch, dtype=torch.bool)
    inner[margin:patch - margin, margin:patch - margin] = True
    near &= inner
    vnear &= inner
    counts = torch.bincount(cls[near], minlength=3).double()
    cw = _class_weights(counts, float(cb["balance_power"]))
    head = model.class_head
    n = len(feats)

    def centre_accuracy(fe, cl) -> float:
        head.eval()
        with torch.inference_mode():
            c = patch // 2
            pred = torch.cat([head(fe[k:k + 512].float())[:, :, c, c].argmax(1) for k in range(0, len(fe), 512)])
        head.train()
        return float((pred == cl[:, c, c]).float().mean())

    def loss_of(fe, c_, nr):
        ce = F.cross_entropy(head(fe.float()), c_, weight=cw, reduction="none")
        return ce[nr].mean()

    def after_epoch(ep: int, loss: float) -> dict:
        rec = {"epoch": ep + 1, "loss": loss, "val_centre_accuracy": centre_accuracy(vfeats, vcls),
               "elapsed_s": time.time() - t0}
        print(f"epoch {ep + 1} loss {rec['loss']:.4f} val centre acc {rec['val_centre_accuracy']:.3f} "
              f"({rec['elapsed_s']:.0f} s)", flush=True)
        return rec

    history = _fit_class_branch(head, [feats, cls, near], loss_of, cb, after_epoch)
    val = validation_set(cfg)
    r = evaluate(model, val, cfg["keypoints"], torch.device("cpu"))
    record = {"mode": "class_branch", "keypoints": n, "class_counts": counts.tolist(), "class_weights": cw.tolist(),
              "data_seconds": t_data, "seconds": time.time() - t0, "history": history,
              "val_f1": r.f1, "val_accuracy": r.accuracy, "parameters_class_branch": count_parameters(head),
              "init_weights": str(tc["init_weights"]), "torch": str(torch.__version__)}
    print(f"generated validation ({len(val)} drawings): F1 {r.f1:.3f} class acc {r.accuracy:.3f}", flush=True)
    export_weights(model, out / "keypoints.pt", record | {"config": tc})
    (out / "record.json").write_text(json.dumps(record, indent=2))
    return record
