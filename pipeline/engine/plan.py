"""The plan: every (image, stage) task of a batch with its content-addressed key, computed up front.

Keys depend only on the image bytes, the stage's version, its config section and the keys of its
inputs (:func:`pipeline.engine.store.artifact_key`), so the driver knows before any work which
artifacts are stored already; cached stages never reach an executor.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

from pipeline.engine import edits
from pipeline.engine.registry import StageSpec
from pipeline.engine.store import artifact_key, hash_bytes


@dataclass(frozen=True)
class Task:
    """One (image, stage) unit of work."""

    image: str
    image_key: str
    stage: str
    version: str
    key: str
    inputs: dict[str, str]
    config: dict
    source: str = ""  # the image as an absolute path: a worker may run in another directory


def plan(images: Iterable[str | Path], cfg: Any, stages: list[StageSpec]) -> list[list[Task]]:
    """Tasks of every image, in topological order, with their content-addressed keys.

    The ``keypoint_edits`` config is per image: the parsed edits file that applies to it
    (:func:`pipeline.engine.edits.stage_config`).

    Raises
    ------
    pipeline.engine.edits.EditsError
        When an image's keypoint edits file is unreadable or malformed.
    """
    # Here, not at the top: the keypoints child unpickles Tasks (this module) and needs no config schemas.
    from pipeline.engine.config import stage_config

    out = []
    configs = {s.name: stage_config(cfg, s.name) for s in stages}
    for image in images:
        image = str(image)
        if "keypoint_edits" in configs:  # per image: the parsed <stem>.keypoints.json (edits.EditsError)
            configs["keypoint_edits"] = edits.stage_config(image, stage_config(cfg, "keypoint_edits"))
        try:
            image_key = hash_bytes(Path(image).read_bytes())
        except OSError as exc:
            image_key = "unreadable-" + hash_bytes(f"{image}:{exc}".encode())
        keys = {"image": image_key}
        tasks = []
        for s in stages:
            inputs = {"image": image_key} if not s.inputs else {i: keys[i] for i in s.inputs}
            keys[s.name] = artifact_key(s.name, s.version, configs[s.name], inputs)
            tasks.append(Task(image, image_key, s.name, s.version, keys[s.name], inputs, configs[s.name],
                              str(Path(image).absolute())))
        out.append(tasks)
    return out
