"""The README: its sweep, resume and remote-cluster commands run as written (on tiny drawings), and every
```bash block of it is run by some test.

The other blocks are run where their feature is tested: ``Running`` and ``Inspecting intermediate
artifacts`` by tests/pipeline/test_cli.py, the keypoint corrections by tests/pipeline/test_inspect_page.py,
training and ``polyvec-bench`` by tests/pipeline/test_readme_training.py (see :data:`RUN_BY`). Each of
those tests, and the ones here, runs the *first* ```bash block after its heading; a second block under a
heading, or a block under a heading no test reads, fails :func:`test_every_bash_block_is_run_by_a_test`.
"""

from __future__ import annotations

import math
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from stages import synthetic

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"

#: A README heading (without ``## ``) → the test that runs the first ```bash block below it.
RUN_BY = {
    "Running": "tests/pipeline/test_cli.py::test_readme_running_commands",
    "Sweeps": "tests/test_readme.py::test_the_sweep_commands_recompute_only_the_flow_and_after",
    "Resuming": "tests/test_readme.py::test_the_resume_commands_pick_up_after_ctrl_c",
    "Inspecting intermediate artifacts": "tests/pipeline/test_cli.py::test_readme_inspect_commands",
    "Correcting keypoints on the inspection page": "tests/pipeline/test_inspect_page.py::test_the_readme_commands_run",
    "Correcting in the browser: polyvec serve": "tests/pipeline/test_serve.py::test_the_readme_commands_run",
    "A remote dask cluster":
        "tests/pipeline/test_cluster_remote.py::test_a_worker_killed_mid_batch_leaves_the_svgs_byte_identical",
    "Keypoint detector: training and evaluation":
        "tests/pipeline/test_readme_training.py::test_readme_detector_and_bench_commands_run",
    "Evaluation: `polyvec-bench`": "tests/pipeline/test_readme_training.py::test_readme_detector_and_bench_commands_run",
}

#: The block above the first heading: the set-up, run by CI (.ci/run) rather than by a test.
SETUP = ['pip install torch==2.13.0 && pip install -e ".[test]" && polyvec', "python -m pytest -q -n 2"]

MAX_LINES = 260

#: Engine internals that belong in docs/ARCHITECTURE.md, not in the user's guide.
INTERNALS = ("mallopt", "glibc", "fork", "GIL", "THREAD_ENV", "garbage collection")

#: Stages above the flow, and the flow with the stages after it (a λ or time-step change reaches these).
UPSTREAM = ("prep", "keypoints", "keypoint_edits", "field", "extension", "graph", "topology")
DOWNSTREAM = ("flow", "select", "export")


# -- reading the README ------------------------------------------------------------------------
def _code_blocks() -> list[tuple[str | None, int, str, list[str]]]:
    """Every fenced block of the README: (its ``## `` heading or None above the first, its place
    among that section's blocks of the same language, the language, its lines)."""
    heading, fence, blocks, seen = None, None, [], {}
    for line in README.read_text().splitlines():
        if fence is None and line.startswith("## "):
            heading = line[3:].strip()
        elif fence is None and line.startswith("```"):
            fence = (line[3:].strip(), [])
        elif fence is not None and line.startswith("```"):
            lang, lines = fence
            n = seen[(heading, lang)] = seen.get((heading, lang), -1) + 1
            blocks.append((heading, n, lang, lines))
            fence = None
        elif fence is not None:
            fence[1].append(line)
    assert fence is None, "README.md: a code block is not closed"
    return blocks


def _lines(heading: str) -> list[str]:
    """The lines of the first ```bash block below ``## heading``, comments kept, blank lines dropped."""
    for h, n, lang, lines in _code_blocks():
        if h == heading and lang == "bash" and n == 0:
            return [ln.strip() for ln in lines if ln.strip()]
    raise AssertionError(f"README.md has no ```bash block under '## {heading}'")


def _command(line: str) -> str:
    """A block's line without its comment (two spaces and ``#``, as the other README tests read them)."""
    return line.split("  #", 1)[0].strip()


def _jobs(args: list[str]) -> int:
    """How many jobs a command line runs: with ``-m``, every combination of its comma-separated values."""
    if "-m" not in args:
        return 1
    return math.prod(len(a.split("=", 1)[1].split(",")) for a in args if "=" in a and not a.startswith("input="))


def _manifests(store: Path, stage: str) -> list[Path]:
    return sorted((store / stage).glob("*/*/manifest.json"))


def _env() -> dict[str, str]:
    return dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(REPO))


# -- the README as a whole ---------------------------------------------------------------------
def test_every_bash_block_is_run_by_a_test():
    """Each ```bash block is the first one under a heading of :data:`RUN_BY` (whose test exists), or the
    set-up block above the first heading; a new block without a test fails here."""
    blocks = [(h, n, lines) for h, n, lang, lines in _code_blocks() if lang in ("bash", "sh", "shell", "console")]
    assert blocks, "README.md has no ```bash block"
    for heading, n, lines in blocks:
        where = f"the ```bash block #{n + 1} under '## {heading}'" if heading else "the set-up block"
        if heading is None:
            assert n == 0 and [_command(ln) for ln in lines if ln.strip()] == SETUP, where
            continue
        assert heading in RUN_BY, f"{where}: no test runs it (add one, and its heading to RUN_BY)"
        assert n == 0, f"{where}: the README tests run only the first block under a heading"
    headings = {h for h, _, _ in blocks}
    for heading, test in RUN_BY.items():
        assert heading in headings, f"'## {heading}' (run by {test}) is gone from README.md, or has no ```bash block"
        path, name = test.split("::")
        assert re.search(rf"^def {name}\(", (REPO / path).read_text(), re.MULTILINE), f"{test} does not exist"


