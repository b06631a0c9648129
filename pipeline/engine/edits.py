"""Keypoint edit files for the ``keypoint_edits`` stage: finding, reading and checking them.

The engine owns the I/O: it finds ``keypoint_edits.file`` or ``<stem>.keypoints.json`` beside an
input, parses it, and puts the parsed content (not the path) into the stage's config, so the
artifact key hashes what the edits say; ``file`` and ``auto`` only say where to look and are left out
of the key.
"""

from __future__ import annotations

import json
from pathlib import Path

EDITS_SUFFIX = ".keypoints.json"
LOCATOR_KEYS = ("file", "auto")


class EditsError(ValueError):
    """A keypoint edits file that cannot be used, as one line naming the file."""


def edits_path_for(image: str | Path) -> Path:
    """``<stem>.keypoints.json`` beside an image."""
    image = Path(image)
    return image.with_name(image.stem + EDITS_SUFFIX)


def find_edits(image: str | Path, section: dict) -> Path | None:
    """The edits file that applies to ``image`` under the ``keypoint_edits`` config section.

    Parameters
    ----------
    image : path
        The input image.
    section : dict
        ``keypoint_edits`` config (``file``, ``auto``).

    Returns
    -------
    Path or None
        ``section["file"]`` when set, else ``<stem>.keypoints.json`` beside the image when ``auto``
        and it exists, else None.
    """
    if section.get("file"):
        return Path(str(section["file"])).expanduser()
    if section.get("auto", True):
        p = edits_path_for(image)
        if p.is_file():
            return p
    return None


def read_edits(path: str | Path) -> dict:
    """Parse and check an edits file.

    Raises
    ------
    EditsError
        One line: the file cannot be read, is not JSON, or is not a valid edits document.
    """
    from stages.errors import InputError
    from stages.keypoint_edits import validate_edits

    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise EditsError(f"keypoint edits {path}: cannot read ({exc.strerror or exc})") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise EditsError(f"keypoint edits {path}: not JSON ({exc.msg} at line {exc.lineno})") from None
    try:
        validate_edits(doc)
    except InputError as exc:
        raise EditsError(f"keypoint edits {path}: {exc}") from None
    return doc


def stage_config(image: str | Path, section: dict) -> dict:
    """The ``keypoint_edits`` task config of one image: the section without ``file``/``auto``, plus
    ``edits`` (the parsed file, or None)."""
    path = find_edits(image, section)
    cfg = {k: v for k, v in section.items() if k not in LOCATOR_KEYS}
    cfg["edits"] = read_edits(path) if path is not None else None
    return cfg
