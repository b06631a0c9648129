"""``polyvec-train``: train the keypoint network on procedural drawings (paper §3.1, Appendix B).

Usage::

    polyvec-train                                   # conf/train_app.yaml: train + keypoints + prep
    polyvec-train train.steps=2000 train.out_dir=runs/small train.network.level_channels=[8,16,32,64]

What it does, per step: a batch of crops of procedural drawings (stages/keypoints/generator.py,
generated on the fly by DataLoader workers, each drawing a pure function of (seed, worker, index);
with ``train.vector_prob`` > 0 that share of the drawings are human strokes of ``train.vector``, restyled
each time), prep's contrast normalisation and narrow band, the authors' network-input normalisation, Gaussian
targets (σ = ``sigma``), random flips / quarter turns, the masked asymmetric loss of Eq. 1, Adam with
cosine annealing. Crops grow in size during training (``crop_schedule``; the authors train on
80×80 crops of growing-resolution images). Every ``checkpoint_every`` steps ``last.pt`` is written
atomically (model, optimiser, scheduler, step); re-running the same command resumes from it. Every
``val.every`` steps the detector is scored on a fixed set of generated drawings (one-to-one F1
within 5 px and classification accuracy). At the end ``keypoints.pt`` (fp16 weights + network
config + training record) is exported: copy it to stages/keypoints/weights/ to ship it.

The training loop needs only torch, numpy, scipy, scikit-image and numba (and rich if present), so
it also runs where Hydra is not installed: ``python -m pipeline.train --plain conf_dir [key=value…]``.

``python -m pipeline.train --class-branch conf_dir train.init_weights=… [key=value…]`` re-trains only
the class branch on a frozen detector (:func:`train_class_branch`, settings ``train.class_branch``):
detection stays exactly as it was, and the run takes minutes on one CPU thread because the trunk runs
once per drawing and the branch trains on cached feature patches around the keypoints.

``python -m pipeline.train --type-classifier conf_dir [key=value…]`` trains the keypoint typing
perceptron of :mod:`stages.keypoints.valence` (settings ``train.type_classifier``) on the detected
keypoints of generated drawings run through the real prep and keypoints stages.
"""

from __future__ import annotations

import glob
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from skimage.measure import approximate_polygon

from stages.evaluate.keypoints import MatchResult, match_keypoints
from stages.keypoints.generator import (GeneratorConfig, drawing_from_strokes, fit_strokes, generate,
                                        read_quickdraw_ndjson, read_stroke3)
from stages.keypoints.inference import dilate_band, find_keypoints, network_input, predict_heatmaps
from stages.keypoints.labels import LabelRules
from stages.keypoints.network import KeypointNet, NetConfig, count_parameters
from stages.keypoints.targets import class_cross_entropy, gaussian_heatmaps, keypoint_loss
from stages.prep import narrow_band, normalise_contrast


# ------------------------------------------------------------------------------------------------
# Data


