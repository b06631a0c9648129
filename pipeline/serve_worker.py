"""``polyvec serve``'s runner: the folder's drawings and one background thread that runs their batches.

Every run goes through :func:`pipeline.engine.execute.batch.run_batch` with the command line's config
(:func:`~pipeline.engine.compose.compose_config` of the server's overrides, ``runtime.cluster=sync``)
and its store, so a drawing's stored stages are hits and the command line and the server share every
artifact. Batches run one at a time on one thread: the stages already use both cores, and requests
stay answered meanwhile (they only read this module's small records, under a lock). A page's jobs (an
edit, a setting, a page load, a download) go before the folder's first runs, and each drawing's first
run is a batch of its own, so a page opened while the rest of the folder runs waits for one drawing
at most.
"""

from __future__ import annotations

import itertools
import queue
import threading
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

from pipeline.engine.compose import compose_config
from pipeline.engine.execute.batch import run_batch, validated_stages
from pipeline.engine.execute.node import load_artifact
from pipeline.engine.store import ArtifactStore
from pipeline.hydra_command import UsageError
from pipeline.inputs import resolve_inputs
from pipeline.page import curve_layers

#: Seconds between two scans of the folder for new or changed drawings (the list page polls faster).
RESCAN_S = 2.0


@dataclass
class Drawing:
    """One image of the served folder and the state of its latest run with the server's own settings."""

    rel: str            #: path below the folder, with ``/`` (the URLs' name of the drawing)
    path: Path          #: the file (inside the folder)
    stamp: tuple        #: (mtime_ns, size) when it was last queued: a change queues it again
    state: str = "queued"   #: queued | running | done | failed
    stage: str = ""     #: the last stage finished (progress)
    done: int = 0       #: stages finished in the running batch
    error: str = ""


@dataclass
class Job:
    """One batch for the worker: the drawings, the flow settings and what came of it."""

    id: int
    drawings: list[Drawing]
    params: dict                #: ``lam``, ``dt`` (None: the config's), ``bezier`` (bool)
    kind: str = "run"           #: run (the folder's drawings) | edit (a page's re-run) | download
    shown_topology: str = ""    #: the topology key whose candidates the page shows already (not sent again)
    state: str = "queued"       #: queued | running | done | failed | superseded
    error: str = ""
    keys: dict = field(default_factory=dict)     #: stage → key, for a one-drawing job
    layers: list = field(default_factory=list)   #: the page's curve layers after an edit job
    seconds: float = 0.0
    finished: threading.Event = field(default_factory=threading.Event)

    def summary(self) -> dict:
        """What the status endpoint says of this job (JSON-able)."""
        out = {"job": self.id, "state": self.state, "error": self.error, "seconds": round(self.seconds, 3)}
        if self.state == "done" and self.kind == "edit":
            out["layers"], out["topology"] = self.layers, self.keys.get("topology", "")
        return out


def param_overrides(params: dict) -> list[str]:
    """``key=value`` overrides of a job's settings (``flow.lam``, ``flow.dt``, ``export.bezier``)."""
    out = []
    if params.get("lam") is not None:
        out.append(f"flow.lam={float(params['lam'])!r}")
    if params.get("dt") is not None:
        out.append(f"flow.dt={float(params['dt'])!r}")
    if params.get("bezier"):
        out.append("export.bezier=true")
    return out


