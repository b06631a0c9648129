"""``polyvec``: the Hydra app that vectorises a drawing, a folder or a glob through the stage DAG.

Examples
--------
``polyvec``                                   the bundled example drawing
``polyvec scans/ output=svg/``                every image of a folder (outputs mirror its tree)
``polyvec -m input=a.png flow.lam=0.05,0.2``  a sweep; upstream artifacts are shared cache hits
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.console import PROGRESS, StageProgress, compile_message, print_summary
from pipeline.engine.execute.base import BatchResult
from pipeline.engine.execute.batch import run_batch, validated_stages
from pipeline.engine.execute.dask_cluster import ClusterError
from pipeline.engine.execute.outputs import write_outputs
from pipeline.engine.execute.process import quiet_full_collections, reuse_freed_memory
from pipeline.engine.store import ArtifactStore
from pipeline.hydra_command import ExitCode, UsageError, hydra_app, multirun_folder
from pipeline.inputs import check_output_folder, resolve_inputs
from stages.errors import InputError

if TYPE_CHECKING:   # the keypoints child imports this module again (spawn): it needs no omegaconf
    from omegaconf import DictConfig

HELP = """usage: polyvec [PATH ...] [key=value ...] [-m] [--cfg job]

Vectorise raster line drawings (clean ink or scanned pencil) into SVG curves: Puhachov et al. 2021,
keypoint-driven PolyVector flow, run as a cached DAG of stages.

PATH is an image file, a folder (searched recursively) or a glob; input=PATH works too. With no
PATH, the bundled example drawing is vectorised. Outputs mirror the input tree under output=
(default out/): scans/clean/cat.png -> out/clean/cat.svg and out/clean/cat.json.

Stages (each a config group; key=value overrides its settings):
  prep            decode, lighting, contrast, ink
  keypoints       endpoints, junctions, corners (CNN)
  keypoint_edits  a user's corrections of the keypoints (<stem>.keypoints.json)
  field           PolyVector frame field
  extension       the field beyond the band, for the flow
  graph           streamlines, cross-sections, clean-up
  topology        key vertices, candidate paths
  flow            PolyVector flow of every path
  select          MIP choice of curves
  export          SVG + JSON (export.bezier=true: Béziers)

Examples:
  polyvec drawing.png                          one image -> out/drawing.svg
  polyvec scans/ "my drawings (2024)/cat.png"  a folder and a file
  polyvec scans/ output=svg/ flow.lam=0.5      every image of a folder, with an override
  polyvec drawing.png runtime.until=graph      stop after a stage
  polyvec -m drawing.png flow.lam=0.05,0.2     a sweep: shared stages are computed once
  polyvec --cfg job                            print the composed config

Other settings: store.path= (artifact store, default artifacts/), runtime.workers=,
runtime.cluster=sync|local|auto, runtime.scheduler_address=tcp://HOST:PORT.
Exit status: 0 done, 1 some image failed, 2 usage error, 130 interrupted (re-run to resume).
polyvec serve [FOLDER] [--port N] [key=value ...]: correct keypoints in the browser (polyvec serve --help).
See also: polyvec-inspect, polyvec-bench, polyvec-train."""


def job_output_dir(cfg: DictConfig) -> Path:
    """The output folder; in a multirun, a sub-folder named after the job's overrides."""
    return multirun_folder(Path(str(cfg.output)))


def run(cfg: DictConfig, inputs: list[str] | None = None) -> BatchResult:
    """Run the batch the config describes and write its outputs.

    Parameters
    ----------
    cfg : DictConfig
        The composed config.
    inputs : list of str, optional
        Paths given as positional arguments; ``cfg.input`` is used when there are none.

    Raises
    ------
    UsageError
        When the input names no image.
    """
    from rich.console import Console

    console = Console(stderr=True)
    out_dir = job_output_dir(cfg)
    named = resolve_inputs(inputs or cfg.get("input"), out_dir)
    check_output_folder(out_dir)
    images = [image for image, _ in named]
    try:
        # A value out of its range (export.join.max_turn_deg=200) is a usage error: one line, exit 2,
        # before the store is opened (run_batch checks again, for its other callers: milliseconds).
        stages = [s.name for s in validated_stages(cfg)]
    except InputError as exc:
        raise UsageError(str(exc)) from None
    store = ArtifactStore(str(cfg.store.path))
    if "keypoint_edits" in stages:
        announce_edits(images, cfg, console)
    PROGRESS.start(len(images), stages[-1] if stages else None)
    with StageProgress(stages, len(images), bool(cfg.runtime.get("progress", True)) and console.is_terminal) as prog:
        try:
            batch = run_batch(images, cfg, on_result=PROGRESS.counting(prog), store=store,
                              on_compile=lambda why: console.print(compile_message(why), highlight=False,
                                                                   soft_wrap=True))
        except ClusterError as exc:
            store.remove_if_unused()  # a run that did nothing leaves no empty store folder
            raise UsageError(str(exc)) from None
    write_outputs(batch, store, out_dir, {str(image): rel for image, rel in named})
    print_summary(batch, console, bool(cfg.runtime.get("debug", False)))
    if cfg.runtime.get("pages", False):
        from pipeline.page import write_pages

        for page in write_pages(batch, store, out_dir):
            console.print(f"wrote {page}", highlight=False, soft_wrap=True, markup=False)
    return batch


def announce_edits(images: list[Path], cfg: DictConfig, console) -> None:
    """Check the keypoint edits files that apply and print one line per image that has one.

    Raises
    ------
    UsageError
        ``keypoint_edits.file`` with several inputs, or an edits file that is unreadable or malformed.
    """
    from pipeline.engine.config import stage_config
    from pipeline.engine.edits import EditsError, find_edits, read_edits

    section = stage_config(cfg, "keypoint_edits")
    if section.get("file") and len(images) > 1:
        raise UsageError(f"keypoint_edits.file names one drawing's edits, but the input has {len(images)} images; "
                         "put <stem>.keypoints.json beside each image instead")
    for image in images:
        path = find_edits(image, section)
        if path is None:
            continue
        try:
            read_edits(path)
        except EditsError as exc:
            raise UsageError(str(exc)) from None
        how = "keypoint_edits.file" if section.get("file") else "found beside the input"
        console.print(f"keypoint edits: {path} for {image} ({how})", highlight=False, soft_wrap=True, markup=False)


_EXIT = ExitCode("polyvec", positional=True)


def _job(cfg: DictConfig) -> bool:
    return bool(run(cfg, _EXIT.inputs).failed_images)


def _run_job(cfg: DictConfig) -> None:
    _EXIT.job(_job, cfg)


_app = hydra_app(_run_job, "config")


def main() -> None:
    """Console entry point; exits 1 when any image failed, 2 on a usage error, 130 on Ctrl-C."""
    quiet_full_collections()   # before the stages' imports and tasks, which run in this process
    reuse_freed_memory()
    if any(a in ("--help", "-h") for a in sys.argv[1:]):
        try:
            print(HELP, flush=True)
        except BrokenPipeError:   # `polyvec --help | head`: the reader has what it wanted
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        sys.exit(0)
    _EXIT.console(_app, single=(_job, "config"))


if __name__ == "__main__":
    main()
