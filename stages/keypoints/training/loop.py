"""The training loops of the keypoint network: the detector (:func:`train`) and the class branch
on a frozen detector (:func:`train_class_branch`).

The detector's loop is here; the class branch's is in :mod:`stages.keypoints.training.class_branch`,
the validation both run in :mod:`stages.keypoints.training.validation` and the checkpoint and weights
files they write in :mod:`stages.keypoints.training.checkpoints`.  This module gives those modules'
public names too, as :mod:`stages.keypoints.training` and the typing perceptron's training import
them from here.
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

from stages.config import from_section
from stages.errors import InputError
from stages.keypoints.inference import use_bf16
from stages.keypoints.network import KeypointNet, NetConfig, count_parameters
from stages.keypoints.training.checkpoints import _atomic_save, export_weights
from stages.keypoints.training.data import DrawingStream, compose_settings, stroke_count_power, validation_set
from stages.keypoints.training.targets import class_cross_entropy, junction_weighted_band, keypoint_loss
from stages.keypoints.training.validation import evaluate
from stages.keypoints.training.widen import widen

__all__ = ["cpu_autocast", "train"]


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
