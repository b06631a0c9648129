"""polyvec's front ends (``polyvec``, ``polyvec-inspect`` …) on top of the engine, ``pipeline.engine``.

``from pipeline import vectorize`` is the Python API (:mod:`pipeline.api`). It is imported only when
asked for (PEP 562's module ``__getattr__``): this file must import nothing at module level, because
``polyvec``'s launcher imports this package before it forks its keypoints child, and that fork must
happen while the process has imported the standard library alone (no threads yet).
"""

#: Names this package hands out from :mod:`pipeline.api`, which is imported on first use.
_API = ("vectorize", "Vectorization", "VectorizationError")


def __getattr__(name: str):
    if name in _API:
        from pipeline import api

        return getattr(api, name)
    # Not ours: ``from pipeline import cli`` then imports the sub-module, as without this function.
    raise AttributeError(f"module 'pipeline' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_API])
