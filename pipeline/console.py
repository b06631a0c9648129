"""What ``polyvec`` shows while and after it runs: the live per-stage progress, the summary table, the
warning and error lines, and the count of finished work that the Ctrl-C line reports."""

from __future__ import annotations

import time

from pipeline.engine.execute.base import BatchResult, TaskResult
from pipeline.engine.registry import BY_NAME


def compile_message(why: str) -> str:
    """The line a run prints before its numba kernels compile (a first run that takes longer)."""
    return f"polyvec: compiling kernels, first run only (about half a minute; {why})"


#: Redraws a second of the live progress display (:class:`StageProgress`).
REFRESH_PER_SECOND = 2


#: Drawings that must have been computed before the live progress shows an estimate of the time left.
ETA_AFTER = 3


def time_left(seconds: float) -> str:
    """An estimate of the time left in words, rounded as a reader wants it: ``about 40 s left``,
    ``about 3 min left``, ``about 1 h 20 min left``."""
    seconds = max(0.0, seconds)
    if seconds < 60:
        return f"about {max(1, round(seconds / 5) * 5 if seconds >= 10 else round(seconds))} s left"
    minutes = round(seconds / 60)
    if minutes < 60:
        return f"about {minutes} min left"
    return f"about {minutes // 60} h {minutes % 60} min left"


class StageProgress:
    """rich progress: one bar per stage with computed / cached / failed counts, and on the last stage's
    bar an estimate of the time left once :data:`ETA_AFTER` drawings were computed.

    The estimate is the run's seconds so far per drawing computed, times the drawings left: cached
    drawings (and those a stored failure ends, :meth:`pipeline.engine.store.ArtifactStore.failure`) are
    reported before any work and count on neither side; on dask the drawings overlap, so the seconds per
    drawing are the batch's throughput, not one drawing's time.

    Parameters
    ----------
    stages : list of str
        The run's stages, in order; the last one's results count the drawings done.
    n_images : int
    enabled : bool
        False: nothing is drawn (not a terminal, ``runtime.progress=false``); the counts still are.
    console : rich.console.Console, optional
        Where it is drawn (rich's default console when None).
    """

    def __init__(self, stages: list[str], n_images: int, enabled: bool, console=None):
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self.enabled = enabled
        self.counts = {s: {"computed": 0, "cached": 0, "failed": 0, "skipped": 0} for s in stages}
        self.last = stages[-1] if stages else None
        self.n_images, self.started, self.clock = n_images, time.monotonic(), time.monotonic
        # Two redraws a second, not rich's ten: each redraw renders every stage's row on a thread of
        # this process, under the GIL its stages need (a drawing's default run in a terminal 0.1-0.6 s
        # longer at ten; stages/DECISIONS.md, engine). A task's result still shows within half a second.
        self.progress = Progress(TextColumn("{task.description:>10}"), BarColumn(), MofNCompleteColumn(),
                                 TextColumn("{task.fields[status]}"), TimeElapsedColumn(), console=console,
                                 disable=not enabled, transient=False, refresh_per_second=REFRESH_PER_SECOND)
        self.ids = {s: self.progress.add_task(s, total=n_images, status="") for s in stages}

    def __enter__(self):
        self.progress.__enter__()
        return self

    def __exit__(self, *exc):
        self.progress.__exit__(*exc)

    def __call__(self, r: TaskResult) -> None:
        if r.stage not in self.counts:
            return
        c = self.counts[r.stage]
        c[r.status] = c.get(r.status, 0) + 1
        status = f"[green]{c['computed']} computed[/] [cyan]{c['cached']} cached[/]"
        if c["failed"] or c["skipped"]:
            status += f" [red]{c['failed']} failed[/] [yellow]{c['skipped']} skipped[/]"
        if r.stage == self.last and (eta := self.eta()) is not None:
            status += f" {eta}"
        self.progress.update(self.ids[r.stage], advance=1, status=status)

    def eta(self) -> str | None:
        """The estimate of the time left (:func:`time_left`), None before :data:`ETA_AFTER` drawings
        were computed or once every drawing is done."""
        c = self.counts[self.last]
        left = self.n_images - sum(c.values())
        if c["computed"] < ETA_AFTER or left <= 0:
            return None
        return time_left((self.clock() - self.started) / c["computed"] * left)


def print_summary(batch: BatchResult, console, debug: bool = False) -> None:
    """Summary table (per stage) and one line per failed image.

    Paths and messages are escaped: rich would read ``[v2]`` in a file name as markup and drop it, and
    ``[/]`` as a closing tag with nothing to close (a traceback).
    """
    from rich.markup import escape
    from rich.table import Table

    table = Table(title=f"polyvec: {len(batch.results)} image(s) in {batch.wall_s:.1f} s")
    for col in ("stage", "computed", "cached", "failed", "skipped", "compute s"):
        table.add_column(col, justify="right" if col != "stage" else "left")
    counts = batch.counts()
    for stage in batch.stages:
        c = counts.get(stage, {})
        secs = sum(per[stage].duration_s for per in batch.results.values() if stage in per)
        table.add_row(stage, str(c.get("computed", 0)), str(c.get("cached", 0)), str(c.get("failed", 0)),
                      str(c.get("skipped", 0)), f"{secs:.2f}")
    console.print(table)
    for image, why in batch.failed_images.items():
        per = batch.results[image]
        if any(r.stored for r in per.values()):   # failed on this file and config before: not run again
            why += " — a stored failure of an earlier run; a changed file or config tries it again"
        console.print(f"[red]error[/] {escape(str(image))}: {escape(why)}", highlight=False, soft_wrap=True)
        detail = next((per[s].detail for s in batch.stages if s in per and per[s].status == "failed"), None)
        if debug and detail:
            console.print(detail, highlight=False, markup=False)
    for image, per in batch.results.items():
        for stage in batch.stages:
            r = per.get(stage)
            for note in (r.warnings if r is not None else ()):
                console.print(f"[yellow]warning[/] {escape(str(image))}: {stage}: {escape(str(note))}", highlight=False,
                              soft_wrap=True)
    for stage in batch.stages:
        # per-item stages: how much of the work earlier runs had done (one line per stage, not per image)
        done = [per[stage].items for per in batch.results.values() if stage in per and per[stage].items]
        reused, total = sum(d[0] for d in done), sum(d[1] for d in done)
        if reused:   # a first run reuses nothing: no line
            name = getattr(BY_NAME[stage].load(), "ITEM_NAME", "items")
            console.print(f"{stage}: {reused} of {total} {name} reused from earlier runs",
                          highlight=False, soft_wrap=True)
    for image, files in batch.outputs.items():
        console.print("wrote " + ", ".join(files), highlight=False, soft_wrap=True, markup=False)


class _Progress:
    """Images finished and stage results stored in this process (all jobs of a sweep), for the line
    printed on Ctrl-C: a batch runs the images side by side (:func:`pipeline.engine.execute.dask_cluster.priority`), so
    much of an interrupted one is stored before its first image is done, and a resume reuses it."""

    def __init__(self):
        self.done, self.total, self.last, self.stored = 0, 0, None, 0

    def start(self, n_images: int, last_stage: str | None) -> None:
        """A new job of ``n_images`` whose last stage is ``last_stage``."""
        self.total += n_images
        self.last = last_stage

    def counting(self, report):
        """``report`` wrapped so that every image's last-stage result counts it as done."""
        def wrapped(r: TaskResult) -> None:
            if r.stage == self.last:
                self.done += 1
            self.stored += r.status == "computed"
            report(r)
        return wrapped


PROGRESS = _Progress()
