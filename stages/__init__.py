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

#: The x86-64 micro-architecture level numba compiles the kernels for, where the CPU has it: AVX2, FMA,
#: BMI1/2, F16C, LZCNT and MOVBE (v3) over SSE3/SSSE3/SSE4.1/4.2, POPCNT, CX16, LAHF (v2), as Linux's
#: ``/proc/cpuinfo`` names them (``pni`` is SSE3, ``abm`` LZCNT).
PORTABLE_CPU = "x86-64-v3"
_PORTABLE_CPU_FLAGS = frozenset("avx avx2 bmi1 bmi2 f16c fma abm movbe xsave cx16 lahf_lm popcnt pni sse4_1 sse4_2 "
                                "ssse3".split())


def _cpu_flags() -> frozenset:
    """This CPU's feature flags from Linux's ``/proc/cpuinfo`` (empty elsewhere or when it cannot be read)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as info:
            for line in info:
                if line.startswith("flags"):
                    return frozenset(line.partition(":")[2].split())
    except OSError:
        pass
    return frozenset()


def portable_cpu_target(environ=os.environ) -> bool:
    """Make numba compile for :data:`PORTABLE_CPU`, not for this exact CPU, when the CPU has that level.

    numba loads a cached kernel only for the CPU name and features it was compiled for; the package ships
    its kernels compiled for this level (:mod:`pipeline.engine.kernels.shipped`), so they load on every x86-64 CPU that
    has it (most since 2015) instead of being compiled on a user's first drawing. A user's own
    ``NUMBA_CPU_NAME`` / ``NUMBA_CPU_FEATURES`` are kept. Same speed and byte-identical outputs as this
    machine's own target (stages/DECISIONS.md). Must run before numba is imported (it reads them once);
    being environment variables, they hold for the whole process and its children, so other numba code
    run beside polyvec's compiles for that level too (a CPU with AVX-512 does not use it there).

    Returns
    -------
    bool
        Whether the level is (now) the target.
    """
    import sys

    if "NUMBA_CPU_NAME" in environ or "NUMBA_CPU_FEATURES" in environ:
        return environ.get("NUMBA_CPU_NAME") == PORTABLE_CPU and environ.get("NUMBA_CPU_FEATURES") == ""
    if not (sys.platform.startswith("linux") and os.uname().machine == "x86_64"
            and _PORTABLE_CPU_FLAGS <= _cpu_flags()):
        return False
    environ["NUMBA_CPU_NAME"], environ["NUMBA_CPU_FEATURES"] = PORTABLE_CPU, ""
    return True


portable_cpu_target()
