"""Public names of a package that its submodules define, imported when first used (PEP 562).

A stage package's ``__init__`` is light: its ``STAGE_VERSION`` and config dataclasses, which every
run needs (the artifact keys, the Hydra schemas of :mod:`pipeline.engine.config`). Its code is in a
submodule (``stages/<stage>/stage.py``) that imports numba, scipy, scikit-image, PuLP or torch, which
a run whose artifacts are all stored never needs (issue 14: a fully cached run in under a second).
:func:`lazy_names` gives the package a module ``__getattr__`` and ``__dir__`` so that
``from stages.flow import run`` and ``stages.flow.run`` still work: the submodule is imported at the
first use of one of its names.
"""

from __future__ import annotations

import importlib
import sys
from typing import Any, Callable


def lazy_names(package: str, exports: dict[str, tuple[str, ...]]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module ``__getattr__`` and ``__dir__`` of a package whose public names live in submodules.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    exports : dict of str to tuple of str
        Submodule (full import path) → the names it gives the package.

    Returns
    -------
    __getattr__, __dir__ : callable
        To assign in the package: ``__getattr__, __dir__ = lazy_names(__name__, {...})``.
    """
    where = {name: module for module, names in exports.items() for name in names}

    def __getattr__(name: str) -> Any:
        if name in where:
            return getattr(importlib.import_module(where[name]), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(where))

    return __getattr__, __dir__
