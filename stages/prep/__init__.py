"""Stage ``prep``: decode the drawing, grey it, normalise its contrast and find the narrow band.

``STAGE_VERSION`` and the config dataclasses. Its code is in :mod:`stages.prep.stage` (``run``: the
order of the steps, and the docstring that describes it) and one module per step (``decode``,
``sheet``, ``sheet_flatten``, ``invert``, ``lighting``, ``crop``, ``specks``, ``layout``, ``contrast``,
``band``, ``upscaling``, ``width``, ``supersampling``, ``downsampling``; shared helpers in ``pixels``), whose
docstrings say what each step does and its choices; ``run`` and the other public names load from there
when first used (:mod:`stages.lazy`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.errors import InputError
from stages.lazy import lazy_names

STAGE_VERSION = "15"  # 2: paper-white pixels repaired only as one-pixel pinholes; 3: sparse ink is not blank;
#                     4: the band threshold stays clear of the paper grain; 5: thin strokes supersampled;
#                     6: wide strokes downsampled; 7: on grainy paper the band is found on a smoothed grey;
#                     8: an EXIF orientation is applied (the drawing upright, as viewers show it), uneven
#                        lighting is divided out (prep.lighting); 9: light strokes on dark paper are
#                        inverted (prep.invert), white line art on a transparent page read over black;
#                     10: a drawing on a much larger page is cropped to its ink (prep.crop); 11: small
#                        marks far from the drawing (dust on a scanned sheet) and the page's dark edge do
#                        not widen the crop; 12: parts far apart on a page are laid side by side (a mosaic),
#                        a photographed sheet is cut out of the darker background round it; 13: it is
#                        found before the inversion, turned or running off the photo, its box's desk painted;
#                     14: a photographed sheet seen whole is flattened to its rectangle (prep.crop.sheet_flatten);
#                     15: a drawing enlarged from a low resolution is smoothed at its block period (prep.deblock);
#                        strokes that cut a grey page in two are no photographed sheet


@dataclass
class ContrastConfig:
    """``prep.contrast``: percentile stretch of the grey levels (darkest ink → black, paper → white)."""

    enabled: bool
    low_percentile: float
    high_percentile: float
    min_contrast: float


@dataclass
class LightingConfig:
    """``prep.lighting``: divide out the paper's uneven brightness (a photographed drawing, a shadow)."""

    enabled: bool
    window_px: float
    min_range: float

    def __post_init__(self) -> None:
        if self.window_px < 3 or not 0 <= self.min_range <= 1:
            raise InputError("prep.lighting: need window_px ≥ 3 and 0 ≤ min_range ≤ 1")


@dataclass
class SupersampleConfig:
    """``prep.supersample``: work at a higher internal resolution when the strokes are too thin."""

    enabled: bool
    below_width: float
    max_soft_edges: float
    target_width: float
    max_factor: int
    max_pixels: int
    blur: float

    def __post_init__(self) -> None:
        if self.below_width < 0 or not 0 <= self.max_soft_edges <= 1 or self.target_width <= 0 \
                or self.max_factor < 1 or self.max_pixels < 1 or self.blur < 0:
            raise InputError("prep.supersample: need below_width ≥ 0, 0 ≤ max_soft_edges ≤ 1, target_width > 0, "
                             "max_factor ≥ 1, max_pixels ≥ 1, blur ≥ 0")


@dataclass
class DeblockConfig:
    """``prep.deblock``: a drawing enlarged from a low resolution is smoothed at its block period."""

    enabled: bool
    min_lattice: float
    min_period: float
    max_period: float
    blur: float

    def __post_init__(self) -> None:
        if self.min_lattice < 0 or not 1 < self.min_period <= self.max_period or self.blur < 0:
            raise InputError("prep.deblock: need min_lattice ≥ 0, 1 < min_period ≤ max_period and blur ≥ 0")


