"""The live progress of a batch of hundreds of drawings (issue 54, item 4): an estimate of the time left."""

from __future__ import annotations

import io

from rich.console import Console

from pipeline.console import ETA_AFTER, StageProgress, time_left
from pipeline.engine.execute.base import TaskResult


def test_time_left_in_words():
    assert time_left(3.2) == "about 3 s left"
    assert time_left(44) == "about 45 s left"
    assert time_left(150) == "about 2 min left"
    assert time_left(3700) == "about 1 h 2 min left"
    assert time_left(-1) == "about 1 s left"


def _shown(n_images: int, finished: list[str], seconds_each: float = 2.0) -> str:
    """What a terminal shows of the progress after drawings finish with these statuses, 2 s apart."""
    out = io.StringIO()
    clock = [0.0]
    with StageProgress(["prep", "export"], n_images, True,
                       console=Console(file=out, force_terminal=True, width=140)) as progress:
        progress.clock, progress.started = (lambda: clock[0]), 0.0
        for i, status in enumerate(finished):
            clock[0] += seconds_each if status == "computed" else 0.0
            progress(TaskResult(f"d{i}.png", "prep", "k", "computed" if status == "computed" else "cached"))
            progress(TaskResult(f"d{i}.png", "export", "k", status))
    return out.getvalue()


def test_the_progress_shows_the_time_left_once_a_few_drawings_are_computed():
    assert "left" not in _shown(300, ["computed"] * (ETA_AFTER - 1))
    # 3 drawings in 6 s: 2 s each, 297 left -> 594 s
    assert "about 10 min left" in _shown(300, ["computed"] * 3)


def test_cached_drawings_do_not_shorten_the_estimate():
    """Cached drawings are done before any work: 100 of them and 3 computed in 6 s leave 197 drawings at
    2 s each, not at 6 s / 103."""
    assert "about 7 min left" in _shown(300, ["cached"] * 100 + ["computed"] * 3)


def test_no_estimate_once_every_drawing_is_done():
    assert "left" not in _shown(4, ["computed"] * 4).rsplit("export", 1)[-1]