def prepare_sample(sample, cfg: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Network input, targets and loss band of one generated drawing, as the stage would see it.

    Parameters
    ----------
    sample : stages.keypoints.generator.Sample
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
    by :func:`render_vector` every time one is drawn); the rest are procedural.
    """

    def __init__(self, cfg: dict, crop: int, start: int):
        self.cfg, self.crop, self.start = cfg, crop, start

    def __iter__(self):
        info = torch.utils.data.get_worker_info()
        wid = info.id if info is not None else 0
        tc = self.cfg["train"]
        rng = np.random.default_rng([int(tc["seed"]), self.start, wid])
        gcfg = GeneratorConfig.from_dict(tc["generator"])
        rules = LabelRules.from_dict(tc["labels"])
        c = self.crop
        kp_prob = float(tc["keypoint_crop_prob"])
        vprob = float(tc.get("vector_prob") or 0.0)
        vcfg = tc.get("vector") or {}
        pool = vector_pool(vcfg, "train") if vprob > 0 else {}
        while True:
            sample = draw_vector(rng, pool, vcfg, gcfg, rules) if pool and rng.random() < vprob else None
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
                    px, py = pts[rng.integers(len(pts))]
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
    gcfg = GeneratorConfig.from_dict(cfg["train"]["generator"])
    rules = LabelRules.from_dict(cfg["train"]["labels"])
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


def evaluate(model: KeypointNet, val, kcfg: dict, device: torch.device) -> MatchResult:
    """One-to-one (5 px) matching result of ``model`` on a validation set."""
    model.eval()
    total = MatchResult()
    with torch.inference_mode():
        for x, band, pts, types in val:
            m = model.multiple
            h, w = x.shape
            xp = np.pad(x, ((0, m - h % m), (0, m - w % m)))
            hm = model(torch.from_numpy(xp)[None, None].to(device))[0][0].float().cpu().numpy()[:, :h, :w]
            p, t, _ = find_keypoints(hm, float(kcfg["threshold"]), int(kcfg["min_distance"]),
                                     band if kcfg["restrict_to_band"] else None, bool(kcfg["subpixel"]))
            total = total + match_keypoints(pts, types, p, t, 5.0)
    model.train()
    return total


# ------------------------------------------------------------------------------------------------
# Training


def _freeze(model: torch.nn.Module, train_only: list) -> list[torch.nn.Module]:
    """Freeze every parameter outside the modules named in ``train_only`` (empty: train all).

    Returns the frozen modules, whose BatchNorm layers must stay in eval mode.
    """
    if not train_only:
        return []
    frozen = []
    for name, mod in model.named_modules():
        trainable = any(name == r or name.startswith(r + ".") for r in train_only)
        if not trainable and not list(mod.children()):
            for p in mod.parameters(recurse=False):
                p.requires_grad_(False)
            frozen.append(mod)
    return frozen


def _train_mode(model: torch.nn.Module, frozen: list) -> None:
    model.train()
    for mod in frozen:
        mod.eval()  # frozen BatchNorm keeps its running statistics


def _worker_init(_wid: int) -> None:
    torch.set_num_threads(1)  # workers run numpy/numba only; keep them from oversubscribing cores


def _crop_at(schedule, frac: float) -> int:
    size = int(schedule[0][1])
    for f, s in schedule:
        if frac >= float(f):
            size = int(s)
    return size


def _augment(x, t, b):
    """Random flips and quarter turns of a batch (labels move with the pixels)."""
    k = int(torch.randint(0, 4, ()))
    dims = (-2, -1)
    if k:
        x, t, b = (torch.rot90(a, k, dims) for a in (x, t, b))
    if bool(torch.randint(0, 2, ())):
        x, t, b = (torch.flip(a, (-1,)) for a in (x, t, b))
    return x, t, b


def _atomic_save(obj, path: Path) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def export_weights(model: KeypointNet, path: Path, record: dict) -> None:
    """Write the shippable checkpoint: fp16 weights, network config and a training record."""
    sd = {k: (v.half() if v.is_floating_point() else v) for k, v in model.state_dict().items()}
    _atomic_save({"network": model.cfg.to_dict(), "state_dict": sd, "record": record}, path)
    say_weights(path)


def say_weights(path: Path) -> None:
    """One line naming the weights file just written (the user would otherwise have to search for it)."""
    print(f"weights written to {Path(path).resolve()} (copy it to stages/keypoints/weights/ to ship it)",
          flush=True)


class _Log:
    """Progress output: rich when available, plain lines otherwise."""

    def __init__(self, total: int, start: int):
        try:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            self.console = Console()
            self.progress = Progress(TextColumn("[bold]train"), BarColumn(), MofNCompleteColumn(),
                                     TimeRemainingColumn(), TextColumn("{task.fields[info]}"),
                                     console=self.console, disable=not self.console.is_terminal)
            self.task = self.progress.add_task("train", total=total, completed=start, info="")
            self.progress.start()
        except ImportError:  # pragma: no cover - rich is a dependency, but not on every GPU box
            self.console = self.progress = None

    def update(self, step: int, info: str) -> None:
        if self.progress is not None:
            self.progress.update(self.task, completed=step, info=info)

    def line(self, text: str) -> None:
        if self.console is not None:
            self.console.log(text)
        else:
            print(text, flush=True)

    def close(self) -> None:
        if self.progress is not None:
            self.progress.stop()


def train(cfg: dict) -> dict:
    """Train (or resume) the keypoint network.

    Parameters
    ----------
    cfg : dict
        Composed config with sections ``train``, ``keypoints`` and ``prep`` (conf/train_app.yaml).

    Returns
    -------
    dict
        The training record (steps, time, losses, validation figures, paths).
    """
    tc = cfg["train"]
    out = Path(tc["out_dir"])
    out.mkdir(parents=True, exist_ok=True)
    seed = int(tc["seed"])
    torch.manual_seed(seed)
    np.random.seed(seed)
    dev_name = tc["device"]
    if dev_name == "auto":
        dev_name = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(dev_name)
    if device.type == "cpu" and tc.get("cpu_threads"):
        torch.set_num_threads(int(tc["cpu_threads"]))
    net_cfg = NetConfig.from_dict(tc["network"])
    model = KeypointNet(net_cfg).to(device)
    steps = int(tc["steps"])
    budget_s = float(tc["schedule_minutes"]) * 60 if tc.get("schedule_minutes") else None
    lr0 = float(tc["lr"])
    opt = torch.optim.Adam(model.parameters(), lr=lr0, weight_decay=float(tc["weight_decay"]))
    start, elapsed0 = 0, 0.0
    if tc.get("init_weights") and not (tc["resume"] and (out / "last.pt").is_file()):
        # Warm start (fine-tuning) from an exported or training checkpoint of the same network.
        ck = torch.load(tc["init_weights"], map_location=device, weights_only=False)
        if ck["network"] != net_cfg.to_dict():
            raise SystemExit(f"init_weights {tc['init_weights']} has network {ck['network']}")
        sd = ck.get("state_dict", ck.get("model"))
        model.load_state_dict({k: v.float() for k, v in sd.items()})
        for name, mod in model.named_modules():
            if name and any(name == r or name.startswith(r + ".") for r in tc["init_reset"]):
                if hasattr(mod, "reset_parameters"):
                    mod.reset_parameters()
    history: list[dict] = []
    last = out / "last.pt"
    if tc["resume"] and last.is_file():
        ck = torch.load(last, map_location=device, weights_only=False)
        if ck["network"] != net_cfg.to_dict():
            raise SystemExit(f"{last} was trained with network {ck['network']}, config asks for {net_cfg.to_dict()}")
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        start, history, elapsed0 = int(ck["step"]), ck.get("history", []), float(ck.get("elapsed_s", 0.0))
    (out / "config.json").write_text(json.dumps(cfg, indent=2, default=str))

    frozen = _freeze(model, tc["train_only"])
    if frozen:
        opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=lr0,
                               weight_decay=float(tc["weight_decay"]))
    workers = tc["num_workers"]
    workers = max(1, (os.cpu_count() or 2) - 1) if workers == "auto" else int(workers)
    val = validation_set(cfg)
    val_vec = validation_set(cfg, "vector")
    # bf16 autocast and channels-last also on the CPU: a training step of batch 16 at 80 px took
    # 0.84 s (fp32), 0.65 s (channels-last), 0.54 s (bf16) on one thread of this 2-core EPYC; both
    # together (0.41 s) give a NaN gradient in the dilated class conv, so the default is bf16 alone.
    use_amp = bool(tc["amp"]) and (device.type == "cuda" or bool(tc.get("cpu_amp")))
    channels_last = device.type == "cuda" or bool(tc.get("channels_last"))
    if channels_last:
        model = model.to(memory_format=torch.channels_last)
    log = _Log(steps, start)
    log.line(f"network {net_cfg.to_dict()}: {count_parameters(model)} parameters; device {device}; "
             f"steps {start}->{steps}; workers {workers}")
    t0 = time.time() - elapsed0

    def progress() -> float:
        # Fraction of training done: by steps, or by wall time when schedule_minutes is set.
        if budget_s is not None:
            return min((time.time() - t0) / budget_s, 1.0)
        return min(step / steps, 1.0)

    max_s = float(tc["max_minutes"]) * 60 if tc.get("max_minutes") else math.inf
    step = start
    run_loss = None
    loss_curve: list[float] = []  # raw loss of every step of this session
    stopped_early = False
    done = False
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
    _train_mode(model, frozen)
    while not done and not stopped_early:
        crop = _crop_at(tc["crop_schedule"], progress())
        # One loader per crop size; its stream is seeded by the step it starts at (resumable).
        loader = torch.utils.data.DataLoader(
            DrawingStream(cfg, crop, step), batch_size=int(tc["batch_size"]), num_workers=workers,
            pin_memory=device.type == "cuda", persistent_workers=False, worker_init_fn=_worker_init,
            prefetch_factor=4 if workers > 0 else None)
        for x, t, b in loader:
            x, t, b = (a.to(device, non_blocking=True) for a in (x, t, b))
            x, t, b = _augment(x, t, b)
            if channels_last:
                x = x.contiguous(memory_format=torch.channels_last)
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=use_amp):
                final, inter, logits = model(x, return_logits=True)
            loss, parts = keypoint_loss(final.float(), [i.float() for i in inter], t, b,
                                        tuple(float(w) for w in tc["loss_weights"]), float(tc["fp_weight"]))
            if float(tc["class_ce_weight"]) > 0:
                loss = loss + float(tc["class_ce_weight"]) * class_cross_entropy(logits.float(), t, b)
            frac = progress()
            lr = 0.5 * lr0 * (1 + math.cos(math.pi * frac))  # cosine annealing (paper)
            for g in opt.param_groups:
                g["lr"] = lr
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            step += 1
            done = step >= steps or (budget_s is not None and frac >= 1.0)
            lv = float(loss.detach())
            run_loss = lv if run_loss is None else 0.98 * run_loss + 0.02 * lv
            loss_curve.append(round(lv, 5))
            log.update(step, f"loss {run_loss:.4f} crop {crop} lr {lr:.2e}")
            if step % int(tc["log_every"]) == 0:
                log.line(f"step {step} loss {run_loss:.4f} crop {crop} lr {lr:.2e} "
                         f"{(step - start) / (time.time() - t0 - elapsed0):.1f} it/s")
            if step % int(tc["val"]["every"]) == 0 or done:
                r = evaluate(model, val, cfg["keypoints"], device)
                _train_mode(model, frozen)
                rec = {"step": step, "loss": run_loss, "val_f1": r.f1, "val_precision": r.precision,
                       "val_recall": r.recall, "val_accuracy": r.accuracy, "elapsed_s": time.time() - t0}
                msg = ""
                if val_vec:
                    rv = evaluate(model, val_vec, cfg["keypoints"], device)
                    _train_mode(model, frozen)
                    rec |= {"val_vector_f1": rv.f1, "val_vector_precision": rv.precision,
                            "val_vector_recall": rv.recall, "val_vector_accuracy": rv.accuracy}
                    msg = f"; held-out human strokes F1 {rv.f1:.3f} (P {rv.precision:.3f} R {rv.recall:.3f}) acc {rv.accuracy:.3f}"
                history.append(rec)
                log.line(f"step {step} val F1 {r.f1:.3f} (P {r.precision:.3f} R {r.recall:.3f}) "
                         f"class acc {r.accuracy:.3f}{msg}")
            over = time.time() - t0 - elapsed0 > max_s
            if step % int(tc["checkpoint_every"]) == 0 or done or over:
                _atomic_save({"model": model.state_dict(), "optimizer": opt.state_dict(), "step": step,
                              "elapsed_s": time.time() - t0, "network": net_cfg.to_dict(),
                              "history": history}, last)
            if over and not done:
                log.line(f"max_minutes reached at step {step}: stopping (resume to continue)")
                stopped_early = True
                break
            if done or _crop_at(tc["crop_schedule"], progress()) != crop:
                break
    log.close()
    record = {"steps": step, "planned_steps": steps, "schedule_minutes": tc.get("schedule_minutes"),
              "seconds": time.time() - t0, "completed": done, "device": str(device),
              "device_name": torch.cuda.get_device_name(0) if device.type == "cuda" else "cpu",
              "parameters": count_parameters(model), "history": history, "final_loss": run_loss,
              "torch": str(torch.__version__)}
    model_cpu = KeypointNet(net_cfg)
    model_cpu.load_state_dict({k: v.float().cpu() for k, v in model.state_dict().items()})
    export_weights(model_cpu, out / "keypoints.pt", {k: v for k, v in record.items() if k != "history"}
                   | {"config": cfg["train"], "last_val": history[-1] if history else None})
    (out / "record.json").write_text(json.dumps(record | {"loss_curve": loss_curve}, indent=2))
    record["loss_curve"] = loss_curve
    return record


# ------------------------------------------------------------------------------------------------
# Class branch on a frozen detector


def _class_weights(counts: torch.Tensor, power: float) -> torch.Tensor:
    """Cross-entropy class weights ∝ frequency^-power (0 = none, 1 = balanced), mean 1."""
    cw = (counts.sum() / counts.clamp_min(1)) ** power
    return (cw / cw.mean()).float()


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
    gcfg = GeneratorConfig.from_dict(cfg["train"]["generator"])
    rules = LabelRules.from_dict(cfg["train"]["labels"])
    r = patch // 2
    feats, classes, nears = [], [], []
    model.eval()
    with torch.inference_mode():
        for _ in range(count):
            s = generate(rng, gcfg, rules)
            if not len(s.points):
                continue
            x, t, b = prepare_sample(s, cfg)
            m = model.multiple
            h, w = x.shape
            xp = np.pad(x, ((r, r + m - (h + 2 * r) % m), (r, r + m - (w + 2 * r) % m)))
            f = model.trunk(torch.from_numpy(xp)[None, None])[0][0]
            tp = np.pad(t, ((0, 0), (r, r), (r, r)))
            bp = np.pad(b, ((r, r), (r, r)))
            for px, py in s.points:
                i, j = int(py) + r, int(px) + r
                feats.append(f[:, i - r:i + r + 1, j - r:j + r + 1].half())
                tt = tp[:, i - r:i + r + 1, j - r:j + r + 1]
                classes.append(torch.from_numpy(tt[1:4].argmax(0)))
                nears.append(torch.from_numpy((tt[0] > 0.5) & (bp[i - r:i + r + 1, j - r:j + r + 1] > 0)))
    return torch.stack(feats), torch.stack(classes).long(), torch.stack(nears)


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
    net_cfg = NetConfig.from_dict(tc["network"])
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
    for mod in head.modules():
        if hasattr(mod, "reset_parameters"):
            mod.reset_parameters()
    opt = torch.optim.Adam(head.parameters(), lr=float(cb["lr"]))
    n, bs, epochs = len(feats), int(cb["batch_size"]), int(cb["epochs"])
    total = epochs * math.ceil(n / bs)
    step, history = 0, []

    def centre_accuracy(fe, cl) -> float:
        head.eval()
        with torch.inference_mode():
            c = patch // 2
            pred = torch.cat([head(fe[k:k + 512].float())[:, :, c, c].argmax(1) for k in range(0, len(fe), 512)])
        head.train()
        return float((pred == cl[:, c, c]).float().mean())

    head.train()
    for ep in range(epochs):
        perm = torch.randperm(n)
        tot = 0.0
        for k in range(0, n, bs):
            idx = perm[k:k + bs]
            fe = feats[idx].float()
            if bool(torch.randint(0, 2, ())):  # flips and quarter turns, as in the detector's training
                fe, c_, nr = torch.flip(fe, (-1,)), torch.flip(cls[idx], (-1,)), torch.flip(near[idx], (-1,))
            else:
                c_, nr = cls[idx], near[idx]
            q = int(torch.randint(0, 4, ()))
            fe, c_, nr = torch.rot90(fe, q, (-2, -1)), torch.rot90(c_, q, (-2, -1)), torch.rot90(nr, q, (-2, -1))
            logits = head(fe)
            ce = F.cross_entropy(logits, c_, weight=cw, reduction="none")
            loss = ce[nr].mean()
            for g in opt.param_groups:
                g["lr"] = 0.5 * float(cb["lr"]) * (1 + math.cos(math.pi * step / total))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            step += 1
            tot += float(loss.detach()) * len(idx)
        rec = {"epoch": ep + 1, "loss": tot / n, "val_centre_accuracy": centre_accuracy(vfeats, vcls),
               "elapsed_s": time.time() - t0}
        history.append(rec)
        print(f"epoch {ep + 1} loss {rec['loss']:.4f} val centre acc {rec['val_centre_accuracy']:.3f} "
              f"({rec['elapsed_s']:.0f} s)", flush=True)
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


# ------------------------------------------------------------------------------------------------
# Keypoint typing by local valence (stages/keypoints/valence.py)


def _typing_samples(cfg: dict, count: int, seed: int, vector: bool):
    """Generated drawings (``count``), then (``vector``) the human strokes of ``train.vector``.

    Yields
    ------
    stages.keypoints.generator.Sample
    """
    rng = np.random.default_rng(seed)
    gcfg = GeneratorConfig.from_dict(cfg["train"]["generator"])
    rules = LabelRules.from_dict(cfg["train"]["labels"])
    for _ in range(count):
        yield generate(rng, gcfg, rules)
    if vector:
        limit = cfg["train"]["type_classifier"].get("vector_drawings")
        yield from vector_samples(cfg["train"].get("vector") or {}, rng, gcfg, rules,
                                  limit=None if limit is None else int(limit))


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


def draw_vector(rng: np.random.Generator, pool: dict, vcfg: dict, gcfg: GeneratorConfig, rules: LabelRules):
    """One styled, labelled rendering of a random drawing of ``pool`` (None when the pool is empty).

    A share ``stroke3_prob`` of the draws come from the stroke-3 symbols (on a ``stroke3_size``
    canvas: they are single characters), the rest from the Quick, Draw! drawings (``size``).
    """
    nd, s3 = pool.get("ndjson") or [], pool.get("stroke3") or []
    if not nd and not s3:
        return None
    source = "stroke3" if s3 and (not nd or rng.random() < float(vcfg.get("stroke3_prob", 0.0))) else "ndjson"
    drawings = pool[source]
    return render_vector(rng, drawings[rng.integers(len(drawings))], _canvas(vcfg, source), gcfg, rules)


def render_vector(rng: np.random.Generator, strokes: list[np.ndarray], size_range, gcfg: GeneratorConfig,
                  rules: LabelRules):
    """One styled, labelled rendering of a human-stroke drawing on a square canvas of side in ``size_range``."""
    lo, hi = (int(v) for v in size_range)
    size = int(rng.integers(lo, hi + 1))
    return drawing_from_strokes(rng, fit_strokes(strokes, size), (size, size), gcfg, rules)


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
    stages.keypoints.generator.Sample
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
    from stages.keypoints.labels import TYPE_CODES
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


# ------------------------------------------------------------------------------------------------
# Entry points


def _set(d: dict, dotted: str, value) -> None:
    keys = dotted.split(".")
    for k in keys[:-1]:
        d = d[k]
    d[keys[-1]] = value


def compose_plain(conf_dir: str | Path, overrides: list[str]) -> dict:
    """Compose train_app's sections from YAML without Hydra (for machines that lack it)."""
    import yaml

    conf_dir = Path(conf_dir)
    cfg = {name: yaml.safe_load((conf_dir / name / "default.yaml").read_text())
           for name in ("train", "keypoints", "prep")}
    for o in overrides:
        k, v = o.split("=", 1)
        _set(cfg, k, yaml.safe_load(v))
    return cfg


def main() -> None:
    """``polyvec-train`` (Hydra). ``--plain CONF_DIR key=value…`` composes without Hydra."""
    if len(sys.argv) > 2 and sys.argv[1] == "--plain":
        train(compose_plain(sys.argv[2], sys.argv[3:]))
        return
    if len(sys.argv) > 2 and sys.argv[1] == "--class-branch":
        train_class_branch(compose_plain(sys.argv[2], sys.argv[3:]))
        return
    if len(sys.argv) > 2 and sys.argv[1] == "--type-classifier":
        train_type_classifier(compose_plain(sys.argv[2], sys.argv[3:]))
        return
    import hydra
    from omegaconf import OmegaConf

    from pipeline.cli import no_stray_multirun

    @hydra.main(version_base=None, config_path="pkg://conf", config_name="train_app")
    def _app(cfg) -> None:
        train(OmegaConf.to_container(cfg, resolve=True))

    with no_stray_multirun():
        _app()


if __name__ == "__main__":
    main()
