"""Benchmark: the keypoints stage on a 700×700 drawing (target ≤ 1.5 s on one thread of a 2-core CPU).

Run: ``python tests/benchmarks/bench_keypoints.py [--repeat 5] [--size 700] [KEY=VALUE ...]`` (overrides of
the keypoints section, e.g. ``'detection_ensemble=[packaged_procedural]' precision=fp32``). Prints the time of
``stages.keypoints.run`` (1 torch thread, as inside a worker — the stage sets it; the process's heap set as
the keypoints child's), of its first call in the process (the weights already loaded) and, for comparison,
of the network alone with 2 threads. Not a test: timings depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
import yaml

from pipeline.engine.execute.process import keep_network_memory
from stages.artifact import Artifact
from stages.config import from_section
from stages.keypoints import load_model, run
from stages.keypoints.training.generator import GeneratorConfig, drawing_from_strokes, generate
from stages.keypoints.training.labels import LabelRules

ROOT = Path(__file__).resolve().parents[2]


def drawing(size: int) -> Artifact:
    """A procedural drawing of ``size``×``size`` px (a 320-px drawing scaled up, clean ink)."""
    rng = np.random.default_rng(7)
    train = yaml.safe_load((ROOT / "conf" / "train" / "default.yaml").read_text())
    generator = from_section(GeneratorConfig, train["generator"], "train.generator")
    rules = from_section(LabelRules, train["labels"], "train.labels")
    cfg = replace(generator, primitives_min=12, primitives_max=12, pencil_prob=0.0)
    s = generate(rng, cfg, rules)
    k = size / s.grey.shape[0]
    strokes = [p * k for p in s.strokes]
    widths = [w * k * 0.6 for w in s.widths]
    d = drawing_from_strokes(rng, strokes, (size, size), cfg, rules, widths)
    return Artifact(arrays={"grey": d.grey, "mask": d.grey < 0.647}, data={})


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--size", type=int, default=700)
    ap.add_argument("overrides", nargs="*", help="KEY=VALUE of the keypoints section (YAML values)")
    args = ap.parse_args()
    cfg = yaml.safe_load((ROOT / "conf" / "keypoints" / "default.yaml").read_text())
    for item in args.overrides:
        key, _, value = item.partition("=")
        if key not in cfg:
            raise SystemExit(f"bench_keypoints: no key {key!r} in the keypoints section")
        cfg[key] = yaml.safe_load(value)
    keep_network_memory()  # as in the keypoints child that runs the stage (pipeline/engine/execute/child.py)
    prep = drawing(args.size)
    model, name = load_model(cfg["weights"])
    t = time.perf_counter()
    run(cfg, prep=prep)  # the first pass: the child of a one-drawing run makes only this one
    first = time.perf_counter() - t
    times, cpu = [], []
    for _ in range(args.repeat):
        t, c = time.perf_counter(), time.process_time()
        a = run(cfg, prep=prep)
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    # The stage runs on one thread, so its CPU seconds are its wall seconds on a quiet core: the CPU
    # column is the one to read on a busy machine.
    print(f"keypoints.run {args.size}x{args.size} ({name}, {cfg['torch_threads']} thread): "
          f"wall min {min(times):.2f} s, median {np.median(times):.2f} s; "
          f"CPU min {min(cpu):.2f} s, median {np.median(cpu):.2f} s; {len(a['points'])} keypoints; "
          f"first call in this process {first:.2f} s (its memory faulted in page by page)")
    torch.set_num_threads(2)
    x = torch.rand(1, 1, (args.size // 8 + 1) * 8, (args.size // 8 + 1) * 8)
    nt = []
    with torch.inference_mode():
        for _ in range(args.repeat):
            t = time.perf_counter()
            model(x)
            nt.append(time.perf_counter() - t)
    print(f"network alone, 2 threads: min {min(nt):.2f} s, median {np.median(nt):.2f} s")


if __name__ == "__main__":
    main()
