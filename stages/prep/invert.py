"""Inversion: light strokes on dark paper (chalk on a blackboard, a negative scan) become ink on paper.

Every later step takes dark for ink and light for paper; this one turns a page whose paper is darker
than mid-grey over (``prep.invert``: ``auto``, ``always`` or ``never``).  A transparent page whose
strokes are lighter than mid-grey is read over black when decoded
(:func:`~stages.prep.decode.decode_image`), so that it comes here as light on dark.

Choices made on purpose
-----------------------
* **Light strokes on dark paper are inverted** (``invert: auto``; not in the references): the paper
  level (the median grey, as for the paper grain: :mod:`~stages.prep.band`) darker than mid-grey means
  chalk on a blackboard or a negative scan, which the threshold would otherwise read as a page of ink
  ("no ink stands out of the paper grain"); the grey is turned into ``1 − grey`` and a note says so. Why mid-grey: the paper
  of every validation, realvec_dev and bundled drawing is at 0.82 or lighter, and a page darker than
  mid-grey has more ink than paper, which is no line drawing either way.  A photographed sheet is cut
  out of its desk first (:mod:`~stages.prep.sheet`), and the level is its paper's.
"""

from __future__ import annotations

import numpy as np

from stages.prep.band import paper_statistics

#: Mid-grey: ``invert: auto`` turns the grey over when the paper level (the median grey) is darker,
#: and a transparent page whose strokes are lighter is read over black
#: (:func:`~stages.prep.decode._backdrop`).
MID_GREY = 0.5


def invert(grey: np.ndarray, how: str) -> tuple[np.ndarray, list[str]]:
    """The grey turned over (``1 − grey``) when its paper is darker than :data:`MID_GREY`, with a note.

    Parameters
    ----------
    grey : numpy.ndarray
        float (H, W) in [0, 1], 1 = white (a photographed sheet already cut out of its desk).
    how : str
        ``prep.invert``: ``"auto"`` (when the paper level, the median grey of
        :func:`~stages.prep.band.paper_statistics`, is darker than mid-grey), ``"always"`` or ``"never"``.

    Returns
    -------
    grey : numpy.ndarray
        ``1 − grey``, or ``grey`` itself.
    notes : list of str
        The console's line when it was inverted, else empty.
    """
    if how != "never":
        level = paper_statistics(grey)[0]
        if how == "always" or level < MID_GREY:
            return 1.0 - grey, [f"light strokes on dark paper (paper level {level:.2f}): inverted (prep.invert)"
                                if how == "auto" else "inverted (prep.invert=always)"]
    return grey, []
