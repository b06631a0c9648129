"""Stage ``keypoint_edits``: a user's keypoint corrections applied to the detector's keypoints.

``STAGE_VERSION`` and the config dataclass. Its code, and the docstring that describes it and the
edits file's format, are in :mod:`stages.keypoint_edits.stage`; ``run`` and its other public names
load from there when first used (:mod:`stages.lazy`).
"""

from __future__ import annotations

from dataclasses import dataclass

from stages.lazy import lazy_names

STAGE_VERSION = "2"  # 2: edits scaled onto a supersampled prep's keypoints


@dataclass
class KeypointEditsConfig:
    """The ``keypoint_edits`` config section (``conf/keypoint_edits/default.yaml``), one field per key.

    ``file`` and ``auto`` locate the edits file; the engine reads them (:mod:`pipeline.engine.edits`) and
    hands :func:`run` ``match_radius`` and the parsed file as ``edits`` instead, so that the key hashes
    the file's content, not its path.
    """

    file: str | None
    auto: bool
    match_radius: float


__getattr__, __dir__ = lazy_names(__name__, {
    "stages.keypoint_edits.stage": ("run", "validate_edits", "apply_edits", "FORMAT", "TYPE_NAMES", "TYPE_CODES"),
})