class Runner:
    """The served folder's drawings and the thread that runs them.

    Parameters
    ----------
    folder : Path
        The served folder (its images, found recursively as ``polyvec FOLDER`` finds them).
    overrides : list of str
        ``key=value`` overrides from the command line, as ``polyvec`` takes them.

    Raises
    ------
    UsageError
        An override the config refuses.
    """

    def __init__(self, folder: Path, overrides: list[str]):
        self.folder = folder
        self.root = folder.resolve()
        # The command line's own config; sync: a few drawings at a time, in this process (its memo helps).
        self.overrides = [*overrides, "runtime.cluster=sync"]
        try:
            self.cfg = compose_config("config", self.overrides)
            self.stages = [s.name for s in validated_stages(self.cfg)]
        except Exception as exc:   # Hydra's and the schema's errors alike: one line
            said = " ".join(str(exc).split())   # Hydra's messages run over lines: one
            raise UsageError(f"{' '.join(overrides)}: {said}".strip()) from None
        self.store = ArtifactStore(str(self.cfg.store.path))
        self.drawings: dict[str, Drawing] = {}
        self.jobs: dict[int, Job] = {}
        self.lock = threading.Lock()
        self.queue: queue.PriorityQueue[tuple[int, int, Job]] = queue.PriorityQueue()
        self.ids = itertools.count(1)
        self.scanned_at = 0.0
        self.thread = threading.Thread(target=self._work, name="polyvec-serve-worker", daemon=True)

    # -- the folder --------------------------------------------------------------------------
    def start(self) -> None:
        """Scan the folder, queue every drawing, start the worker."""
        self.scan(force=True)
        self.thread.start()

    def inside(self, path: Path) -> bool:
        """Whether a path, its symbolic links followed, lies in the served folder."""
        return path.resolve().is_relative_to(self.root)

    def scan(self, force: bool = False) -> None:
        """Find the folder's drawings; queue one batch of the new and changed ones (at most every
        :data:`RESCAN_S` seconds unless ``force``)."""
        now = time.monotonic()
        if not force and now - self.scanned_at < RESCAN_S:
            return
        self.scanned_at = now
        try:
            found = resolve_inputs([str(self.folder)], self.folder)
        except UsageError:   # an empty folder is a list with nothing in it, not an error
            found = []
        fresh = []
        with self.lock:
            for image, _ in found:
                if not self.inside(image):
                    continue   # a link out of the folder: never served, never read
                rel = image.relative_to(self.folder).as_posix()
                try:
                    st = image.stat()
                except OSError:
                    continue
                stamp = (st.st_mtime_ns, st.st_size)
                old = self.drawings.get(rel)
                if old is None or old.stamp != stamp:
                    self.drawings[rel] = d = Drawing(rel, image, stamp)
                    fresh.append(d)
            for rel in set(self.drawings) - {image.relative_to(self.folder).as_posix() for image, _ in found}:
                del self.drawings[rel]
        for d in fresh:
            self.submit([d], {}, "run")

    def listing(self) -> list[dict]:
        """The drawings and their states (JSON-able), in path order."""
        self.scan()
        with self.lock:
            return [{"path": d.rel, "state": d.state, "stage": d.stage, "done": d.done, "stages": len(self.stages),
                     "error": d.error} for d in sorted(self.drawings.values(), key=lambda d: d.rel)]

    def drawing(self, rel: str) -> Drawing | None:
        """The drawing of that name, after a scan when it is not known yet."""
        if rel not in self.drawings:
            self.scan(force=True)
        return self.drawings.get(rel)

    # -- jobs --------------------------------------------------------------------------------
    def submit(self, drawings: list[Drawing], params: dict, kind: str, shown_topology: str = "") -> Job:
        """Queue a batch; an older queued edit of the same drawing is superseded (only the page's
        latest state matters, and a dragged slider would queue many)."""
        job = Job(next(self.ids), drawings, dict(params), kind, shown_topology)
        with self.lock:
            if kind == "edit":
                for other in self.jobs.values():
                    if other.kind == "edit" and other.state == "queued" and other.drawings == drawings:
                        other.state = "superseded"
                        other.finished.set()
            self.jobs[job.id] = job
            for old in [i for i, j in self.jobs.items() if j.finished.is_set()][:-200]:
                del self.jobs[old]   # keep the last finished ones for their pollers, not all of them
        self.queue.put((1 if kind == "run" else 0, job.id, job))   # a page's jobs first
        return job

    def run_now(self, drawing: Drawing, params: dict, timeout: float = 600) -> Job:
        """Queue a one-drawing batch and wait for it (a page load, a download)."""
        job = self.submit([drawing], params, "download")
        job.finished.wait(timeout)
        return job

    def job(self, job_id: int) -> Job | None:
        """The job of that id (None once forgotten: only the last 200 finished are kept)."""
        with self.lock:
            return self.jobs.get(job_id)

    def _work(self) -> None:
        while True:
            job = self.queue.get()[2]
            if job.state == "superseded":
                continue
            t0 = time.perf_counter()
            job.state = "running"
            try:
                self._run(job)
            except Exception as exc:   # a drawing that fails is a message, never a dead worker
                job.state, job.error = "failed", str(exc) or type(exc).__name__
                if job.kind == "run":
                    for d in job.drawings:
                        d.state, d.error = "failed", job.error
            job.seconds = time.perf_counter() - t0
            job.finished.set()

    def _run(self, job: Job) -> None:
        cfg = self.cfg
        extra = param_overrides(job.params)
        if extra:
            cfg = compose_config("config", self.overrides + extra)
        by_path = {str(d.path): d for d in job.drawings}

        def progress(result) -> None:
            d = by_path.get(result.image)
            if d is not None and job.kind == "run":
                d.state, d.done, d.stage = "running", d.done + 1, result.stage

        for d in job.drawings:
            if job.kind == "run":
                d.state, d.done = "running", 0
        batch = run_batch(list(by_path), cfg, on_result=progress, store=self.store)
        failed = batch.failed_images
        for path, d in by_path.items():
            keys = batch.keys(path)
            if job.kind == "run":
                d.state, d.error = ("failed", failed[path]) if path in failed else ("done", "")
            if len(by_path) == 1:
                job.keys = keys
                if path in failed:
                    job.state, job.error = "failed", failed[path]
                    return
        if job.kind == "edit" and "export" in job.keys:
            # through the memo: the artifacts just computed here are read from memory, not the store
            load = partial(load_artifact, self.store)
            layers = curve_layers(self.store, job.keys, load("prep", job.keys["prep"]).data, load)[0]
            # a λ or time step leaves the candidates as they are: ~40 % of the layers' bytes not sent again
            same = job.keys.get("topology") == job.shown_topology
            job.layers = [L for L in layers if not (same and L["id"] == "candidates")]
        job.state = "done"

    def export_text(self, keys: dict, bezier: bool) -> str | None:
        """The SVG text (or Bézier SVG) of a drawing's stored export artifact."""
        if "export" not in keys:
            return None
        data = load_artifact(self.store, "export", keys["export"]).data
        return data.get("bezier_svg") if bezier else data.get("svg")
