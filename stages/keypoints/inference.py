"""Running the keypoint network on a drawing: normalisation, padding, tiles, peaks.

Choices made on purpose
-----------------------
* **Contrast normalisation** follows the authors (``png_to_numpy(normalize=True)``): ink = 1 − grey,
  divided by max(max, 0.2), then stretched so the 2nd–98th percentiles span [0, 1]. On sparse clean
  drawings both percentiles are paper (the authors' code then divides by zero); we keep the stretch
  range at least ``contrast_floor`` wide, which leaves such drawings nearly as they are. Training
  applies the very same function (stages/keypoints/training/), so the network sees what it was trained on.
* **Padding** as the authors: zeros (paper) at the bottom and right up to a multiple of the network's
  stride, always 1..stride pixels (their ``8 - dim % 8``).
* **Tiles**: drawings larger than ``single_pass_max`` run in overlapping ``tile_size`` tiles whose
  outputs are blended with weights that ramp linearly over the overlap (no seams); the authors cut
  non-overlapping 720-px tiles, which leaves seams and loses keypoints on tile borders.  Tiles with
  no pixel of the dilated band are skipped (their output is zeroed anyway), so 512-px tiles pay on
  a large sparse scan what 1024-px ones would not skip (4× elephant, 2000×3012: 40 → 22 s, the same
  keypoints to 0.05 px).
* **Peaks**: the peaks of ``skimage.feature.peak_local_max`` (the authors' NMS; :func:`local_peaks`,
  the same points found without importing skimage and scipy.spatial in the keypoints process) on H1
  with ``threshold`` (authors 0.5) and
  ``min_distance`` (authors 1, which lets duplicate peaks 2 px apart through; 3 by default), only
  within ``band_dilation`` px of the narrow band: the loss only ever saw the band, so the heatmaps
  are meaningless off it — they are zeroed there before NMS (and in the artifact). Positions are refined to sub-pixel by a parabola through the 3×3 neighbourhood
  and reported at pixel centres, (j + 0.5, i + 0.5) + offset.
* **Type** = argmax of H2..H4 at the peak pixel (endpoint 1, junction 3, corner 5).
* **Test-time views** (``test_time_views``, not in the paper or the authors' code): the heatmaps may
  be averaged over the drawing and some of its mirror images (each run through the network and
  mapped back); the network is not exactly equivariant to them, so the mean is a cheap ensemble.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage

from stages.keypoints import VIEWS
from stages.keypoints.codes import TYPE_CODES


def network_input(grey: np.ndarray, contrast_floor: float) -> np.ndarray:
    """The authors' contrast normalisation, from grey (1 = white) to ink (1 = ink).

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) in [0, 1], 1 = paper white.
    contrast_floor : float
        Smallest width of the percentile stretch range.

    Returns
    -------
    numpy.ndarray
        float32 (H, W) in [0, 1], 1 = ink.
    """
    ink = 1.0 - np.asarray(grey, np.float32)
    ink = ink / max(float(ink.max()), 0.2)
    lo, hi = np.percentile(ink, (2, 98))
    hi = max(float(hi), float(lo) + contrast_floor)
    return np.clip((ink - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)


def pad_to_multiple(x: np.ndarray, multiple: int) -> np.ndarray:
    """Zero-pad bottom and right by ``multiple - dim % multiple`` (1..multiple) pixels, as the authors."""
    h, w = x.shape
    return np.pad(x, ((0, multiple - h % multiple), (0, multiple - w % multiple)))


def _tile_starts(n: int, tile: int, step: int) -> list[int]:
    if n <= tile:
        return [0]
    starts = list(range(0, n - tile, step))
    starts.append(n - tile)
    return starts


def predict_views(model: torch.nn.Module, x: np.ndarray, views: list[str], tile_size: int, tile_overlap: int,
                  needed: np.ndarray | None = None, single_pass_max: int | None = None,
                  bf16: bool = False) -> np.ndarray:
    """Heatmaps H1..H4 averaged over the drawing and its ``views`` (test-time augmentation).

    Parameters
    ----------
    model, x, tile_size, tile_overlap, needed, single_pass_max, bf16
        As :func:`predict_heatmaps`.
    views : list of str
        Names in :data:`stages.keypoints.VIEWS`; each costs one more pass of the network. [] = the drawing alone.

    Returns
    -------
    numpy.ndarray
        float32 (4, H, W): the mean of every view's heatmaps, each mapped back onto the drawing.
    """
    out = predict_heatmaps(model, x, tile_size, tile_overlap, needed=needed, single_pass_max=single_pass_max,
                           bf16=bf16)
    if not views:
        return out                  # the default: no copy of the (4, H, W) maps
    for v in views:
        view = VIEWS[v]
        out += view(predict_heatmaps(model, np.ascontiguousarray(view(x)), tile_size, tile_overlap,
                                     needed=None if needed is None else np.ascontiguousarray(view(needed)),
                                     single_pass_max=single_pass_max, bf16=bf16))
    return np.ascontiguousarray(out / (1 + len(views)), dtype=np.float32)


def predict_heatmaps(model: torch.nn.Module, x: np.ndarray, tile_size: int, tile_overlap: int,
                     detection_only: bool = False, needed: np.ndarray | None = None,
                     single_pass_max: int | None = None, bf16: bool = False) -> np.ndarray:
    """Heatmaps H1..H4 of a normalised drawing, tiled with blended overlaps when large.

    Parameters
    ----------
    model : torch.nn.Module
        A :class:`~stages.keypoints.network.KeypointNet` in eval mode.
    x : numpy.ndarray
        (H, W) network input (1 = ink); padded here to the network's multiple.
    tile_size, tile_overlap : int
        Tile side and overlap in pixels (rounded down to the network's multiple).
    detection_only : bool
        Compute H1 alone (``model.detect``), skipping the class branch.
    single_pass_max : int, optional
        A drawing whose padded sides are both at most this (and at least ``tile_size``) runs in one
        pass; default ``tile_size``.
    needed : numpy.ndarray, optional
        bool (H, W): the pixels whose values the caller keeps (the stage zeroes the rest: the dilated
        band).  A tile holding none of them is not run and its pixels come out 0; every pixel the
        caller keeps has the same value as without skipping (a pixel of a skipped tile is not
        needed, so only unneeded pixels lose a tile's share of the blend).  Line drawings are
        sparse: most tiles of a large scan hold no stroke.
    bf16 : bool
        Run the network under bfloat16 autocast (the outputs come back as float32).

    Returns
    -------
    numpy.ndarray
        float32 (4, H, W), or (1, H, W) with ``detection_only`` (cropped back to the input size).
    """
    m = model.multiple
    h, w = x.shape
    xp = pad_to_multiple(x, m)
    hp, wp = xp.shape
    tile = max(m, tile_size // m * m)
    overlap = min(tile_overlap // m * m, tile - m)
    t = torch.from_numpy(xp)[None, None]
    net = model.detect if detection_only else (lambda a: model(a)[0])
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        whole = max(tile, single_pass_max or 0)
        if hp <= whole and wp <= whole:
            out = net(t)[0].float().numpy()
            return np.ascontiguousarray(out[:, :h, :w])
        acc = np.zeros((1 if detection_only else 4, hp, wp), np.float32)
        wsum = np.zeros((hp, wp), np.float32)
        ramp = np.minimum(np.arange(tile) + 0.5, np.arange(tile)[::-1] + 0.5) / max(overlap, 1)
        ramp = np.clip(ramp, 1e-3, 1.0).astype(np.float32)
        for i0 in _tile_starts(hp, tile, tile - overlap):
            for j0 in _tile_starts(wp, tile, tile - overlap):
                th, tw = min(tile, hp), min(tile, wp)
                if needed is not None and not needed[i0:i0 + th, j0:j0 + tw].any():
                    continue
                y = net(t[..., i0:i0 + th, j0:j0 + tw])[0].float().numpy()
                wt = ramp[:th, None] * ramp[None, :tw] if (th == tile and tw == tile) else \
                    np.outer(ramp[:th] if th == tile else np.ones(th), ramp[:tw] if tw == tile else np.ones(tw))
                acc[:, i0:i0 + th, j0:j0 + tw] += y * wt
                wsum[i0:i0 + th, j0:j0 + tw] += wt
        # Pixels of skipped tiles only: weight 0, value 0.
        return np.ascontiguousarray((acc / np.where(wsum > 0, wsum, 1.0))[:, :h, :w])


def find_keypoints(heatmaps: np.ndarray, threshold: float, min_distance: int,
                   band: np.ndarray | None = None, subpixel: bool = True
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Non-maximum suppression on H1 and typing by the class maps.

    Parameters
    ----------
    heatmaps : numpy.ndarray
        (4, H, W): H1 detection, H2 endpoint, H3 junction, H4 corner.
    threshold : float
        Minimum H1 value of a peak.
    min_distance : int
        Peaks are separated by at least this many pixels (Chebyshev; :func:`local_peaks`).
    band : numpy.ndarray, optional
        bool (H, W): peaks outside it are discarded.
    subpixel : bool
        Refine peak positions by a parabola fit per axis.

    Returns
    -------
    points : numpy.ndarray
        float32 (N, 2) in (x, y), pixel centres at +0.5.
    types : numpy.ndarray
        int8 (N,) in {1, 3, 5}.
    scores : numpy.ndarray
        float32 (N,) H1 at the peaks.
    """
    h1 = heatmaps[0]
    if band is not None:
        # Mask before NMS: H1 is untrained off the band, and a high value there would suppress
        # the real peaks within min_distance.
        h1 = np.where(band, h1, 0.0)
    coords = local_peaks(h1, max(int(min_distance), 1), threshold)
    if len(coords) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, np.int8), np.zeros(0, np.float32)
    i, j = coords[:, 0], coords[:, 1]
    yx = coords.astype(np.float64) + 0.5
    if subpixel:
        hh, ww = h1.shape
        for axis, (lo_idx, hi_idx) in enumerate([((np.maximum(i - 1, 0), j), (np.minimum(i + 1, hh - 1), j)),
                                                 ((i, np.maximum(j - 1, 0)), (i, np.minimum(j + 1, ww - 1)))]):
            a, b, c = h1[lo_idx], h1[i, j], h1[hi_idx]
            den = a - 2 * b + c
            off = np.where(den < -1e-6, 0.5 * (a - c) / np.where(den < -1e-6, den, -1.0), 0.0)
            yx[:, axis] += np.clip(off, -0.5, 0.5)
    cls = np.argmax(heatmaps[1:4, i, j], axis=0)
    types = np.asarray(TYPE_CODES, np.int8)[cls]
    order = np.argsort(-h1[i, j], kind="stable")
    return (yx[order][:, ::-1].astype(np.float32), types[order], h1[i, j][order].astype(np.float32))


#: :func:`local_peaks` looks the neighbours of each candidate up offset by offset for windows up to
#: this half-width (13² offsets), beyond it by a KD-tree (an NMS distance a user set wide).
MAX_WINDOW_LOOKUP = 6


def local_peaks(image: np.ndarray, min_distance: int, threshold: float) -> np.ndarray:
    """The local maxima of ``image`` above ``threshold``, at least ``min_distance`` apart: the points
    ``skimage.feature.peak_local_max(image, min_distance, threshold_abs=threshold, exclude_border=False)``
    returns, in its order (highest first, ties in row-major order).

    A pixel is a candidate where it equals the maximum of its (2·``min_distance`` + 1)² window (the
    image's edge repeated) and exceeds ``threshold``; none where every pixel is (a constant image).
    Candidates are taken highest first and each one accepted removes the later ones closer than
    ``min_distance`` (Chebyshev), found offset by offset in an image of candidate ranks (by a
    KD-tree above :data:`MAX_WINDOW_LOOKUP`). Written here rather than imported: ``skimage.feature`` pulls
    ``scipy.spatial`` (0.2 s) into the keypoints process, whose start is the critical path of a small
    drawing (stages/DECISIONS.md, keypoints); ``tests/stages/test_keypoints.py`` holds it to skimage's
    result.

    Parameters
    ----------
    image : numpy.ndarray
        2-D float array (H1).
    min_distance : int
        At least 1.
    threshold : float
        Candidates must be strictly greater.

    Returns
    -------
    numpy.ndarray
        int64 (N, 2) (row, column).
    """
    image = np.asarray(image)
    if image.size == 1:
        mask = image > threshold
    else:
        mask = image == ndimage.maximum_filter(image, size=2 * min_distance + 1, mode="nearest")
        if mask.all():  # a constant image has no peak
            mask[:] = False
        mask &= image > threshold
    coords = np.argwhere(mask)
    coords = coords[np.argsort(-image[mask], kind="stable")]
    if min_distance <= 1 or len(coords) < 2:
        return coords.astype(np.int64)
    k = len(coords)
    r = min_distance - 1
    if r <= MAX_WINDOW_LOOKUP:
        # The later candidates within Chebyshev distance < min_distance of each one, found by looking
        # up each offset of that window in an image of candidate ranks: linear in the candidates.
        rank = np.full(image.shape, -1, np.int32)   # int32: an image-sized array (35 MB for an A4 page)
        rank[coords[:, 0], coords[:, 1]] = np.arange(k, dtype=np.int32)
        firsts, seconds = [], []
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                y, x = coords[:, 0] + dy, coords[:, 1] + dx
                ok = (y >= 0) & (y < image.shape[0]) & (x >= 0) & (x < image.shape[1])
                other = np.full(k, -1, np.int64)
                other[ok] = rank[y[ok], x[ok]]
                later = other > np.arange(k)
                firsts.append(np.flatnonzero(later))
                seconds.append(other[later])
        first, second = np.concatenate(firsts), np.concatenate(seconds)
    else:
        # a wide window: its offsets would outnumber the candidates' neighbours; pairs from a KD-tree
        from scipy.spatial import cKDTree

        pairs = cKDTree(coords).query_pairs(r, p=np.inf, output_type="ndarray")   # i < j, distances ≤ r
        first, second = pairs[:, 0], pairs[:, 1]
    order = np.argsort(first, kind="stable")
    second = second[order]
    bounds = np.searchsorted(first[order], np.arange(k + 1))
    alive = np.ones(k, bool)
    for q in range(k):   # highest first: an accepted candidate removes its later neighbours
        if alive[q]:
            alive[second[bounds[q]:bounds[q + 1]]] = False
    return coords[alive].astype(np.int64)


def dilate_band(mask: np.ndarray, radius: int) -> np.ndarray:
    """The narrow band grown by ``radius`` pixels (disk)."""
    if radius <= 0:
        return mask.astype(bool)
    yy, xx = np.mgrid[-radius:radius + 1, -radius:radius + 1]
    return ndimage.binary_dilation(mask, structure=(xx * xx + yy * yy) <= radius * radius)


def use_bf16(precision: str) -> bool:
    """Whether ``keypoints.precision`` means bfloat16 on this machine (``auto``: where the CPU has
    native bf16 instructions; emulated bf16 is slower than float32)."""
    if precision == "auto":
        import torch

        probe = getattr(torch.cpu, "_is_avx512_bf16_supported", None)
        return bool(probe and probe())
    return precision == "bf16"
