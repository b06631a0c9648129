"""Upscaled drawings: a drawing enlarged from a low resolution is smoothed at its block period.

A drawing made at a low resolution with thin anti-aliased strokes and then enlarged (nearest or
area-weighted, by an integer or not) is a staircase of blocks: each stroke a chain of dark blocks (its
core) inside grey ones (its anti-aliasing, enlarged into a wide halo), every block a few pixels across.
The field's streamlines follow the staircase and stop at its steps, and the keypoint network puts
endpoints and corners there (the paper's duck, enlarged ≈3.5×: 216 curves, 45 free ends).  Such a
drawing repeats whole rows and columns: the rows inside a block are the same, and they change only at
the block edges, one period apart.  :func:`block_period` finds that period; :func:`deblocked` blurs the
grey by a Gaussian of a share of it, which turns the staircase into the smooth stroke it was drawn as,
at the drawing's own resolution (the stroke is already several pixels wide there: no resampling needed).

Choices made on purpose
-----------------------
* **Found by the lattice of its block edges, on both axes** (not in the references).  Repeated ink
  rows are not enough: the rows between a box's top and bottom sides are all the same too (a
  validation drawing of straight strokes repeats 94 % of its rows), and so are those along a steep
  aliased line (40 % on an aliased validation drawing).  An enlarged drawing's rows change at its
  block edges, one period apart everywhere: the edges keep to a lattice (:func:`edge_lattice`,
  Rayleigh's statistic at least ``min_lattice``) of a period between ``min_period`` and
  ``max_period`` px, the same for the rows and the columns.  On validation drawings enlarged 2.5–4.25×
  the smaller axis's statistic is 24–123, on every drawing of the validation and busy splits at its own
  resolution (and their aliased and 3× larger re-renderings) below 7 (stages/DECISIONS.md).
* **Smoothed in place, not shrunk** to the low resolution and enlarged again: the period is found to a
  hundredth of a pixel, not its phase, and a Gaussian of ``blur`` × the period needs neither.
  ``blur`` 0.5: on the enlarged validation drawings 0.35 left steps (more curves) and 0.7 merged
  neighbouring strokes (lower endpoint F1; stages/DECISIONS.md).  The band is found again on the
  smoothed grey before the stroke width is measured, so the resampling rules see the smooth stroke.
"""

from __future__ import annotations

import numpy as np

from stages.prep import DeblockConfig
from stages.prep.pixels import smoothed

#: Grey levels closer than this are one level (8-bit rounding of an area-weighted enlargement).
SAME_GREY = 0.02
#: The rows' and the columns' periods of one enlargement agree within this ratio.
PERIOD_AGREE = 1.2
#: Block periods tried (px), a hundredth apart: an enlargement by 3.5 has edges 3 and 4 rows apart.
PERIOD_STEP = 0.01
#: Periods whose lattice statistic is within this share of the best are equally good; the longest wins
#: (edges every 4 rows lie on a lattice of 2 too, but not of 8).
PERIOD_TIE = 0.95


def block_edges(grey: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Where the rows of ``grey`` change: the first of each run of neighbouring ink rows that differ.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) contrast-normalised grey, 1 = paper.
    mask : numpy.ndarray
        bool (H, W): its band; a pair of rows counts when either has ink.

    Returns
    -------
    numpy.ndarray
        int64 row indices: one per block edge of an enlarged drawing, however blended (its rows inside a
        block repeat, to :data:`SAME_GREY`).
    """
    change = np.abs(np.diff(np.asarray(grey, np.float32), axis=0)).max(axis=1) >= SAME_GREY
    ink = np.asarray(mask).any(axis=1)
    change &= ink[:-1] | ink[1:]
    return np.flatnonzero(change & ~np.r_[False, change[:-1]])


def edge_lattice(edges: np.ndarray, min_period: float, max_period: float) -> tuple[float, float]:
    """The period of the lattice the block edges keep to, and how closely they keep to it.

    The statistic is Rayleigh's, ``n · R²`` with ``R`` the length of the mean of ``exp(2πi · edge /
    period)`` over the ``n`` edges: about 1 for edges at random rows (below 7 on every validation
    drawing, anti-aliased or aliased), ``n`` for edges exactly one period apart.

    Parameters
    ----------
    edges : numpy.ndarray
        Row indices (:func:`block_edges`).
    min_period, max_period : float
        Periods tried (px).

    Returns
    -------
    period : float
        The longest period within :data:`PERIOD_TIE` of the best statistic.
    statistic : float
        ``n · R²`` at that period; 0 with fewer than 3 edges.
    """
    if len(edges) < 3:
        return 0.0, 0.0
    periods = np.arange(min_period, max_period + PERIOD_STEP / 2, PERIOD_STEP)
    r = np.abs(np.exp(2j * np.pi * edges[None, :] / periods[:, None]).mean(axis=1))
    i = int(np.flatnonzero(r >= PERIOD_TIE * r.max()).max())
    return float(periods[i]), float(len(edges) * r[i] ** 2)


def block_period(grey: np.ndarray, mask: np.ndarray, cfg: DeblockConfig) -> float | None:
    """The block period of an enlarged drawing (px), or None for a drawing at its own resolution.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) contrast-normalised grey, 1 = paper.
    mask : numpy.ndarray
        bool (H, W): its band.
    cfg : DeblockConfig
        The ``prep.deblock`` section (``min_lattice``, ``min_period``, ``max_period``).

    Returns
    -------
    float or None
        The mean of the rows' and the columns' periods when the block edges keep to a lattice on both
        axes (:func:`edge_lattice` at least ``min_lattice``) and the two periods agree (within
        a ratio of :data:`PERIOD_AGREE`).
    """
    grey, mask = np.asarray(grey), np.asarray(mask)
    found = [edge_lattice(block_edges(g, m), cfg.min_period, cfg.max_period)
             for g, m in ((grey, mask), (grey.T, mask.T))]
    (pr, zr), (pc, zc) = found
    if min(zr, zc) < cfg.min_lattice or max(pr, pc) > PERIOD_AGREE * min(pr, pc):
        return None
    return 0.5 * (pr + pc)


def deblocked(grey: np.ndarray, mask: np.ndarray, cfg: DeblockConfig) -> tuple[np.ndarray, float | None, list[str]]:
    """The step as prep runs it: ``grey`` blurred by ``blur`` × its :func:`block_period` when it is an
    enlarged drawing, with the console's line.

    Parameters
    ----------
    grey : numpy.ndarray
        float32 (H, W) contrast-normalised grey, 1 = paper.
    mask : numpy.ndarray
        bool (H, W): its band.
    cfg : DeblockConfig
        The ``prep.deblock`` section.

    Returns
    -------
    grey : numpy.ndarray
        The smoothed grey (float32), or ``grey`` itself.
    period : float or None
        The block period, or None (not enlarged, or ``cfg`` disabled).
    notes : list of str
        What it did.
    """
    if not cfg.enabled or (period := block_period(grey, mask, cfg)) is None:
        return grey, None, []
    out = smoothed(np.asarray(grey, np.float32), cfg.blur * period)
    note = (f"the drawing is enlarged from a lower resolution (blocks of {period:.1f} px): smoothed at that "
            "scale (prep.deblock)")
    return np.clip(out, 0.0, 1.0).astype(np.float32), period, [note]
