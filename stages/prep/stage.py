"""Stage ``prep``: decode the drawing, grey it, normalise its contrast and find the narrow band.

The narrow band is the set of ink pixels on which the PolyVector field lives (B19 §A.1: "simply
the set of dark pixels", no dilation), followed by the reference's small-hole repair.

:func:`run` takes these steps in this order; each is a module of this package, whose docstring says what
it does and the choices made on purpose, with their reasons and measurements:

1. :mod:`~stages.prep.decode`: the file's bytes to grey levels over white (alpha composited), upright
   (EXIF orientation).
2. :mod:`~stages.prep.sheet`: a sheet photographed on a darker desk is cut out of it, or, seen whole,
   flattened to its rectangle (:mod:`~stages.prep.sheet_flatten`); first of all, before the inversion
   and the lighting, which the desk misled.
3. :mod:`~stages.prep.invert`: light strokes on dark paper are turned into ink on paper.
4. :mod:`~stages.prep.lighting`: the paper's uneven brightness is divided out.
5. :mod:`~stages.prep.crop`: a drawing on a much larger page is cut to its ink's box, dust and the
   page's dark edge left out (:mod:`~stages.prep.specks`), or its parts far apart are laid side by side
   (:mod:`~stages.prep.layout`).
6. :mod:`~stages.prep.contrast` and :mod:`~stages.prep.band`: the grey stretched, paper white and ink
   black, and the narrow band found on it (hole repair with all 8 neighbours, not the reference's
   direction-dependent 5 of 6; the threshold kept clear of the paper grain); on the crop's box, on each
   piece of a mosaic, or on the whole page.
7. :mod:`~stages.prep.upscaling`: a drawing enlarged from a low resolution (a staircase of blocks) is
   smoothed at its block period, and the band found again.
8. :mod:`~stages.prep.supersampling` or :mod:`~stages.prep.downsampling`: thin aliased strokes worked
   on at a higher resolution, wide ones at a lower (decided on :mod:`~stages.prep.width`), and the band
   found again there (:func:`~stages.prep.band.band_at_scale`).

Choices made on purpose
-----------------------
* **Two size limits**: ``max_page_pixels`` (80 M) refuses to decode larger files; ``max_pixels``
  (16 M) bounds what the later stages work on, after the crop and resampling, since a sketch on an
  A4 sheet at 600 dpi (35 Mpx, refused before) is a box of ~1.6 Mpx, downsampled (stages/DECISIONS.md).
"""

from __future__ import annotations

from stages.artifact import Artifact
from stages.config import from_section
from stages.errors import InputError
from stages.prep import PrepConfig
from stages.prep.band import band_at_scale, grey_and_band
from stages.prep.crop import cropped
from stages.prep.decode import decode_image
from stages.prep.downsampling import downsampled
from stages.prep.invert import invert
from stages.prep.lighting import even_lighting
from stages.prep.sheet import photographed_sheet
from stages.prep.supersampling import supersampled
from stages.prep.upscaling import deblocked
from stages.prep.width import stroke_width


def run(cfg: dict, image_bytes: bytes, image_name: str = "") -> Artifact:
    """Decode and prepare one drawing.

    Parameters
    ----------
    cfg : dict
        The ``prep`` config section (keys of :class:`PrepConfig`).
    image_bytes : bytes
        Content of the image file.
    image_name : str
        For messages only.

    Returns
    -------
    Artifact
        ``grey`` float32 (H, W) and ``mask`` bool (H, W); see stages/INTERFACES.md.
    """
    c = from_section(PrepConfig, cfg, "prep")
    grey, mode, decode_notes, focal_35mm = decode_image(image_bytes, c.max_page_pixels)
    notes: list[str] = list(decode_notes)
    # A photographed sheet's corner in the photograph: every box below is the sheet's, moved by it.
    source_shape, corner, origin, sheet_corners = grey.shape, (0, 0), None, None
    if c.crop.enabled and (sheet := photographed_sheet(grey, c, focal_35mm)) is not None:
        grey, corner, source_shape, note, sheet_corners = sheet
        origin = list(corner)
        notes.append(note)
    grey, more = invert(grey, c.invert)
    notes += more
    grey, more = even_lighting(grey, c.lighting)
    notes += more
    pieces = None
    if c.crop.enabled and (crop := cropped(grey, c, corner)) is not None:
        grey, mask, band_data, origin, pieces, note = crop
        notes.append(note)
    else:
        grey, mask, band_data = grey_and_band(grey, c)
    grey, period, more = deblocked(grey, mask, c.deblock)
    notes += more
    if period is not None:
        mask = band_at_scale(grey, 1.0, pieces, band_data, c)
    width = stroke_width(mask) if c.supersample.enabled or c.downsample.enabled else None
    grey, factor, more = supersampled(grey, mask, width, c.supersample)
    notes += more
    scale = float(factor)
    if factor == 1:
        grey, k, more = downsampled(grey, mask, width, c.downsample)
        notes += more
        scale = 1.0 / k
    if grey.size > c.max_pixels:
        raise InputError(f"drawing too large to work on: {grey.shape[1]}x{grey.shape[0]} = {grey.size} pixels "
                         f"after the crop and resampling > prep.max_pixels={c.max_pixels} (crop the image, or "
                         "scan at a lower resolution)")
    if scale != 1.0:
        mask = band_at_scale(grey, scale, pieces, band_data, c)
    return Artifact(arrays={"grey": grey, "mask": mask},
                    data={"height": source_shape[0], "width": source_shape[1], "scale": scale, "origin": origin,
                          **({"pieces": pieces} if pieces else {}), "stroke_width": width, "mode": mode,
                          **({"block_period": period} if period is not None else {}),
                          **({"sheet_corners": sheet_corners} if sheet_corners else {}), **band_data},
                    notes=notes)
