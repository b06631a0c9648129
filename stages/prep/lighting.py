"""Uneven lighting: the paper's brightness (a photographed drawing, a shadow on a scan) divided out.

With paper from white to mid-grey, no one threshold tells ink from paper; dividing the grey by the
paper's brightness, estimated where strokes vanish (a grey closing wider than them), makes the paper
white again.  Evenly lit drawings are left exactly as they are.

Choices made on purpose
-----------------------
* **Uneven lighting is divided out** (``lighting``; not in the references): a photographed drawing
  or a scan with a shadow has paper from white to mid-grey, and one threshold then took the shadow
  for ink or the faint strokes for paper (a rough pencil bird under a 33 % shadow: "no ink stands
  out of the paper grain"). The paper's brightness (a grey closing over ``window_px``, wider than
  strokes) divides the grey where it varies by at least ``min_range`` (12 %) across the page; evenly
  lit drawings (every validation, realvec_dev and bundled drawing: at most 8.6 %) are left exactly as
  they were. Measured on shadowed copies of the validation split (stages/DECISIONS.md, prep).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from stages.prep import LightingConfig
from stages.prep.pixels import blocks

#: The darkest shade of the paper :func:`flatten_lighting` divides out, relative to the brightest paper;
#: darker areas wider than its window are ink (fills), not shadow.
SHADE_FLOOR = 0.4
#: Fewer blocks than this across the shrunk copy (a strip) and the lighting is left alone.
MIN_LIGHTING_BLOCKS = 8


def even_lighting(grey: np.ndarray, cfg: LightingConfig) -> tuple[np.ndarray, list[str]]:
    """The step as prep runs it: :func:`flatten_lighting` when ``prep.lighting`` is enabled, with a note
    when it divided something out.

    Parameters
    ----------
    grey : numpy.ndarray
        float (H, W) in [0, 1], 1 = white (inverted if it was light on dark).
    cfg : LightingConfig
        The ``prep.lighting`` section.

    Returns
    -------
    grey : numpy.ndarray
        The lighting-flattened grey, or ``grey`` itself.
    notes : list of str
        The console's line when the lighting was divided out, else empty.
    """
    if not cfg.enabled:
        return grey, []
    lit, variation = flatten_lighting(grey, cfg.window_px, cfg.min_range)
    if lit is grey:
        return grey, []
    return lit, [f"uneven lighting (the paper's brightness varies by {variation:.0%}): divided out (prep.lighting)"]


def flatten_lighting(grey: np.ndarray, window_px: float, min_range: float) -> tuple[np.ndarray, float]:
    """Divide the paper's uneven brightness out of a grey image (a photographed drawing, a shadow).

    The paper's brightness is estimated as a grey closing (the brightest grey within ``window_px``,
    then the darkest of those, which restores a shadow's edge) smoothed over the same window, on a
    copy shrunk to at most 256 px (lighting varies slowly); strokes narrower than the window vanish
    from it. Within half a window of the image's edge the closing sees light only from inside, so
    where the light falls off towards an edge it overestimated the paper there (6 % on a shadowed
    validation drawing: grain specks along the edge); there it fades into a cubic surface fitted to
    the inner closing. Where that brightness varies across the page by less than ``min_range`` of its
    brightest (5th–95th percentile) the image is returned as it is.

    Parameters
    ----------
    grey : numpy.ndarray
        float (H, W) in [0, 1], 1 = white.
    window_px : float
        Window of the closing in pixels: wider than any stroke, narrower than the lighting's changes.
    min_range : float
        Smallest relative variation of the paper's brightness that is divided out.

    Returns
    -------
    grey : numpy.ndarray
        ``grey`` divided by the paper's brightness (clipped to [0, 1]), or ``grey`` itself.
    range : float
        The paper's relative variation that was measured.
    """
    h, w = grey.shape
    f = max(1, -(-max(h, w) // 256))
    fy, fx = min(f, h), min(f, w)
    hs, ws = h // fy, w // fx
    if min(hs, ws) < MIN_LIGHTING_BLOCKS:
        # a strip a few blocks across (a 10000×20 scan of one line): every block holds ink, none
        # tells the paper's light
        return grey, 0.0
    small = grey[:hs * fy, :ws * fx].reshape(hs, fy, ws, fx).mean(axis=(1, 3)) if f > 1 else grey
    k = tuple(max(3, int(round(window_px / b)) | 1) for b in (fy, fx))
    paper = ndimage.minimum_filter(ndimage.maximum_filter(small, k), k)
    # Ink filled over more than the window (a black eye, a silhouette) survives the closing: where it
    # is darker than any shade the paper takes (below SHADE_FLOOR of the brightest), it is ink, and
    # the paper there is taken as bright as the page's, so that the fill is neither lightened nor
    # counted as uneven light.
    brightest = float(np.percentile(paper, 95))
    paper = np.where(paper < SHADE_FLOOR * brightest, brightest, paper)
    paper = _paper_border_fitted(ndimage.uniform_filter(paper, k), (k[0] // 2, k[1] // 2))
    low, high = np.percentile(paper, [5, 95])
    variation = float((high - low) / max(high, 1e-6))
    if variation < min_range:
        return grey, variation
    if f > 1:
        # back to full size: each block's value, smoothed over a block, the edge rows repeated
        full = blocks(paper, fy, fx)
        full = np.pad(full, ((0, h - full.shape[0]), (0, w - full.shape[1])), mode="edge")
        paper = ndimage.uniform_filter(full, (fy, fx))
    return np.clip(grey / np.maximum(paper, 1e-3), 0.0, 1.0), variation


def _paper_border_fitted(paper: np.ndarray, margin: tuple[int, int]) -> np.ndarray:
    """``paper`` with its edge band (``margin`` rows, columns) faded (linearly, to the edge) into a cubic
    surface fitted by least squares to the inside; unchanged when the inside is too small to fit."""
    h, w = paper.shape
    my, mx = margin
    if min(my, mx) < 1 or h <= 2 * my + 4 or w <= 2 * mx + 4:
        return paper
    yy, xx = np.mgrid[0:h, 0:w]
    y, x = (2.0 * yy / h - 1.0).ravel(), (2.0 * xx / w - 1.0).ravel()
    basis = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y, x ** 3, x * x * y, x * y * y, y ** 3], axis=1)
    inner = np.zeros((h, w), bool)
    inner[my:h - my, mx:w - mx] = True
    coef, *_ = np.linalg.lstsq(basis[inner.ravel()], paper[inner], rcond=None)
    fitted = (basis @ coef).reshape(h, w)
    keep = np.clip(np.minimum(np.minimum(yy, h - 1 - yy) / my, np.minimum(xx, w - 1 - xx) / mx), 0.0, 1.0)
    return keep * paper + (1.0 - keep) * fitted
