"""Benchmark of the topology stage: time, counts and coverage per drawing.

Usage::

    python tests/benchmarks/bench_topology.py [--cases NAME ...] [--repeat 3] [--render OUT_DIR]
                                              [--keypoints reference|stage]

Cases (default: all available):

* ``synthetic``: the bundled example drawing through the real prep → field → graph, without keypoints;
  ``ladder-200``: a fixture graph (tests/synthetic_graph.py) of one component with 200 cycles
  and 4 keypoints — the kind of component on which the authors' constrained path search gives up;
* the four scanned drawings of ``../shared/data/drawings/scanned`` (no keypoints unless
  ``--keypoints stage``);
* ``example``: the authors' pencil dog with the authors' own predicted keypoints (example.pts);
* ten ``realvec_dev`` cases with their ground-truth keypoints (json: endpoints, junctions, corners).

``prep``, ``field`` and ``graph`` are computed once and cached (pickle under
``$TMPDIR/polyvec-bench-topology``, keyed by the image bytes, the three configs and the stages' source);
only the topology stage is timed (best of ``--repeat``), after a warm-up that loads the numba kernel.
``--keypoints stage`` runs the keypoints stage instead of the reference keypoints (only meaningful
once trained weights are packaged).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import pickle
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import ROOT, source_hash, stage_cfg  # noqa: E402

SHARED = ROOT / ".." / "shared" / "data"
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # tests/synthetic_graph.py, the fixture graphs

REALVEC = ["qd_dog_00_pencil", "qd_teddy-bear_00_clean", "cr_test_277_clean", "cr_test_199_pencil",
           "qd_cat_00_clean", "qd_giraffe_00_clean", "qd_crab_01_pencil", "qd_rhinoceros_01_pencil",
           "qd_rabbit_00_pencil", "qd_rhinoceros_00_clean"]
SCANNED = ["kitten", "puppy", "elephant", "banana_tree"]


_cfg = stage_cfg
_source_hash = source_hash


def _upstream(name: str, data: bytes, cache: Path) -> dict:
    """prep, field and graph artifacts of one drawing (cached)."""
    from stages import field, graph, prep

    cfgs = [_cfg(s) for s in ("prep", "field", "graph")]
    key = hashlib.sha1(data + json.dumps(cfgs, sort_keys=True).encode()
                       + _source_hash(ROOT / "stages" / "prep", ROOT / "stages" / "field",
                                      ROOT / "stages" / "graph").encode()).hexdigest()[:16]
    out = cache / f"{name}-{key}.pkl"
    if out.exists():
        return pickle.loads(out.read_bytes())
    t = time.perf_counter()
    p = prep.run(cfgs[0], image_bytes=data, image_name=f"{name}.png")
    f = field.run(cfgs[1], prep=p)
    g = graph.run(cfgs[2], prep=p, field=f)
    arts = {"prep": p, "field": f, "graph": g}
    out.write_bytes(pickle.dumps(arts))
    print(f"  {name}: prep + field + graph {time.perf_counter() - t:.1f} s (cached)", file=sys.stderr)
    return arts


def _keypoints_artifact(kps):
    from stages.artifact import Artifact

    pts = np.array([(x, y) for x, y, _ in kps], np.float32).reshape(-1, 2)
    return Artifact(arrays={"points": pts, "types": np.array([t for *_, t in kps], np.int8),
                            "scores": np.ones(len(pts), np.float32)}, data={})


def _reference_keypoints(name: str):
    if name == "example":
        lines = (SHARED / "authors_example" / "example.pts").read_text().split("\n")
        rows = [list(map(float, ln.split())) for ln in lines[1:1 + int(lines[0].split()[0])]]
        return [(c + 0.5, r + 0.5, int(t)) for r, c, t in rows]     # .pts is (row, col, type)
    if name in REALVEC:
        d = json.loads((SHARED / "realvec_dev" / f"{name}.json").read_text())
        return ([(x, y, 1) for x, y in d["endpoints"]] + [(x, y, 3) for x, y in d["junctions"]]
                + [(x, y, 5) for x, y in d["corners"]])
    return []


def _image(name: str) -> Path:
    if name == "example":
        return SHARED / "authors_example" / "example.png"
    if name in SCANNED:
        return SHARED / "drawings" / "scanned" / f"{name}.png"
    return SHARED / "realvec_dev" / f"{name}.png"


def _case_inputs(name: str, cache: Path, keypoints: str) -> tuple[dict, np.ndarray]:
    from synthetic_graph import ladder, synthetic_inputs

    from stages import synthetic

    if name == "ladder-200":
        key = cache / "ladder-200.pkl"
        if not key.exists():
            key.write_bytes(pickle.dumps(synthetic_inputs(ladder(200))))
        inputs = pickle.loads(key.read_bytes())
        return inputs, inputs["prep"]["grey"]
    if name == "synthetic":
        d = synthetic.example_drawing()
        arts = _upstream("synthetic-example", d.png_bytes(), cache)
        return {**arts, "keypoints": _keypoints_artifact([])}, arts["prep"]["grey"]
    arts = _upstream(name, _image(name).read_bytes(), cache)
    if keypoints == "stage":
        from stages import keypoints as kp_stage

        kp = kp_stage.run(_cfg("keypoints"), prep=arts["prep"])
    else:
        kp = _keypoints_artifact(_reference_keypoints(name))
    return {**arts, "keypoints": kp}, arts["prep"]["grey"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="*", default=None)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--render", type=Path, default=None, help="write <case>.png renders here")
    ap.add_argument("--keypoints", choices=["reference", "stage"], default="reference")
    args = ap.parse_args(argv)

    from synthetic_graph import synthetic_inputs

    import stages.topology as topology
    from stages.synthetic import line

    cache = Path(os.environ.get("TMPDIR", tempfile.gettempdir())) / "polyvec-bench-topology"
    cache.mkdir(parents=True, exist_ok=True)
    cases = args.cases
    if cases is None:
        cases = ["synthetic", "ladder-200"]
        if SHARED.exists():
            cases += SCANNED + ["example"] + REALVEC
    cfg = _cfg("topology")
    t = time.perf_counter()
    topology.run(cfg, **synthetic_inputs(line()))
    print(f"warm-up (numba kernel load/compile): {time.perf_counter() - t:.2f} s")
    if args.render:
        args.render.mkdir(parents=True, exist_ok=True)
    head = (f"{'case':24s} {'V':>6s} {'E':>6s} {'comp':>5s} {'kps':>4s} {'keyv':>5s} {'synth':>5s} "
            f"{'cand':>5s} {'loopA':>5s} {'loopB':>5s} {'cover%':>7s} {'time s':>7s}")
    print(head)
    print("-" * len(head))
    times = []
    for name in cases:
        inputs, grey = _case_inputs(name, cache, args.keypoints)
        best = np.inf
        for _ in range(max(1, args.repeat)):
            t = time.perf_counter()
            art = topology.run(cfg, **inputs)
            best = min(best, time.perf_counter() - t)
        times.append(best)
        c = art.data["counts"]
        cover = 100.0 * c["band_pixels_covered"] / max(c["band_pixels"], 1)
        print(f"{name:24s} {c['vertices']:6d} {c['edges']:6d} {c['components']:5d} {c['keypoints']:4d} "
              f"{c['key_vertices']:5d} {c['synthetic_key_vertices']:5d} {c['candidates']:5d} "
              f"{c['loop_a_paths']:5d} {c['loop_b_paths']:5d} {cover:7.2f} {best:7.3f}", flush=True)
        if args.render:
            from PIL import Image

            Image.fromarray(topology.render_topology(grey, art)).save(args.render / f"{name}.png")
    print(f"max {max(times):.3f} s, mean {np.mean(times):.3f} s over {len(times)} drawings")
    return 0


if __name__ == "__main__":
    sys.exit(main())