@dataclass
class DownsampleConfig:
    """``prep.downsample``: work at a lower internal resolution when the strokes are wide."""

    enabled: bool
    above_width: float
    target_width: float
    max_factor: int

    def __post_init__(self) -> None:
        if self.above_width <= 0 or self.target_width <= 0 or self.max_factor < 1:
            raise InputError("prep.downsample: need above_width > 0, target_width > 0, max_factor ≥ 1")


@dataclass
class CropConfig:
    """``prep.crop``: work on the ink's bounding box when the drawing covers a small part of the page."""

    enabled: bool
    margin_px: int
    max_area_fraction: float
    cluster_gap_px: int
    min_cluster_share: float
    max_speck_px: int
    page_edge_fraction: float
    sheet_rim_share: float
    sheet_min_contrast: float
    sheet_flatten: bool

    def __post_init__(self) -> None:
        if not 0 < self.sheet_rim_share <= 1 or not 0 < self.sheet_min_contrast <= 1:
            raise InputError("prep.crop: need 0 < sheet_rim_share ≤ 1 and 0 < sheet_min_contrast ≤ 1")
        if self.margin_px < 0 or not 0 < self.max_area_fraction <= 1:
            raise InputError("prep.crop: need margin_px ≥ 0 and 0 < max_area_fraction ≤ 1")
        if (self.cluster_gap_px < 1 or not 0 <= self.min_cluster_share <= 1 or self.max_speck_px < 0
                or not 0 < self.page_edge_fraction <= 1):
            raise InputError("prep.crop: need cluster_gap_px ≥ 1, 0 ≤ min_cluster_share ≤ 1, max_speck_px ≥ 0 "
                             "and 0 < page_edge_fraction ≤ 1")


@dataclass
class PrepConfig:
    """The ``prep`` config section (``conf/prep/default.yaml``), one field per key."""

    max_page_pixels: int
    max_pixels: int
    threshold: float
    repair_passes: int
    repair_neighbours: int
    repair_max_grey: float
    min_component_px: int
    paper_grain_sigmas: float
    grain_smoothing: float
    max_ink_fraction: float
    invert: str
    lighting: LightingConfig
    contrast: ContrastConfig
    deblock: DeblockConfig
    supersample: SupersampleConfig
    downsample: DownsampleConfig
    crop: CropConfig

    def __post_init__(self) -> None:
        if self.invert not in ("auto", "always", "never"):
            raise InputError(f"prep.invert must be 'auto', 'always' or 'never', got {self.invert!r}")


def internal_scale(data: dict) -> float:
    """Internal pixels per drawing pixel of a prep or keypoints artifact (its ``data``): 1, the
    factor of a supersampled prep (thin aliased strokes, 2), or 1/k of a downsampled one (wide
    strokes); later stages' coordinates are the drawing's times this, from :func:`internal_origin`."""
    return float(data.get("scale", 1) or 1)


def internal_origin(data: dict) -> np.ndarray:
    """(x, y) in the drawing's pixels of the internal picture's corner: (0, 0), or where prep cropped a
    drawing out of a larger page (``origin`` of a prep or keypoints artifact's ``data``; (0, 0) for a
    mosaic of pieces, whose offsets are :func:`internal_pieces`')."""
    return np.asarray(data.get("origin") or (0, 0), np.float64)


def internal_pieces(data: dict) -> np.ndarray | None:
    """float64 (K, 6) ``(mosaic x, mosaic y, source x, source y, width, height)`` of each box of a
    drawing whose far-apart parts prep laid side by side (``pieces`` of a prep or keypoints artifact's
    ``data``, in the drawing's pixels), or None."""
    pieces = data.get("pieces")
    return np.asarray(pieces, np.float64).reshape(-1, 6) if pieces else None


