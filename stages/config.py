"""Stage parameters as dataclasses: one dataclass per config section, one field per key.

Each stage declares its section of ``conf/<stage>/default.yaml`` as a (nested) frozen dataclass with no
defaults: the YAML holds every value, the dataclass every key and its type. The engine registers the
same dataclasses as Hydra structured configs (:mod:`pipeline.engine.config`), so a key the dataclass lacks is
an error when the config is composed; :func:`from_section` applies the same rule to the plain dict a
stage's ``run`` receives (tests and scripts call stages without Hydra).
"""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any, TypeVar

from stages.errors import InputError

T = TypeVar("T")

_SCALARS = {float: float, int: int, bool: bool, str: str}


def _convert(tp: Any, value: Any, where: str) -> Any:
    """``value`` as the annotated type ``tp`` (scalars cast as the stages always did: int → float)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _convert(args[0], value, where)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise InputError(f"{where}: expected a section (mapping), got {value!r}")
        return from_section(tp, value, where)
    if origin in (list, tuple):
        (item,) = typing.get_args(tp)[:1] or (Any,)
        seq = [_convert(item, v, where) for v in (value or [])]
        return tuple(seq) if origin is tuple else seq
    if tp in _SCALARS:
        if value is None:
            raise InputError(f"{where}: a value is required")
        if tp is bool and not isinstance(value, bool):
            raise InputError(f"{where} must be true or false (got {value!r}; write {where}=true)")
        try:
            return _SCALARS[tp](value)
        except (TypeError, ValueError):
            raise InputError(f"{where}: expected {tp.__name__}, got {value!r}") from None
    return value


def from_section(cls: type[T], section: dict, name: str) -> T:
    """Build the dataclass ``cls`` from a config section; every key is required, unknown keys are errors.

    Parameters
    ----------
    cls : type
        A dataclass whose fields mirror the section (nested dataclasses for nested sections).
    section : dict
        The plain-dict config section.
    name : str
        Its dotted name, for messages (``"flow"``, ``"flow.barrier"``).

    Returns
    -------
    cls
        The instance (its ``__post_init__`` checks the values' ranges, where it has one).

    Raises
    ------
    InputError
        On missing or unknown keys, or values of the wrong type.
    """
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    missing = sorted(set(names) - set(section))
    unknown = sorted(set(section) - set(names))
    if missing or unknown:
        raise InputError(f"{name} config: missing keys {missing}, unknown keys {unknown}")
    return cls(**{k: _convert(hints[k], section[k], f"{name}.{k}") for k in names})
