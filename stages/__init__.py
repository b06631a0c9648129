"""The algorithms of polyvec, one package per stage.

Stages are functions of arrays: they never read configs or the artifact store, and the engine hands
them their inputs. The files they read are their own shipped data (the keypoint weights and type
classifier in ``stages/keypoints/weights/``, or a checkpoint named by ``keypoints.weights``). Each stage package
exposes ``STAGE_VERSION`` (bump when results change) and ``run(cfg, **inputs) -> Artifact`` where
``cfg`` is a plain ``dict`` (the stage's own Hydra config section, whose keys and types are one
dataclass of the stage, built by :func:`stages.config.from_section`) and every input is the
:class:`~stages.artifact.Artifact` of an upstream stage, passed by that stage's name. A package's
``__init__`` holds its ``STAGE_VERSION`` and config dataclasses and nothing heavy; ``run`` comes from
its code (``stage.py``), imported when first used (:mod:`stages.lazy`).
See ``stages/INTERFACES.md`` for what every artifact holds and ``stages/DECISIONS.md`` for the
measurements behind the stages' choices. Shared plane geometry is in :mod:`stages.geometry`; the
training of the keypoint network is apart, in :mod:`stages.keypoints.training`.
"""

import os

# numba formats an error message, in colour through colorama, for every overload it tries and rejects
# while typing a kernel; without the colour a first run's compiles take ~8 % less (stages/DECISIONS.md).
# Set before any stage imports numba, which reads it once.
os.environ.setdefault("NUMBA_DISABLE_ERROR_MESSAGE_HIGHLIGHTING", "1")
