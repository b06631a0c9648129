"""Stored artifacts of an image: what ``polyvec-inspect`` lists and the inspection page draws.

Queries over the store's manifests (an artifact names its image's hash and its inputs' keys), in the
stages' DAG order: every artifact of an image, the chain of artifacts upstream of one, and the chain
that a command line's config would use.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.engine.registry import STAGES
from pipeline.engine.store import ArtifactStore, hash_bytes

#: Stage → its place in the DAG's order.
STAGE_ORDER = {s.name: i for i, s in enumerate(STAGES)}


def artifacts_of(store: ArtifactStore, image: str) -> list[tuple[str, str, dict]]:
    """``(stage, key, manifest)`` of every artifact made from ``image`` (a path), newest last."""
    image_key = hash_bytes(Path(image).read_bytes())
    found = [(s, k, m) for s, k, m in store.iter_manifests() if m.get("image") == image_key]
    return sorted(found, key=lambda t: (STAGE_ORDER.get(t[0], 99), t[2].get("written_at", 0)))


def chain_keys(store: ArtifactStore, stage: str, key: str) -> dict[str, str]:
    """Stage → key of an artifact and of every artifact upstream of it (following the manifests)."""
    out = {stage: key}
    todo = [(stage, key)]
    while todo:
        s, k = todo.pop()
        for name, up in store.manifest(s, k).get("inputs", {}).items():
            if name != "image" and name not in out and store.exists(name, up):
                out[name] = up
                todo.append((name, up))
    return out


def latest_keys(store: ArtifactStore, image: str | Path) -> dict[str, str]:
    """Keys of one consistent chain of artifacts of ``image``: the newest artifact of the last stage
    stored, and everything upstream of it.

    Raises
    ------
    LookupError
        When nothing of the image is stored.
    """
    rows = artifacts_of(store, str(image))
    if not rows:
        raise LookupError(f"nothing stored for {image} in {store.url}; run `polyvec input={image}` first")
    last = max(rows, key=lambda r: (STAGE_ORDER.get(r[0], -1), r[2].get("written_at", 0)))
    return chain_keys(store, last[0], last[1])


def planned_keys(store: ArtifactStore, image: str | Path, overrides: list[str] | None = None) -> dict[str, str]:
    """Keys of the artifacts ``polyvec input=IMAGE [overrides]`` would use (its config composed as the
    CLI does, ``<stem>.keypoints.json`` beside the image included), when its last stage is stored;
    otherwise :func:`latest_keys`.
    """
    from pipeline.engine.compose import compose_config
    from pipeline.engine.plan import plan
    from pipeline.engine.registry import active_stages

    try:
        cfg = compose_config("config", list(overrides or []))
        (tasks,) = plan([image], cfg, active_stages())
    except ValueError:  # a malformed edits file beside the image (pipeline.engine.edits.EditsError)
        return latest_keys(store, image)
    if tasks and store.exists(tasks[-1].stage, tasks[-1].key):
        return chain_keys(store, tasks[-1].stage, tasks[-1].key)
    return latest_keys(store, image)
