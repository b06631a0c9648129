"""The unit of exchange between stages and the engine."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Artifact:
    """Output of one stage for one image.

    Parameters
    ----------
    arrays : dict of str to numpy.ndarray
        Dense numeric data; the engine persists each entry as one zarr array.
    data : dict
        Small structured, JSON-serialisable data (lists, numbers, strings, nested dicts).
    notes : list of str
        One line per guard that bound while computing it (a cap on a count, an iteration or a size
        that made the stage do less rather than blow up): the engine records them in the manifest
        (``warnings``) and the CLI says each once.
    """

    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    data: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def __getitem__(self, name: str) -> np.ndarray:
        return self.arrays[name]

    def nbytes(self) -> int:
        """Total size of the arrays in bytes."""
        return int(sum(a.nbytes for a in self.arrays.values()))


def pack_ragged(parts: list[np.ndarray], dtype=None) -> tuple[np.ndarray, np.ndarray]:
    """Concatenate variable-length arrays into ``(flat, offsets)``.

    ``parts[k] == flat[offsets[k]:offsets[k + 1]]``; ``offsets`` has ``len(parts) + 1`` entries.
    """
    lengths = np.array([len(p) for p in parts], dtype=np.int64)
    offsets = np.zeros(len(parts) + 1, dtype=np.int64)
    np.cumsum(lengths, out=offsets[1:])
    if parts:
        flat = np.concatenate([np.asarray(p) for p in parts])
    else:
        flat = np.zeros((0,), dtype=dtype or np.float64)
    if dtype is not None:
        flat = flat.astype(dtype, copy=False)
    return flat, offsets


def unpack_ragged(flat: np.ndarray, offsets: np.ndarray) -> list[np.ndarray]:
    """Inverse of :func:`pack_ragged`."""
    return [flat[offsets[k]:offsets[k + 1]] for k in range(len(offsets) - 1)]


@dataclass
class ItemPlan:
    """A stage's work as independent items, for a stage whose engine may reuse per-item results.

    A per-item stage exposes, beside ``run``: ``ITEM_INPUTS`` (the input stages every item's
    result depends on, besides the item's own content), ``plan_items(cfg, **inputs) -> ItemPlan``,
    ``run_items(plan, which) -> list[dict]`` (results of the items ``which``: dicts of numpy arrays,
    each a function of that item, ``context`` and the ``ITEM_INPUTS`` artifacts only) and
    ``assemble(plan, results) -> Artifact``; ``run`` must equal assemble of run_items of every item.

    Parameters
    ----------
    items : list of tuple of numpy.ndarray
        Each item's content: the arrays whose bytes identify it.
    context : dict
        JSON-serialisable; what every item's result depends on besides its content and the
        ``ITEM_INPUTS`` artifacts (e.g. the effective config).
    work : Any
        Stage-private state handed back to ``run_items`` and ``assemble``.
    notes : list of str
        The guard notes of the whole artifact (see :class:`Artifact`).
    """

    items: list[tuple[np.ndarray, ...]]
    context: dict[str, Any]
    work: Any = None
    notes: list[str] = field(default_factory=list)
