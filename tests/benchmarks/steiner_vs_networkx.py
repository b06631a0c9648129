"""Hand-written Steiner trees (stages/topology/steiner.py) against networkx's ``steiner_tree``.

Usage::

    python tests/benchmarks/steiner_vs_networkx.py [FOLDER]     # default ../shared/data/drawings

Runs prep → topology on every PNG below FOLDER (in-process, a temporary store), records every
Steiner problem the topology stage solves, then times both implementations (Mehlhorn and Kou) on
them and compares the tree weights.
"""

import sys
import tempfile
import time
from pathlib import Path

import networkx as nx
import numpy as np
from networkx.algorithms.approximation import steiner_tree as nx_steiner

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import stages.topology.candidates as ex  # noqa: E402
from stages.topology.steiner import steiner_tree  # noqa: E402


def record(folder: Path) -> list:
    from hydra import compose, initialize_config_module

    from pipeline.engine.execute.batch import run_batch

    calls = []
    orig = ex.steiner_tree

    def rec(csr, term, method="mehlhorn"):
        calls.append((csr.copy(), np.asarray(term).copy()))
        return orig(csr, term, method)

    ex.steiner_tree = rec
    with tempfile.TemporaryDirectory() as store, initialize_config_module(config_module="conf", version_base=None):
        cfg = compose(config_name="config", overrides=["runtime.cluster=sync", "runtime.until=topology",
                                                        f"store.path={store}", "runtime.progress=false"])
        run_batch(sorted(str(p) for p in folder.rglob("*.png")), cfg)
    ex.steiner_tree = orig
    return calls


def main() -> None:
    folder = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT.parent / "shared" / "data" / "drawings"
    calls = record(folder)
    tot = {k: 0.0 for k in ("ours-mehlhorn", "ours-kou", "nx-mehlhorn", "nx-kou", "nx-graph-build")}
    worst = dict.fromkeys(tot, 0.0)
    ratio = {"mehlhorn": [], "kou": []}
    for csr, term in calls:
        t = time.perf_counter()
        coo = csr.tocoo()
        g = nx.Graph()
        g.add_weighted_edges_from(zip(coo.row.tolist(), coo.col.tolist(), coo.data.tolist()))
        tot["nx-graph-build"] += time.perf_counter() - t
        for m in ("mehlhorn", "kou"):
            t = time.perf_counter()
            e = steiner_tree(csr, term, m)
            d = time.perf_counter() - t
            tot["ours-" + m] += d
            worst["ours-" + m] = max(worst["ours-" + m], d)
            t = time.perf_counter()
            tree = nx_steiner(g, [int(x) for x in term], weight="weight", method=m)
            d = time.perf_counter() - t
            tot["nx-" + m] += d
            worst["nx-" + m] = max(worst["nx-" + m], d)
            if tree.size(weight="weight") > 0:
                ratio[m].append(sum(csr[a, b] for a, b in e) / tree.size(weight="weight"))
    sizes = [c[0].shape[0] for c in calls]
    print(f"{len(calls)} Steiner problems, vertices median {int(np.median(sizes))} max {max(sizes)}")
    for k in tot:
        print(f"{k}: total {tot[k]:.3f} s, worst call {worst[k] * 1000:.1f} ms")
    for m, r in ratio.items():
        print(f"{m}: tree weight ours / networkx mean {np.mean(r):.4f} max {np.max(r):.4f}")


if __name__ == "__main__":
    main()