def piece_windows(data: dict, shape: tuple[int, int]) -> list[tuple[slice, slice]] | None:
    """The internal (rows, columns) window of each piece of a mosaic (:func:`internal_pieces`) in a
    picture of ``shape``, or None: work that looks at a pixel's surroundings (the keypoint network) runs
    on each alone, as on a drawing cropped to that piece, and not on the paper between them."""
    pieces = internal_pieces(data)
    if pieces is None:
        return None
    scale, (h, w) = internal_scale(data), shape[-2:]
    return [(slice(int(np.floor(y * scale)), min(h, int(np.ceil((y + ph) * scale)))),
             slice(int(np.floor(x * scale)), min(w, int(np.ceil((x + pw) * scale)))))
            for x, y, _, _, pw, ph in pieces]


def internal_frame(data: dict) -> dict:
    """The ``data`` keys that map a prep's internal pixels to the drawing's (``scale``, ``origin``,
    ``pieces``): a later artifact that keeps them maps its points with :func:`to_source` alone."""
    frame = {"scale": internal_scale(data), "origin": internal_origin(data).tolist()}
    return dict(frame, pieces=data["pieces"]) if data.get("pieces") else frame


def internal_is_source(data: dict) -> bool:
    """Whether the internal pixels are the drawing's (no resampling, no crop): the mappings below are
    the identity, and callers that keep their values as they are may skip them."""
    return internal_scale(data) == 1 and not internal_origin(data).any() and internal_pieces(data) is None


def _nearest_box(points: np.ndarray, corners: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Index of the box (corner, size) each point lies in, or the nearest one (a point on the paper
    between a mosaic's pieces, or a curve's end a pixel beyond its box)."""
    below = corners[None] - points[:, None]
    above = points[:, None] - (corners + sizes)[None]
    gap = np.maximum(np.maximum(below, above), 0.0)
    return np.argmin((gap * gap).sum(axis=2), axis=1)


def to_source(points, data: dict) -> np.ndarray:
    """(N, 2) internal (x, y) → the drawing's pixels: ``internal / scale + origin``; in a mosaic, each
    point moves by the offset of the piece it lies in (or is nearest to)."""
    at = np.asarray(points, np.float64).reshape(-1, 2) / internal_scale(data)
    pieces = internal_pieces(data)
    if pieces is None:
        return at + internal_origin(data)
    k = _nearest_box(at, pieces[:, 0:2], pieces[:, 4:6])
    return at - pieces[k, 0:2] + pieces[k, 2:4]


def to_internal(points, data: dict) -> np.ndarray:
    """(N, 2) (x, y) in the drawing's pixels → internal: ``(source − origin) · scale``; in a mosaic,
    by the offset of the piece whose box holds the point (or is nearest to it)."""
    at = np.asarray(points, np.float64).reshape(-1, 2)
    pieces = internal_pieces(data)
    if pieces is None:
        return (at - internal_origin(data)) * internal_scale(data)
    k = _nearest_box(at, pieces[:, 2:4], pieces[:, 4:6])
    return (at - pieces[k, 2:4] + pieces[k, 0:2]) * internal_scale(data)


def source_size(data: dict, internal_shape: tuple[int, int]) -> tuple[int, int]:
    """(height, width) of the drawing itself: prep's ``height``/``width``, else (a prep made by hand,
    with only its grey) the internal shape divided by :func:`internal_scale`."""
    scale = internal_scale(data)
    return tuple(int(data.get(k) or round(n / scale)) for k, n in zip(("height", "width"), internal_shape[-2:]))


__getattr__, __dir__ = lazy_names(__name__, {
    "stages.prep.stage": ("run",),
    "stages.prep.decode": ("decode_image",),
    "stages.prep.lighting": ("flatten_lighting",),
    "stages.prep.contrast": ("normalise_contrast",),
    "stages.prep.band": ("paper_statistics", "narrow_band"),
    "stages.prep.upscaling": ("block_period", "deblocked"),
    "stages.prep.width": ("stroke_width", "soft_edges"),
    "stages.prep.supersampling": ("supersample_factor", "supersample"),
    "stages.prep.downsampling": ("downsample_factor", "downsample"),
})
