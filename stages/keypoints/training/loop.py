"""The training loops of the keypoint network: the detector (:func:`train`) and the class branch
on a frozen detector (:func:`train_class_branch`).
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from stages.config import from_section
from stages.errors import InputError
from stages.evaluate.keypoints import MatchResult, match_keypoints
from stages.keypoints.inference import find_keypoints, use_bf16
from stages.keypoints.network import KeypointNet, NetConfig, count_parameters
from stages.keypoints.training.data import (DrawingStream, compose_settings, draw_vector, prepare_sample,
                                            stroke_count_cdf, stroke_count_power, validation_set, vector_pool)
from stages.keypoints.training.generator import GeneratorConfig, generate
from stages.keypoints.training.labels import LabelRules
from stages.keypoints.training.targets import class_cross_entropy, junction_weighted_band, keypoint_loss
from stages.keypoints.training.widen import widen


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


def cpu_autocast(cpu_amp) -> bool:
    """Whether ``train.cpu_amp`` (true, false or ``"auto"``) means bf16 autocast on this CPU.

    ``auto`` follows ``keypoints.precision: auto`` (:func:`~stages.keypoints.inference.use_bf16`):
    bf16 only where the CPU has native bf16 instructions.
    """
    if isinstance(cpu_amp, bool):
        return cpu_amp
    if cpu_amp == "auto":
        return use_bf16("auto")
    raise InputError(f"train.cpu_amp must be true, false or auto, got {cpu_amp!r}")


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
    cpu_bf16 = cpu_autocast(tc["cpu_amp"])    # checked before anything is written
    stroke_count_power(tc.get("vector") or {})
    compose_settings(tc.get("vector") or {})
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
    net_cfg = from_section(NetConfig, tc["network"], "train.network")
    model = KeypointNet(net_cfg).to(device)
    steps = int(tc["steps"])
    budget_s = float(tc["schedule_minutes"]) * 60 if tc.get("schedule_minutes") else None
    lr0 = float(tc["lr"])
    opt = torch.optim.Adam(model.parameters(), lr=lr0, weight_decay=float(tc["weight_decay"]))
    start, elapsed0 = 0, 0.0
    widened_from = None
    if tc.get("init_weights") and not (tc["resume"] and (out / "last.pt").is_file()):
        # Warm start (fine-tuning) from an exported or training checkpoint of the same network.
        ck = torch.load(tc["init_weights"], map_location=device, weights_only=False)
        sd = ck.get("state_dict", ck.get("model"))
        if ck["network"] != net_cfg.to_dict():
            # A wider train.network starts from the narrow checkpoint's function (training/widen.py).
            try:
                sd = widen(sd, NetConfig.from_dict(ck["network"]), net_cfg)
            except ValueError:
                raise SystemExit(f"init_weights {tc['init_weights']} has network {ck['network']}, which "
                                 f"train.network {net_cfg.to_dict()} neither equals nor widens") from None
            widened_from = ck["network"]
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
        widened_from = ck.get("widened_from")
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
    # 0.84 s (fp32), 0.65 s (channels-last), 0.54 s (bf16) on one thread of a 2-core EPYC with native
    # bf16; both together (0.41 s) give a NaN gradient in the dilated class conv, so the default is bf16
    # alone — where the CPU has it: emulated (AVX2 only) a step took 6.5 s against 0.94 s in fp32.
    use_amp = bool(tc["amp"]) and (device.type == "cuda" or cpu_bf16)
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
            loss, parts = keypoint_loss(final.float(), [i.float() for i in inter], t,
                                        junction_weighted_band(b, t, float(tc["junction_loss_weight"])),
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
                              "widened_from": widened_from, "history": history}, last)
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
              "torch": str(torch.__version__), "widened_from": widened_from}
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


