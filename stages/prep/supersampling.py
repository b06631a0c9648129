"""Supersampling: thin aliased strokes are worked on at an integer multiple of the resolution.

A 1-px aliased line is a chain of diagonal pixel steps that the field cannot resolve; zoomed (bilinear,
pixel-aligned) and blurred a little, it becomes a smooth stroke a few pixels wide.  Every later stage
works at that resolution, and the export maps the curves back (``scale`` in the data).

Choices made on purpose
-----------------------
* **Thin aliased strokes are supersampled** (``supersample``; issue #17 item 5, not in the
  references).  When the strokes' mean width (ink area / skeleton length of the band) is below
  ``below_width`` px and their edges are hard (at most ``max_soft_edges`` of the pixels bordering the
  band are grey: aliased ink), the field cannot resolve them (a 1-px aliased line is a chain of
  diagonal pixel steps, whose streamlines stop at every step: a drawn ellipse came out as 9 curves).
  Why only aliased ink: on the validation split's thinnest drawings (anti-aliased and pencil, 1.8–2.7
  px) supersampling lowered the junction F1 (stages/DECISIONS.md), and none of them has hard edges.
  The contrast-normalised grey is zoomed by the integer ``s = min(max_factor, ceil(target_width /
  width))`` (bilinear, pixel-aligned: internal ``x = s · x_source``), blurred by ``blur`` source px to
  smooth the staircase, and banded again; every later stage works at that resolution and the export
  maps the curves back (``scale`` in the data; ``height``/``width`` stay the source's).  Capped by
  ``max_pixels`` (the factor drops, with a note).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from stages.prep import SupersampleConfig
from stages.prep.width import soft_edges, width_words


def supersampled(grey: np.ndarray, mask: np.ndarray, width: float | None, cfg: SupersampleConfig
                 ) -> tuple[np.ndarray, int, list[str]]:
    """The step as prep runs it: ``grey`` at :func:`supersample_factor` × the resolution when its strokes
    are thin and aliased, with the console's lines.

    Parameters
    ----------
    grey : numpy.ndarray
        float32 (H, W) contrast-normalised grey, 1 = paper.
    mask : numpy.ndarray
        bool (H, W): its band.
    width : float or None
        The band's :func:`~stages.prep.width.stroke_width` (None when ``cfg`` is disabled).
    cfg : SupersampleConfig
        The ``prep.supersample`` section.

    Returns
    -------
    grey : numpy.ndarray
        The supersampled grey, or ``grey`` itself.
    factor : int
        Internal pixels per source pixel (1 = none).
    notes : list of str
        Why the factor was capped (``max_pixels``), and what it did.
    """
    if not cfg.enabled:
        return grey, 1, []
    soft = soft_edges(grey, mask)
    factor, note = supersample_factor(width, soft, grey.shape, cfg)
    notes = [note] if note else []
    if factor > 1:
        grey = supersample(grey, factor, cfg.blur)
        notes.append(f"{width_words(width, mask)}: working at {factor}x resolution "
                     "(prep.supersample; the curves are mapped back)")
    return grey, factor, notes


def supersample_factor(width: float, soft: float, shape: tuple[int, int], cfg) -> tuple[int, str | None]:
    """The internal resolution factor for strokes ``width`` px wide (1 = none) and a note when capped.

    Parameters
    ----------
    width : float
        Mean stroke width (:func:`~stages.prep.width.stroke_width`).
    soft : float
        :func:`~stages.prep.width.soft_edges` of the band: only aliased ink (at most ``max_soft_edges``) is
        supersampled.
    shape : tuple of int
        Source image (H, W).
    cfg : SupersampleConfig

    Returns
    -------
    factor : int
    note : str or None
        Says why the factor is lower than the strokes ask for (``max_pixels``).
    """
    if not cfg.enabled or width <= 0 or width >= cfg.below_width or soft > cfg.max_soft_edges:
        return 1, None
    want = min(cfg.max_factor, int(np.ceil(cfg.target_width / width - 1e-9)))
    factor = want
    while factor > 1 and shape[0] * shape[1] * factor * factor > cfg.max_pixels:
        factor -= 1
    note = None
    if factor < want:
        note = (f"strokes about {width:.1f} px wide would need {want}x resolution; prep.supersample.max_pixels "
                f"({cfg.max_pixels}) allows {factor}x")
    return max(1, factor), note


def supersample(grey: np.ndarray, factor: int, blur: float) -> np.ndarray:
    """Grey image at ``factor`` × the resolution: pixel-aligned bilinear zoom, then a Gaussian blur.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) in [0, 1].
    factor : int
        Integer zoom; internal pixel ``[i, j]`` covers source ``[i / factor, (i + 1) / factor)``.
    blur : float
        Gaussian σ in *source* pixels (0 = none).

    Returns
    -------
    numpy.ndarray
        float32 (factor·H, factor·W).
    """
    z = ndimage.zoom(np.asarray(grey, np.float32), factor, order=1, grid_mode=True, mode="nearest")
    if blur > 0:
        z = ndimage.gaussian_filter(z, blur * factor, mode="nearest")
    return np.clip(z, 0.0, 1.0).astype(np.float32)