def test_the_readme_is_a_short_users_guide():
    """At most :data:`MAX_LINES` lines; the set-up CI runs is the README's; no engine internals."""
    text = README.read_text()
    assert len(text.splitlines()) <= MAX_LINES, f"README.md has {len(text.splitlines())} lines (at most {MAX_LINES})"
    ci = (REPO / ".ci" / "run").read_text()
    assert "torch==2.13.0" in ci and "python -m pytest -q -n 2" in ci
    for word in INTERNALS:
        assert word not in text, f"README.md mentions {word!r}: engine internals go to docs/ARCHITECTURE.md"
    assert (REPO / "docs" / "ARCHITECTURE.md").is_file()


def test_the_architecture_cites_real_decisions():
    """Every entry of stages/DECISIONS.md that docs/ARCHITECTURE.md cites ("2026-11-25 — In-process runs …",
    the start of its heading) is the start of exactly one heading there."""
    def flat(text: str) -> str:
        return re.sub(r"\s+", " ", text)

    headings = [flat(line[4:].strip()) for line in (REPO / "stages" / "DECISIONS.md").read_text().splitlines()
                if line.startswith("### ")]
    cited = re.findall(r'"(20\d\d-\d\d-\d\d — [^"]+)"', flat((REPO / "docs" / "ARCHITECTURE.md").read_text()))
    assert len(cited) >= 20
    for entry in cited:
        assert sum(h.startswith(entry) for h in headings) == 1, f"docs/ARCHITECTURE.md cites {entry!r}"


# -- the README's commands ---------------------------------------------------------------------
@pytest.mark.slow
def test_the_sweep_commands_recompute_only_the_flow_and_after(tmp_path, cli):
    """After a first run of the drawing, a λ re-run and the README's sweep compute prep … topology no
    more; the flow, select and export once per job, each job's files in the folder the README names."""
    (tmp_path / "drawing.png").write_bytes(synthetic.tee(size=64).png_bytes())
    first = cli("drawing.png", "runtime.cluster=sync", cwd=tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    jobs = 1
    for line in _lines("Sweeps"):
        args = shlex.split(_command(line))
        assert args[0] == "polyvec", line
        proc = cli(*args[1:], "runtime.cluster=sync", cwd=tmp_path)
        assert proc.returncode == 0, (line, proc.stderr[-2000:])
        jobs += _jobs(args)
        for named in re.findall(r"→ (\S+)", line.split("  #", 1)[1] if "  #" in line else ""):
            if named.startswith("out/"):
                assert (tmp_path / named).is_file(), (line, named)
    store = tmp_path / "artifacts"
    assert {s: len(_manifests(store, s)) for s in UPSTREAM} == dict.fromkeys(UPSTREAM, 1)
    assert {s: len(_manifests(store, s)) for s in DOWNSTREAM} == dict.fromkeys(DOWNSTREAM, jobs)
    assert jobs > 2


@pytest.mark.slow
def test_the_resume_commands_pick_up_after_ctrl_c(tmp_path, cli):
    """The README's first command interrupted by Ctrl-C once a stage's result is stored (exit status
    130, one line); its second reads back every stored result and writes every SVG."""
    scans = tmp_path / "scans"
    scans.mkdir()
    for name, drawing in (("tee", synthetic.tee(size=64)), ("vee", synthetic.vee(size=64)),
                          ("cross", synthetic.cross(size=64))):
        (scans / f"{name}.png").write_bytes(drawing.png_bytes())
    first, again = (shlex.split(_command(line)) for line in _lines("Resuming"))
    assert first == again and first[0] == "polyvec"
    store = tmp_path / "artifacts"
    # SIGINT back to its default in the run: a suite started from a background or non-interactive shell
    # passes SIGINT down ignored, and Python then installs no handler (the Ctrl-C a terminal sends is not)
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.launch", *first[1:], "runtime.cluster=sync"],
                            cwd=tmp_path, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 300
        while not _manifests(store, "field") and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert proc.poll() is None, "the run ended before it could be interrupted"
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err[-2000:]
    assert len(err.strip().splitlines()) == 1 and "run the same command again to resume" in err, err[-2000:]
    stored = {p: p.stat().st_mtime_ns for p in store.glob("*/*/*/manifest.json")}
    assert stored
    resumed = cli(*again[1:], "runtime.cluster=sync", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert {p: p.stat().st_mtime_ns for p in stored} == stored          # read back, not computed again
    out = tmp_path / next(a for a in first if a.startswith("output=")).split("=", 1)[1]
    assert sorted(p.name for p in out.glob("*.svg")) == ["cross.svg", "tee.svg", "vee.svg"]
