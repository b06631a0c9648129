"""A batch's output files: ``<name>.svg``, ``<name>.json`` (and ``<name>.bezier.svg``) of each exported image."""

from __future__ import annotations

import json
import os
from pathlib import Path

from pipeline.engine.execute.base import BatchResult
from pipeline.engine.execute.node import load_artifact
from pipeline.engine.store import ArtifactStore


def write_outputs(batch: BatchResult, store: ArtifactStore, output_dir: str | Path,
                  names: dict[str, str | Path] | None = None) -> dict[str, list[str]]:
    """Write ``<name>.svg``, ``<name>.json`` (and ``<name>.bezier.svg``) of every exported image.

    Parameters
    ----------
    batch : BatchResult
    store : ArtifactStore
    output_dir : path
    names : dict, optional
        Image → output path relative to ``output_dir`` without suffix (the CLI mirrors the input
        tree); by default the image's stem. A name is a function of its image alone, never of which
        other images failed.

    Returns
    -------
    dict
        Image → files written. An image whose files cannot be written is left out, its reason in
        ``batch.output_errors``.

    Raises
    ------
    ValueError
        When two images of the batch have the same name.
    """
    output_dir = Path(output_dir)
    names = {image: Path(names[image]) if names and image in names else Path(Path(image).stem)
             for image in batch.results}
    if len(set(names.values())) != len(names):
        raise ValueError("two images of the batch have the same output name")
    written: dict[str, list[str]] = {}
    for image, per in batch.results.items():
        r = per.get("export")
        if r is None or r.status not in ("computed", "cached"):
            continue
        texts = output_texts(output_dir / names[image], load_artifact(store, "export", r.key).data, str(image),
                             r.key)
        where = (output_dir / names[image]).parent
        try:
            where.mkdir(parents=True, exist_ok=True)
            for where, text in texts.items():
                atomic_write(where, text)
        except OSError as exc:
            # one image's files (a sub-folder's name taken by a file, a full disk): its error line,
            # the other images' files still written; what it wrote stays (whole files only)
            batch.output_errors[image] = f"cannot write {where} ({exc.strerror or exc})"
            continue
        written[image] = [str(p) for p in texts]
    batch.outputs = written
    return written


def output_texts(stem: Path, export: dict, source: str, key: str | None) -> dict[Path, str]:
    """The files of one exported drawing, ``<stem>.svg``, ``<stem>.json`` (and ``<stem>.bezier.svg``),
    by path: the export artifact's ``data`` with the input's path and the artifact's key in the JSON."""
    payload = {k: v for k, v in export.items() if k not in ("svg", "bezier_svg")}
    payload.update(source=source, artifact=key)
    texts = {stem.with_name(stem.name + ".svg"): export["svg"],
             stem.with_name(stem.name + ".json"): curves_json(payload)}
    if export.get("bezier_svg"):
        texts[stem.with_name(stem.name + ".bezier.svg")] = export["bezier_svg"]
    return texts


def curves_json(payload: dict) -> str:
    """The curves JSON written beside each SVG: one top-level key per line, one list item per line.

    ``json.dumps(indent=…)`` streams through the pure-Python encoder (~0.1 s for the elephant's 93
    curves, a fifteenth of its λ re-run) and put every coordinate on a line of its own; here each line
    is one call of the C encoder, and a curve reads as one line.
    """
    lines = []
    for k, v in payload.items():
        if isinstance(v, list) and v:
            items = ",\n".join("  " + json.dumps(x) for x in v)
            lines.append(f" {json.dumps(k)}: [\n{items}\n ]")
        else:
            lines.append(f" {json.dumps(k)}: {json.dumps(v)}")
    return "{\n" + ",\n".join(lines) + "\n}\n"


def atomic_write(path: Path, content: str | bytes) -> None:
    """Write a file whole or not at all (a temporary file renamed into place): a reader — another
    process, the next run — never sees half of it."""
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        if isinstance(content, bytes):
            tmp.write_bytes(content)
        else:
            tmp.write_text(content)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
