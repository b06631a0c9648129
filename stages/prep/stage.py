"""Stage ``prep``: decode the drawing, grey it, normalise its contrast and find the narrow band.

The narrow band is the set of ink pixels on which the PolyVector field lives (B19 §A.1: "simply
the set of dark pixels", no dilation), followed by the reference's small-hole repair.

Choices made on purpose
-----------------------
* **Light strokes on dark paper are inverted** (``invert: auto``; not in the references): the paper
  level (the median grey, as for the grain below) darker than mid-grey means chalk on a blackboard or
  a negative scan, which the threshold would otherwise read as a page of ink ("no ink stands out of
  the paper grain"); the grey is turned into ``1 − grey`` and a note says so. Why mid-grey: the paper
  of every validation, realvec_dev and bundled drawing is at 0.82 or lighter, and a page darker than
  mid-grey has more ink than paper, which is no line drawing either way.  A photographed sheet is cut
  out of its desk first (below), and the level is its paper's.
* **Alpha** is composited over white (the authors' detector ignores alpha, which their issue #7
  traces to blank predictions on transparent PNGs) — over black when the opaque strokes on a mostly
  transparent page are lighter than mid-grey (white line art for a dark background), which the
  inversion above then turns into ink on paper.
* **Uneven lighting is divided out** (``lighting``; not in the references): a photographed drawing
  or a scan with a shadow has paper from white to mid-grey, and one threshold then took the shadow
  for ink or the faint strokes for paper (a rough pencil bird under a 33 % shadow: "no ink stands
  out of the paper grain"). The paper's brightness (a grey closing over ``window_px``, wider than
  strokes) divides the grey where it varies by at least ``min_range`` (12 %) across the page; evenly
  lit drawings (every validation, realvec_dev and bundled drawing: at most 8.6 %) are left exactly as
  they were. Measured on shadowed copies of the validation split (stages/DECISIONS.md, prep).
* **Contrast normalisation** is done here, not by hand as in the paper: the grey levels at the
  ``low_percentile`` and ``high_percentile`` are stretched to 0 and 1. With mostly-white drawings the
  high percentile is paper, the low one the darkest ink, so faint pencil reaches the same mask
  threshold as ink. Stretching is skipped when the black level is already below ``max_black`` and
  only applied upward when the ink is faint, so clean drawings are left as they are.
* **Hole repair** uses all 8 neighbours (a background pixel with at least ``repair_neighbours`` ink
  neighbours becomes ink, ``repair_passes`` times). The reference loop skips the (−1,−1) and (+1,+1)
  offsets by accident (``i1 == j1``), which makes the rule depend on stroke direction; we do not
  copy that quirk. 6 of 8 (75 %) is close to the share of the reference's 5 of 6 (83 %).
  Repair is for pencil texture (pinholes of light grey inside a stroke); a pixel as light as paper
  (grey > ``repair_max_grey``, 0.85) is repaired only when all 8 neighbours are ink. Why: on clean
  drawings the plain rule filled the white slit inside narrow loops (an eye drawn as a thin
  teardrop became a filled blob, vectorised as one line with two free ends) and the paper in acute
  vees. On realvec_dev (detector keypoints) this moved F1@2 0.9941 → 0.9953, the drawings with
  Hausdorff ≤ 3 px 57 → 63 and the junction F1 median 0.718 → 0.725; pencil drawings, whose repaired
  pixels are almost all darker than 0.85, are unchanged.
* Mask components smaller than ``min_component_px`` pixels (scanner dust) are dropped.
* **Paper grain**: the band threshold is lowered to ``paper_grain_sigmas`` grain deviations below the
  paper level (median and MAD of the stretched grey) when the grain would otherwise cross it. Why:
  faint pencil on grainy paper put 25–53 % of the page in the band (3 of 84 pencil drawings of the
  validation split; 4,002 flow paths on one 512² drawing). The reference has no such rule.
  Where the grain lowers the threshold, the band (and the paper statistics that set the threshold)
  is found on the grey blurred by ``grain_smoothing`` px (Gaussian σ): the lowered threshold kept
  only the darkest grains of a faint line, a broken 1-px band that the graph traced as dozens of
  pieces (stages/DECISIONS.md, prep). The grey passed on is not blurred.
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
* **Wide strokes are downsampled** (``downsample``; issue #14, not in the references).  When the mean
  stroke width is at least ``above_width`` px (a high-resolution scan), the grey is shrunk by the
  integer ``k = min(max_factor, floor(width / target_width))`` (block means; internal ``x = x_source /
  k``) and banded again, so strokes reach the later stages about ``target_width``–``2·target_width`` px
  wide, the widths the keypoint network was trained on (1–12 px).  Why: the field, the tracing
  and the cross-sections cost grows with the lanes across a stroke times its length (a 4× scan took
  157 s and 3.5 GB), not with what the drawing shows; the curves come back in the drawing's pixels
  (``scale`` = 1/k).  Chosen on validation cases re-rendered 3× larger (stages/DECISIONS.md).
* **A drawing on a larger page is cropped to its ink** (``crop``; issue #14, not in the references).
  When the band's bounding box grown by ``margin_px`` keeps at most ``max_area_fraction`` of the
  image (a sketch on a scanned sheet), the inverted and lighting-flattened grey is cut to it, its
  contrast stretch and band are found again there (on a sheet the page's percentiles are the paper's:
  ink under 0.5 % of the pixels stretched the paper's texture into the band), the resampling follows,
  and every later stage works on the box: ``origin`` in the data is its corner in the drawing's
  pixels (internal ``x = scale · (x_source − origin)``), which the export maps back.  Why: the
  field, graph, topology and network cost grew with the page, not the ink, and the page's stretch
  made paper texture band (the elephant on an A4 sheet at 300 dpi: 48.7 s and 269 curves against
  10.1 s and 100, 97 alone; stages/DECISIONS.md).  A drawing that fills its image, or an elongated
  one (``max_area_fraction`` 0.25, chosen on the validation splits), is left as it is, so its
  results do not move; a cropped one is processed as the same drawing cut out by hand.  The box is
  found on the unstretched grey (ink ``min_contrast`` and the grain's deviations below the paper: the
  page's stretch made faint pencil on a sheet "blank"), and dust does not widen it: marks no larger
  than ``max_speck_px``, clusters with under ``min_cluster_share`` of the largest one's ink and the
  page's dark edge (ink along ``page_edge_fraction`` of a side) are left out, with a note (six specks
  kept the elephant's A4 sheet whole: 50 s and 280 curves; 0.02 is the geometric middle between the
  validation splits' smallest far stroke, 0.076, and grain, 0.005).
* **Parts far apart are laid side by side** (``crop``; issue #14, not in the references).  When the one
  box round the kept clusters keeps more than ``max_area_fraction`` of the page (two sketches in
  opposite corners of a sheet) but each cluster's box grown by ``margin_px`` (overlapping ones merged)
  keeps at most that share together, those boxes are cut out, their contrast and band found on each
  (as if cut out by hand), and laid in rows, ``margin_px`` of paper between them, on one picture (a
  mosaic);
  ``pieces`` in the data holds each one's corner in the mosaic and in the drawing, which
  :func:`~stages.prep.to_source` maps each point back by.  Why: every later stage grew with the
  page, not the ink (the elephant and the kitten on an A4 sheet: 33 s and 1.7 GB, against 14 s for
  the two alone); the field, the graph and the topology see the same disjoint strokes, and the
  keypoint network runs on each piece alone (:func:`~stages.prep.piece_windows`).
* **A photographed sheet is cut out of the ground round it** (``crop.sheet_rim_share``,
  ``crop.sheet_min_contrast``; issue #14, not in the references).  First of all, before the inversion
  and the lighting, the largest bright region of 16-px cells' means (holes filled) is the sheet when
  solid darker ground (48 px and wider) runs along at least ``sheet_rim_share`` (0.4) of the image's
  border, at least ``sheet_min_contrast`` (0.2) below the paper, the sheet's edge is a step (not
  lighting's slope) and half its cells are plain paper; the later steps work on the box of the sheet
  less one cell, whatever its shape (turned, in perspective, running off the photo), the ground inside
  the box painted with the nearest paper's grey, and ``origin``/``pieces`` are moved by its corner.
  Why: divided by its own brightness, the desk became speckle and the sheet's border a frame of band
  (``photo_desk.png``: 83 curves at 1/4 resolution); a desk over half the photo made the paper level
  dark, so the photo was inverted (a turned sheet: 31 curves, most of them across the paper); a turned
  sheet's corners of desk stayed in the box.  The validation splits' drawings, and the same drawings
  inverted (chalk), have at most 0.2 of their border solid and darker (the banana tree's scan: a shaded
  corner); none of them, and none of the same drawings turned on a page lit from one corner, passes the
  four tests (stages/DECISIONS.md).
* **A photographed sheet seen whole is flattened** (``crop.sheet_flatten``; not in the references).
  When no cell of the sheet is on the photo's border and its edge is four straight sides, its corners
  are found to under a pixel (lines through the edge's sub-pixel points, each the one most of its side's
  points lie on), and the sheet is mapped through their homography onto a rectangle of its proportions
  (the focal length from EXIF, else from the sides' vanishing points, else a phone's); the drawing is
  that rectangle, upright, and the curves are in its pixels, not the photo's.  Why: a sketch
  photographed at an angle came out in perspective and turned, which no artist wants to edit; on 24
  validation drawings photographed leaning 10-40° back, flattened output scores better than the
  photo-frame output even when that is un-warped with the true camera (stages/DECISIONS.md).  Choice:
  the SVG is the flattened sheet's, not mapped back to the photo (scanner apps do the same), so that the
  drawing's right angles and proportions are kept; ``sheet_flatten=false`` keeps the photo's pixels.
* **Two size limits**: ``max_page_pixels`` (80 M) refuses to decode larger files; ``max_pixels``
  (16 M) bounds what the later stages work on, after the crop and resampling, since a sketch on an
  A4 sheet at 600 dpi (35 Mpx, refused before) is a box of ~1.6 Mpx, downsampled (stages/DECISIONS.md).
"""

from __future__ import annotations

import io
import warnings
from typing import NamedTuple

import numpy as np
from scipy import ndimage

from stages.artifact import Artifact
from stages.config import from_section
from stages.errors import InputError
from stages.prep import PrepConfig, piece_windows

_EIGHT = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]])
#: Mid-grey: ``invert: auto`` turns the grey over when the paper level (the median grey) is darker,
#: and a transparent page whose strokes are lighter is read over black (:func:`_backdrop`).
MID_GREY = 0.5
#: Percentile of the ink (the pixels ``min_contrast`` below the paper) stretched to black when the page's
#: percentiles are both paper (:func:`normalise_contrast`).
SPARSE_INK_BLACK_PERCENTILE = 25.0
#: A page's dark edge is the ink, within this many pixels of the sides, of the components that run along
#: a side (an 18-px strip at 300 dpi, 36 at 600); the rest of such a component is a drawing touching it.
PAGE_EDGE_BAND_PX = 64
#: Side of the cells the crop looks at the page in (the ink's clusters, the photographed sheet): px.
CELL_PX = 16
#: A photographed sheet's ground is solid: its cells survive an opening by this many cells (48 px), which
#: strokes and a scan's dark page edge do not.
SHEET_SOLID_CELLS = 3
#: ... and so is most of the sheet: at least this share of its cells are plain paper that survives the same
#: opening (on an inverted drawing's dark paper the bright "region" is strokes, hatching and grain).
SHEET_MIN_SOLID = 0.5
#: ... and its edge a step: the median grey drop from a sheet cell to its neighbour outside is at least this
#: share of the paper's contrast with the ground (turned sheets on desks: 0.43-0.67; lighting that darkens
#: one side of a page, the same drawings without a desk: 0.01-0.10).
SHEET_MIN_STEP = 0.25
#: A sheet seen whole is flattened when its edge is four straight sides: at least this share of the edge's
#: points lie within :data:`SHEET_SIDE_TOLERANCE` of them (a torn or curled sheet is cut out as it is) ...
SHEET_MIN_ON_SIDES = 0.9
#: ... px, or 0.5 % of the sheet's diagonal when larger (the edge is found on the grey smoothed by 1.5 px).
SHEET_SIDE_TOLERANCE = 2.0
#: ... and its corners' angles lie within this many degrees of a right angle (a phone held at up to ~40°).
SHEET_MAX_SKEW = 40.0
#: A flattened sheet's proportions need the camera's focal length, in the photo's longer sides: one found
#: from the sheet's corners outside this range is not trusted (vanishing points nearly at infinity) ...
SHEET_FOCAL_RANGE = (0.3, 5.0)
#: ... and this one is taken instead: a phone's main camera (24-28 mm equivalent on a 4:3 sensor: 0.7-0.8).
SHEET_ASSUMED_FOCAL = 0.75
#: mm: the diagonal of 35-mm film, which an EXIF focal length "in 35-mm film" is relative to.
FILM_35MM_DIAGONAL = 43.27
#: At most this many of the edge's hull vertices are searched for its largest quadrilateral (O(n³): 14 MB).
SHEET_HULL_MAX = 120
#: Lines tried through two of a side's edge points; the one most of them lie on (within 1 px) is fitted.
SHEET_LINE_TRIES = 256
#: px of the flattened sheet's rim left out of the work (its shadowed edge; its corners are found to ~1 px).
SHEET_RIM_PX = 8


def decode_image(image_bytes: bytes, max_pixels: int) -> tuple[np.ndarray, str, list[str], float | None]:
    """Decode PNG/JPEG/TIFF/BMP/WebP/AVIF bytes (HEIC with ``pillow-heif``) into grey levels over white,
    upright as a viewer shows them.

    An EXIF orientation (a phone photo, many scanners' JPEG and TIFF) is applied, as every image viewer
    and browser does: the curves then lie on the drawing the user sees, in its width and height. Of a
    multi-page file (TIFF, GIF) the first page is read, and a note says so.

    Parameters
    ----------
    image_bytes : bytes
        The file's content.
    max_pixels : int
        Refuse images with more pixels than this (checked before decoding the pixel data).

    Returns
    -------
    grey : numpy.ndarray
        float64 (H, W) in [0, 1], 1 = white; alpha composited over white (light strokes on a
        transparent page: over black, see :func:`_backdrop`).
    mode : str
        The source image mode (e.g. ``"RGBA"``, ``"I;16"``).
    notes : list of str
        One line per thing the user should know (pages left out).
    focal_35mm : float or None
        The photo's focal length in 35-mm film terms (EXIF ``FocalLengthIn35mmFilm``, mm), for a
        photographed sheet's proportions (:func:`_sheet_aspect`); None when the file has none.

    Raises
    ------
    InputError
        Empty file, not an image, too many pixels, or a corrupt image.
    """
    from PIL import Image, UnidentifiedImageError

    if len(image_bytes) == 0:
        raise InputError("empty file")
    if _is_heif(image_bytes):
        _register_heif()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            img = Image.open(io.BytesIO(image_bytes))
            w, h = img.size
            if w * h > max_pixels:
                raise InputError(f"image too large: {w}x{h} = {w * h} pixels > prep.max_page_pixels={max_pixels}")
            if w == 0 or h == 0:
                raise InputError("image has no pixels")
            img.load()
    except InputError:
        raise
    except UnidentifiedImageError:
        raise InputError("not an image (unrecognised file format)") from None
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        # Pillow's own limit (Image.MAX_IMAGE_PIXELS, ≈ 89.5 Mpx) fires in Image.open, before our
        # max_pixels check: name the limit that applied, since raising max_pixels does not lift it.
        raise InputError(f"image too large for the decoder (Pillow's decompression-bomb limit of "
                         f"{Image.MAX_IMAGE_PIXELS} pixels, whatever prep.max_page_pixels says)") from None
    except (OSError, ValueError, SyntaxError) as exc:
        raise InputError(f"corrupt or truncated image ({exc})") from None
    mode = img.mode
    notes = []
    pages = getattr(img, "n_frames", 1)
    if pages > 1:
        notes.append(f"{pages} pages (frames) in the file: the first is vectorised")
    exif = img.getexif()
    focal = _exif_focal(exif)
    if exif.get(0x0112, 1) != 1:   # EXIF Orientation: 1 = upright as stored
        from PIL import ImageOps

        img = ImageOps.exif_transpose(img)
    return _to_grey(img), mode, notes, focal


#: ISO base media file brands of HEIF images (a phone's HEIC photo, HEIF stills and sequences); AVIF's
#: ``avif``/``avis`` are Pillow's own.
HEIF_BRANDS = {b"heic", b"heix", b"hevc", b"hevx", b"heim", b"heis", b"hevm", b"hevs", b"mif1", b"msf1"}


def _is_heif(data: bytes) -> bool:
    """Whether ``data`` starts as a HEIF file: an ISO base media ``ftyp`` box of a HEIF brand."""
    return len(data) >= 12 and data[4:8] == b"ftyp" and data[8:12] in HEIF_BRANDS


def _register_heif() -> None:
    """Let Pillow open HEIF (an iPhone's HEIC photos) through the optional ``pillow-heif``.

    Raises
    ------
    InputError
        ``pillow-heif`` is not installed: one line saying how to get it, or to export the photo.
    """
    try:
        import pillow_heif
    except ImportError:
        raise InputError("a HEIC/HEIF photo: reading it needs the optional pillow-heif "
                         "(pip install pillow-heif, or polyvec's [heic] extra), or export it as JPEG or PNG") from None
    pillow_heif.register_heif_opener()


def _to_grey(img) -> np.ndarray:
    """Grey levels in [0, 1] from any PIL mode, alpha composited over white (or black: :func:`_backdrop`)."""
    mode = img.mode
    if mode == "P":
        img = img.convert("RGBA" if "transparency" in img.info else "RGB")
        mode = img.mode
    if mode in ("I;16", "I;16B", "I;16L", "I;16N", "I", "F"):
        a = np.asarray(img).astype(np.float64)
        top = 65535.0 if (mode.startswith("I;16") or a.max() > 255) else 255.0
        if mode == "F":
            top = max(1.0, float(a.max()))
        return np.clip(a / top, 0.0, 1.0)
    if mode == "1":
        return np.asarray(img, dtype=np.float64)
    if mode in ("LA", "RGBA", "PA", "La", "RGBa"):
        rgba = np.asarray(img.convert("RGBA"), dtype=np.float64) / 255.0
        alpha = rgba[..., 3]
        lum = rgba[..., :3] @ np.array([0.299, 0.587, 0.114])
        return lum * alpha + _backdrop(lum, alpha) * (1.0 - alpha)
    if mode != "L":
        img = img.convert("RGB")
        rgb = np.asarray(img, dtype=np.float64) / 255.0
        return rgb @ np.array([0.299, 0.587, 0.114])
    return np.asarray(img, dtype=np.float64) / 255.0


def _backdrop(lum: np.ndarray, alpha: np.ndarray) -> float:
    """The grey a transparent page is read over: white, unless its opaque part — mostly transparent
    around it — is lighter than mid-grey (white line art made for a dark background), which would
    vanish on white: then black, and ``prep.invert`` turns the page over."""
    covered = float(alpha.sum())
    if covered == 0.0 or covered >= 0.5 * alpha.size:
        return 1.0
    return 0.0 if float((lum * alpha).sum()) / covered > MID_GREY else 1.0


#: The darkest shade of the paper :func:`flatten_lighting` divides out, relative to the brightest paper;
#: darker areas wider than its window are ink (fills), not shadow.
SHADE_FLOOR = 0.4
#: Fewer blocks than this across the shrunk copy (a strip) and the lighting is left alone.
MIN_LIGHTING_BLOCKS = 8


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
        full = _blocks(paper, fy, fx)
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


def normalise_contrast(grey: np.ndarray, low_percentile: float, high_percentile: float,
                       min_contrast: float) -> np.ndarray:
    """Stretch grey levels so the paper is white and the darkest ink is black.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) in [0, 1], 1 = white.
    low_percentile, high_percentile : float
        Percentiles taken as the ink (black) and paper (white) levels.
    min_contrast : float
        If paper and ink levels differ by less than this the image is blank.

    Returns
    -------
    numpy.ndarray
        float32 (H, W) in [0, 1].

    Raises
    ------
    InputError
        When the image is uniform (no ink at all).
    """
    lo, hi = np.percentile(grey, [low_percentile, high_percentile])
    # Blank means uniform grey levels, judged on the extremes only: the percentiles of a sparse drawing
    # (one 2-px line on a 600×600 page is 0.3 % ink, below low_percentile) are both paper.
    if grey.max() - grey.min() < min_contrast:
        raise InputError("blank image: no ink found (uniform grey levels)")
    if hi - lo < min_contrast:
        # Percentiles miss very sparse ink (a few strokes on a big page): the ink is then what stands
        # min_contrast below the paper, and black is its lower quartile, where the page's percentile
        # falls on the validation splits' median drawing (1.9 % ink). Not the darkest pixel: on a scanned
        # sheet that is a noise pixel, and faint pencil stayed lighter than the threshold ("blank image").
        darker = grey[grey < hi - min_contrast]
        lo = float(np.percentile(darker, SPARSE_INK_BLACK_PERCENTILE)) if darker.size else float(grey.min())
        if hi - lo < min_contrast:
            hi = float(grey.max())
    return np.clip((grey - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)


def paper_statistics(grey: np.ndarray, max_samples: int = 1 << 20) -> tuple[float, float]:
    """Paper grey level and the spread of its grain: median and 1.4826 × median absolute deviation.

    Both are robust while ink covers well under half of the drawing (a line drawing), so they describe
    the paper, not the strokes.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) in [0, 1], 1 = white.
    max_samples : int
        Larger images are subsampled on a regular grid to about this many pixels (the statistics of
        paper grain do not need every pixel, and prep stays linear in the image).

    Returns
    -------
    level, noise : float
        Paper level and the standard deviation of its grain (0 on clean digital paper).
    """
    step = max(1, int(np.ceil(np.sqrt(grey.size / max_samples))))
    sample = np.asarray(grey[::step, ::step], np.float32).ravel()
    level = float(np.median(sample))
    return level, float(1.4826 * np.median(np.abs(sample - level)))


def narrow_band(grey: np.ndarray, threshold: float, repair_passes: int, repair_neighbours: int,
                min_component_px: int, repair_max_grey: float = 1.0) -> np.ndarray:
    """Ink mask with small-hole repair.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) in [0, 1], 1 = white.
    threshold : float
        Pixels darker than this are ink (the reference's 165/255).
    repair_passes, repair_neighbours : int
        Each pass turns background pixels with at least ``repair_neighbours`` of 8 ink neighbours
        into ink.
    min_component_px : int
        8-connected ink components smaller than this are dropped.
    repair_max_grey : float
        Pixels lighter than this (paper) are repaired only when all 8 neighbours are ink (a
        one-pixel pinhole); 1.0 lets the plain neighbour rule repair every pixel.

    Returns
    -------
    numpy.ndarray
        bool (H, W).
    """
    mask = grey < threshold
    paper = grey > repair_max_grey
    for _ in range(repair_passes):
        count = ndimage.convolve(mask.astype(np.uint8), _EIGHT, mode="constant")
        grown = mask | ((count >= repair_neighbours) & (~paper | (count == 8)))
        if np.array_equal(grown, mask):
            break
        mask = grown
    if min_component_px > 1:
        labels, n = ndimage.label(mask, structure=np.ones((3, 3)))
        if n:
            sizes = np.bincount(labels.ravel())
            keep = sizes >= min_component_px
            keep[0] = False
            mask = keep[labels]
    return mask


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
    source_shape, (sx, sy), origin = grey.shape, (0, 0), None
    sheet_corners = None
    if c.crop.enabled and (found := _photographed_sheet(grey, c, focal_35mm)) is not None:
        # Before the inversion (a desk over half the photograph made its paper level dark) and the
        # lighting (divided by its own brightness, the ground round the sheet became speckle).
        grey, (sx, sy), source_shape, note, sheet_corners = found
        origin = [sx, sy]
        notes.append(note)
    if c.invert != "never":
        level = paper_statistics(grey)[0]
        if c.invert == "always" or level < MID_GREY:
            grey = 1.0 - grey
            notes.append(f"light strokes on dark paper (paper level {level:.2f}): inverted (prep.invert)"
                         if c.invert == "auto" else "inverted (prep.invert=always)")
    if c.lighting.enabled:
        lit, variation = flatten_lighting(grey, c.lighting.window_px, c.lighting.min_range)
        if lit is not grey:
            notes.append(f"uneven lighting (the paper's brightness varies by {variation:.0%}): divided out "
                         "(prep.lighting)")
        grey = lit
    h, w = grey.shape
    pieces = None
    if c.crop.enabled and (found := _ink_box(grey, c)) is not None:
        boxes, left_out, edge = found
        what = [f"{left_out} small mark{'s' if left_out > 1 else ''} far from it"] if left_out else []
        what += ["the page's dark edge"] if edge else []
        marks = f", {' and '.join(what)} left out" if what else ""
        if len(boxes) == 1:
            (y0, y1, x0, x1), = boxes
            origin = [x0 + sx, y0 + sy]
            # The box's own contrast stretch and band: on a sheet the page's percentiles are the paper's
            # (a drawing's ink under 0.5 % of the pixels stretched its paper texture into the band).
            grey, mask, band_data = _grey_and_band(grey[y0:y1, x0:x1], c)
            notes.append(f"the drawing fills {(y1 - y0) * (x1 - x0) / (h * w):.0%} of the page: working on its "
                         f"{x1 - x0}×{y1 - y0} box at ({x0 + sx}, {y0 + sy}){marks} "
                         "(prep.crop; the curves are mapped back)")
        else:
            grey, mask, pieces, band_data = _mosaic(grey, boxes, c, (sx, sy))
            origin = None
            notes.append(f"{len(boxes)} parts far apart on the page, {sum(p[4] * p[5] for p in pieces) / (h * w):.0%} "
                         f"of it: working on their boxes side by side ({grey.shape[1]}×{grey.shape[0]})"
                         f"{marks} (prep.crop; the curves are mapped back)")
    else:
        grey, mask, band_data = _grey_and_band(grey, c)
    scale, width = 1.0, None
    if c.supersample.enabled or c.downsample.enabled:
        width = stroke_width(mask)
    if c.supersample.enabled:
        soft = soft_edges(grey, mask)
        factor, note = supersample_factor(width, soft, grey.shape, c.supersample)
        if note:
            notes.append(note)
        if factor > 1:
            scale = float(factor)
            grey = supersample(grey, factor, c.supersample.blur)
            notes.append(f"{_width_words(width, mask)}: working at {factor}x resolution "
                         "(prep.supersample; the curves are mapped back)")
    if scale == 1.0 and c.downsample.enabled:
        k = downsample_factor(width, c.downsample)
        if k > 1:
            scale = 1.0 / k
            grey = downsample(grey, k)
            notes.append(f"{_width_words(width, mask)}: working at 1/{k} resolution "
                         "(prep.downsample; the curves are mapped back)")
    if grey.size > c.max_pixels:
        raise InputError(f"drawing too large to work on: {grey.shape[1]}x{grey.shape[0]} = {grey.size} pixels "
                         f"after the crop and resampling > prep.max_pixels={c.max_pixels} (crop the image, or "
                         "scan at a lower resolution)")
    if scale != 1.0:
        # The band again at the internal resolution; specks are dropped by their area in the drawing.
        # A mosaic's pieces each with the threshold that found their band.
        windows = piece_windows({"pieces": pieces, "scale": scale}, grey.shape) or [(slice(None), slice(None))]
        mask = np.zeros(grey.shape, dtype=bool)
        for win, bd in zip(windows, band_data.get("pieces_band") or [band_data]):
            mask[win] = narrow_band(_smoothed(grey[win], bd["band_smoothing"] * scale), bd["band_threshold"],
                                    c.repair_passes, c.repair_neighbours,
                                    max(1, int(round(c.min_component_px * scale * scale))), c.repair_max_grey)
        if not mask.any():
            raise InputError("blank image: no ink left at the internal resolution (prep.downsample)")
    return Artifact(arrays={"grey": grey, "mask": mask},
                    data={"height": source_shape[0], "width": source_shape[1], "scale": scale, "origin": origin, **({"pieces": pieces} if pieces else {}),
                          "stroke_width": width,
                          "mode": mode, **({"sheet_corners": sheet_corners} if sheet_corners else {}), **band_data},
                    notes=notes)


def _grey_and_band(lit: np.ndarray, c: PrepConfig) -> tuple[np.ndarray, np.ndarray, dict]:
    """The contrast-normalised grey of the (inverted, lighting-flattened) ``lit`` and its band, with the
    paper statistics and threshold that found it (the ``data`` of the artifact)."""
    if c.contrast.enabled:
        grey = normalise_contrast(lit, c.contrast.low_percentile, c.contrast.high_percentile, c.contrast.min_contrast)
    else:
        if lit.max() - lit.min() < c.contrast.min_contrast:
            raise InputError("blank image: no ink found (uniform grey levels)")
        grey = lit.astype(np.float32)
    threshold = c.threshold
    paper, grain = paper_statistics(grey)
    smoothing, band_grey, band_paper, band_grain = 0.0, grey, paper, grain
    if c.paper_grain_sigmas > 0:
        # Grainy paper (scanned or photographed pencil): after the stretch the grain can reach the ink
        # threshold, and half the page became band. The band never starts within
        # paper_grain_sigmas grain deviations of the paper level, so grain gives isolated specks
        # (dropped with min_component_px), not a carpet; clean paper (grain 0) is unaffected.
        if c.grain_smoothing > 0 and paper - c.paper_grain_sigmas * grain < threshold:
            # That threshold keeps only the darkest grains of a faint line: a broken, 1-px band.
            # The grain is averaged out first (the grey the later stages see is left as it is).
            smoothing = c.grain_smoothing
            band_grey = _smoothed(grey, smoothing)
            band_paper, band_grain = paper_statistics(band_grey)
        threshold = min(threshold, band_paper - c.paper_grain_sigmas * band_grain)
    mask = narrow_band(band_grey, threshold, c.repair_passes, c.repair_neighbours, c.min_component_px,
                       c.repair_max_grey)
    ink = float(mask.mean())
    if ink == 0.0:
        if threshold < c.threshold:
            raise InputError(f"no ink stands out of the paper grain (paper level {paper:.2f}, grain "
                             f"{grain:.3f}; prep.paper_grain_sigmas={c.paper_grain_sigmas})")
        raise InputError("blank image: no pixel darker than prep.threshold")
    if ink > c.max_ink_fraction:
        raise InputError(f"image is {ink:.0%} ink (more than prep.max_ink_fraction): not a line drawing")
    return grey, mask, {"ink_fraction": ink, "paper_level": paper, "paper_grain": grain, "band_threshold": threshold,
                        "band_smoothing": smoothing}


class _Sheet(NamedTuple):
    """A photographed sheet as prep works on it: ``grey`` (the sheet flattened, or its box in the photo),
    ``corner`` (x, y) of ``grey``'s corner in the drawing's pixels, ``shape`` (height, width) of the
    drawing (the flattened sheet, or the photo), the console's line, and the flattened sheet's four
    corners in the photo (None when it is cut out as it lies)."""

    grey: np.ndarray
    corner: tuple[int, int]
    shape: tuple[int, int]
    note: str
    corners: list[list[float]] | None


def _photographed_sheet(grey: np.ndarray, c: PrepConfig, focal_35mm: float | None = None) -> _Sheet | None:
    """A sheet photographed on a darker ground (a desk), flattened or cut out; None when the image is no
    such photo.

    On :data:`CELL_PX` cells' mean grey, the sheet is the largest 8-connected region of cells within
    ``max(min_contrast, half the range of the cells' 5th–90th percentiles)`` of the paper (the 90th
    percentile), its holes (the drawing) filled.  It is a sheet on a ground only when

    - the ground is solid (cells surviving an opening by :data:`SHEET_SOLID_CELLS`, 48 px: strokes and a
      scan's dark page edge are narrower) along at least ``crop.sheet_rim_share`` of the image's border
      (a sheet running off the photograph on two sides leaves about half of it);
    - the paper is at least ``crop.sheet_min_contrast`` brighter than the ground (the percentiles above);
    - its edge is a step (:data:`SHEET_MIN_STEP`), not the slope of uneven lighting;
    - at least :data:`SHEET_MIN_SOLID` of the sheet's cells are solid plain paper (bright cells whose grey
      varies by at most ``contrast.min_contrast``; an inverted drawing's strokes, hatching and grain form
      no such region).

    A sheet seen whole (no cell of it on the image's border, once the ground's opening has cut off any
    lighter patches of desk joined to it by narrow bridges) whose edge is four straight sides
    (:func:`_sheet_corners`) is flattened (``crop.sheet_flatten``): its quadrilateral is mapped onto a
    rectangle of its proportions, the side nearest the photo's top on top, and the drawing is that
    rectangle (:func:`_flattened`).  Otherwise the sheet less one cell all round (its shadowed rim)
    is kept, whatever its shape (turned, in perspective, running off the photograph); the box is its
    bounding box, and the ground inside the box takes the grey of the nearest bright cell of the sheet,
    so that later steps see paper there.  Linear in the image.
    """
    cell = CELL_PX
    h, w = grey.shape
    hc, wc = h // cell, w // cell
    if hc < 8 or wc < 8:
        return None
    # Cells' means (a median took 2.3 s on a 600-dpi A4 sheet): a stroke darkens its cells, which are
    # holes of the sheet, filled, unless they touch the image's border.
    cells = grey[:hc * cell, :wc * cell].reshape(hc, cell, wc, cell)
    means = cells.mean(axis=(1, 3), dtype=np.float64)
    paper, ground = np.percentile(means, (90, 5))
    if paper - ground < c.crop.sheet_min_contrast:
        return None
    bright = means >= paper - max(c.contrast.min_contrast, 0.5 * (paper - ground))
    labels, n = ndimage.label(bright, structure=np.ones((3, 3)))
    if n == 0:
        return None
    largest = labels == 1 + np.argmax(np.bincount(labels.ravel())[1:])
    sheet = ndimage.binary_fill_holes(largest)
    solid = np.ones((SHEET_SOLID_CELLS, SHEET_SOLID_CELLS), dtype=bool)
    ground_cells = ndimage.binary_opening(~sheet, structure=solid)
    rim = np.concatenate([ground_cells[0], ground_cells[-1], ground_cells[:, 0], ground_cells[:, -1]])
    if rim.mean() < c.crop.sheet_rim_share:
        return None
    # The sheet's edge is a step: across it, a cell of the sheet is much brighter than its neighbour
    # outside (uneven lighting's slope changes the grey by a hundredth from cell to cell).
    steps = []
    for m, s in ((means, sheet), (means.T, sheet.T)):
        steps += [(m[:-1] - m[1:])[s[:-1] & ~s[1:]], (m[1:] - m[:-1])[s[1:] & ~s[:-1]]]
    steps = np.concatenate(steps)
    if not steps.size or np.median(steps) < SHEET_MIN_STEP * (paper - ground):
        return None
    # Plain paper: bright cells whose grey varies less than ink stands out (hatching's cells do not).
    # A band of cell rows at a time: a float64 square of a 600-dpi page would be 280 MB.
    spread = np.empty_like(means)
    for r in range(0, hc, 64):
        band = cells[r:r + 64]
        spread[r:r + 64] = np.sqrt(np.maximum(
            np.square(band, dtype=np.float64).mean(axis=(1, 3)) - means[r:r + 64] ** 2, 0.0))
    plain = largest & (spread <= c.contrast.min_contrast)
    if ndimage.binary_opening(plain, structure=solid).sum() < SHEET_MIN_SOLID * sheet.sum():
        return None
    if c.crop.sheet_flatten and (whole := _seen_whole(sheet, solid)) is not None:
        found = _sheet_corners(grey, whole, cell, 0.5 * (paper + np.median(means[ground_cells])))
        if found is not None:
            corners = found[0]
            flat, shape = _flattened(grey, *found, SHEET_RIM_PX, focal_35mm)
            where = ", ".join(f"({x:.0f}, {y:.0f})" for x, y in corners)
            return _Sheet(flat, (SHEET_RIM_PX, SHEET_RIM_PX), shape, corners=corners.round(2).tolist(), note=(
                f"a sheet on a darker ground (a photograph): flattened from its corners {where} to a "
                f"{shape[1]}×{shape[0]} rectangle, the curves in its pixels (prep.crop.sheet_flatten)"))
    # One cell less all round, at the image's border too: a cell there may hold a sliver of desk between
    # the sheet's edge and the border, with no ground cell beside it to show it.
    inside = ndimage.binary_erosion(sheet, structure=np.ones((3, 3)))
    rows, cols = np.flatnonzero(inside.any(axis=1)), np.flatnonzero(inside.any(axis=0))
    if len(rows) < 8 or len(cols) < 8:
        return None
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    y0, y1, x0, x1 = r0 * cell, r1 * cell, c0 * cell, c1 * cell
    box = grey[y0:y1, x0:x1]
    off = ~inside[r0:r1, c0:c1]
    line = f"a sheet on a darker ground (a photograph): working on the sheet, its {x1 - x0}×{y1 - y0} box at ({x0}, {y0})"
    if not off.any():
        return _Sheet(box, (int(x0), int(y0)), (h, w), f"{line} (prep.crop; the curves are mapped back)", None)
    # The ground inside the box (a turned sheet's corners) takes the nearest bright sheet cell's grey.
    source = inside[r0:r1, c0:c1] & bright[r0:r1, c0:c1]
    if not source.any():
        return None
    nearest = ndimage.distance_transform_edt(~source, return_distances=False, return_indices=True)
    fill = means[r0:r1, c0:c1][nearest[0], nearest[1]]
    painted = np.where(_blocks(off, cell, cell), _blocks(fill.astype(grey.dtype), cell, cell), box)
    return _Sheet(painted, (int(x0), int(y0)), (h, w), f"{line}, the ground inside the box painted as paper "
                  "(prep.crop; the curves are mapped back)", None)


def _seen_whole(sheet: np.ndarray, solid: np.ndarray) -> np.ndarray | None:
    """A photographed sheet's cells when none of them is on the image's border, else None.  Bright
    patches of a lighter desk can join the sheet by narrow bridges and run it off the photo: a sheet
    found on the border is taken again without them (the largest region the ground's opening by
    ``solid`` leaves, holes filled)."""
    def on_border(cells: np.ndarray) -> bool:
        return bool(cells[0].any() or cells[-1].any() or cells[:, 0].any() or cells[:, -1].any())

    if not on_border(sheet):
        return sheet
    labels, n = ndimage.label(ndimage.binary_opening(sheet, structure=solid), structure=np.ones((3, 3)))
    if n == 0:
        return None
    whole = ndimage.binary_fill_holes(labels == 1 + np.argmax(np.bincount(labels.ravel())[1:]))
    return None if on_border(whole) else whole


def _sheet_corners(grey: np.ndarray, sheet: np.ndarray, cell: int, level: float
                   ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]] | None:
    """The four corners (x, y) of a photographed sheet seen whole, float64 (4, 2), top-left, top-right,
    bottom-right, bottom-left, with the sheet's pixels (bool, a box of the photo) and that box's corner
    (x, y); None when its edge is not four straight sides.

    ``sheet`` is its cells (:func:`_photographed_sheet`), ``level`` the grey halfway between the paper
    and the ground.  On the grey round the sheet smoothed by 1.5 px, the sheet is the region brighter
    than ``level``, within a cell of its cells, that holds its inner cells (holes filled); its edge's points are where the grey crosses
    ``level`` between two neighbours (sub-pixel).  The largest quadrilateral on the points' convex hull
    gives the four sides; each side's line is then the one through two of the points near its middle
    80 % that most of them lie on (within 1 px; :data:`SHEET_LINE_TRIES`), fitted to those (total least
    squares), and the corners are where the lines meet.
    The sheet is flattened only when :data:`SHEET_MIN_ON_SIDES` of the edge lies on the sides and the
    corners are within :data:`SHEET_MAX_SKEW` of square.
    """
    from scipy.spatial import ConvexHull, QhullError

    # The sheet's cells and one more all round (none of them off the image: the sheet is seen whole).
    rows, cols = np.flatnonzero(sheet.any(axis=1)), np.flatnonzero(sheet.any(axis=0))
    window = np.s_[rows[0] - 1:rows[-1] + 2, cols[0] - 1:cols[-1] + 2]
    y0, y1, x0, x1 = (rows[0] - 1) * cell, (rows[-1] + 2) * cell, (cols[0] - 1) * cell, (cols[-1] + 2) * cell
    g = _smoothed(grey[y0:y1, x0:x1].astype(np.float32), 1.5)
    # Within a cell of the sheet's cells: a lighter desk's bright patches beyond are not the sheet.
    above = (g > level) & _blocks(ndimage.binary_dilation(sheet, structure=np.ones((3, 3)))[window], cell, cell)
    labels, n = ndimage.label(above)
    inner = _blocks(ndimage.binary_erosion(sheet, structure=np.ones((3, 3)))[window], cell, cell)
    held = np.bincount(labels[inner & above], minlength=n + 1)
    held[0] = 0
    if held.max() == 0:
        return None
    region = ndimage.binary_fill_holes(labels == np.argmax(held))
    # Sub-pixel edge points: between a pixel of the region and its neighbour off it, where the grey
    # crosses the level (linearly).
    points = []
    for axis, step in ((0, 1), (0, -1), (1, 1), (1, -1)):
        here, there = [slice(None), slice(None)], [slice(None), slice(None)]
        here[axis], there[axis] = ((slice(None, -1), slice(1, None)) if step == 1
                                   else (slice(1, None), slice(None, -1)))
        here, there = tuple(here), tuple(there)
        edge = region[here] & ~region[there]
        ga, gb = g[here][edge], g[there][edge]
        yy, xx = np.nonzero(edge)
        if step == -1:
            yy, xx = (yy + 1, xx) if axis == 0 else (yy, xx + 1)
        t = step * np.clip((ga - level) / np.maximum(ga - gb, 1e-6), 0.0, 1.0)
        points.append(np.c_[xx + (t if axis == 1 else 0), yy + (t if axis == 0 else 0)])
    points = np.concatenate(points) + [x0, y0]
    try:
        hull = points[ConvexHull(points).vertices]
    except QhullError:
        return None
    if len(hull) > SHEET_HULL_MAX:     # the largest quadrilateral is found among these in O(n³)
        hull = hull[np.linspace(0, len(hull), SHEET_HULL_MAX, endpoint=False).astype(int)]
    # The largest quadrilateral with corners on the hull: for each diagonal (i, k), the farthest vertex
    # on either side of it.
    d = hull[None] - hull[:, None]                                # d[i, k] = hull[k] − hull[i]
    cross = d[:, :, None, 0] * d[:, None, :, 1] - d[:, :, None, 1] * d[:, None, :, 0]
    i, k = np.unravel_index(np.argmax(cross.max(axis=2) - cross.min(axis=2)), cross.shape[:2])
    quad = hull[[i, np.argmax(cross[i, k]), k, np.argmin(cross[i, k])]]
    diagonal = float(np.hypot(x1 - x0, y1 - y0))
    tolerance = max(SHEET_SIDE_TOLERANCE, 0.005 * diagonal)
    lines = []
    rng = np.random.default_rng(0)      # the same corners for the same photo
    for side in range(4):
        a, b = quad[side], quad[(side + 1) % 4]
        length = float(np.hypot(*(b - a)))
        if length < 4 * cell:
            return None
        u = (b - a) / length
        along, off = (points - a) @ u / length, np.abs((points - a) @ np.array([-u[1], u[0]]))
        near = points[(along > 0.1) & (along < 0.9) & (off < max(4 * tolerance, 0.2 * length))]
        if len(near) < 2 * cell:
            return None
        # The line through two of them that most of them lie on (a torn corner or a finger on the edge
        # bends the hull's quadrilateral there: a least-squares start would follow it) ...
        pairs = rng.integers(0, len(near), (SHEET_LINE_TRIES, 2))
        along_pair = near[pairs[:, 1]] - near[pairs[:, 0]]
        normal = (np.c_[-along_pair[:, 1], along_pair[:, 0]]
                  / np.maximum(np.hypot(along_pair[:, 0], along_pair[:, 1]), 1e-9)[:, None])
        on = np.abs(((near[None] - near[pairs[:, 0]][:, None]) * normal[:, None]).sum(axis=2)) <= 1.0
        near = near[on[np.argmax(on.sum(axis=1))]]
        # ... then fitted to them (total least squares).
        centre = near.mean(axis=0)
        normal = np.linalg.svd(near - centre, full_matrices=False)[2][1]
        lines.append((normal, float(normal @ centre)))
    corners = np.array([np.linalg.solve(np.array([lines[s - 1][0], lines[s][0]]), [lines[s - 1][1], lines[s][1]])
                        for s in range(4)])
    # Distance of every edge point to the nearest side.
    dist = np.full(len(points), np.inf)
    for s in range(4):
        a, b = corners[s], corners[(s + 1) % 4]
        t = np.clip((points - a) @ (b - a) / float((b - a) @ (b - a)), 0.0, 1.0)
        dist = np.minimum(dist, np.hypot(*(points - a - t[:, None] * (b - a)).T))
    if np.mean(dist <= tolerance) < SHEET_MIN_ON_SIDES:
        return None
    sides = np.roll(corners, -1, axis=0) - corners
    cosines = [float(-sides[s - 1] @ sides[s]) / (np.hypot(*sides[s - 1]) * np.hypot(*sides[s])) for s in range(4)]
    if max(abs(np.degrees(np.arcsin(np.clip(cos, -1, 1)))) for cos in cosines) > SHEET_MAX_SKEW:
        return None
    # Top-left first, going round as the photo's top left → top right: the order whose first side points
    # most nearly along +x.
    if sides[0, 0] * sides[1, 1] - sides[0, 1] * sides[1, 0] < 0:
        corners = corners[::-1]
        sides = np.roll(corners, -1, axis=0) - corners
    first = int(np.argmax(sides[:, 0] / np.hypot(sides[:, 0], sides[:, 1])))
    return np.roll(corners, -first, axis=0), region, (int(x0), int(y0))


def _flattened(grey: np.ndarray, corners: np.ndarray, region: np.ndarray, corner: tuple[int, int], rim: int,
               focal_35mm: float | None = None) -> tuple[np.ndarray, tuple[int, int]]:
    """The sheet whose ``corners`` (top-left, top-right, bottom-right, bottom-left; (x, y) in the photo)
    are given, mapped onto a rectangle of the sheet's proportions (:func:`_sheet_aspect`) and of the
    quadrilateral's area (bilinear, through the homography of the four corners), less ``rim`` px all
    round; and the rectangle's (height, width).  The corners are the rectangle's outer pixel corners.
    What lies off the sheet's pixels ``region`` (a box of the photo at ``corner``) inside the rectangle
    (a torn or folded corner, a finger on the edge) takes the grey of the nearest pixel on it.
    ``focal_35mm``: the photo's EXIF focal length (:func:`_sheet_aspect`)."""
    from skimage.transform import ProjectiveTransform, warp

    aspect = _sheet_aspect(corners, grey.shape, focal_35mm)
    xs, ys = corners.T
    area = 0.5 * abs(float(xs @ np.roll(ys, -1) - ys @ np.roll(xs, -1)))
    height = int(round(np.sqrt(area / aspect)))
    width = int(round(height * aspect))
    rect = np.array([[0, 0], [width, 0], [width, height], [0, height]], np.float64) - 0.5
    # The homography from the rectangle to the photo (8 unknowns, 4 point pairs).
    rows = []
    for (u, v), (x, y) in zip(rect, corners):
        rows += [[u, v, 1, 0, 0, 0, -u * x, -v * x], [0, 0, 0, u, v, 1, -u * y, -v * y]]
    hom = np.append(np.linalg.solve(np.array(rows), corners.ravel()), 1.0).reshape(3, 3)
    # Output pixel (c, r) is the rectangle's (c + rim, r + rim).
    shift = np.array([[1.0, 0, rim], [0, 1.0, rim], [0, 0, 1.0]])
    out = (height - 2 * rim, width - 2 * rim)
    flat = warp(grey, ProjectiveTransform(matrix=hom @ shift), output_shape=out, order=1, mode="edge",
                preserve_range=True).astype(grey.dtype)
    # The sheet's pixels less 2 px (the darker rim of its edge), in the rectangle.
    inside = ndimage.binary_erosion(region, iterations=2).astype(np.float32)
    box = np.array([[1.0, 0, -corner[0]], [0, 1.0, -corner[1]], [0, 0, 1.0]])
    on = warp(inside, ProjectiveTransform(matrix=box @ hom @ shift), output_shape=out, order=1, cval=0.0) > 0.5
    if on.any() and not on.all():
        nearest = ndimage.distance_transform_edt(~on, return_distances=False, return_indices=True)
        flat = flat[nearest[0], nearest[1]]
    return flat, (height, width)


def _sheet_aspect(corners: np.ndarray, shape: tuple[int, int], focal_35mm: float | None = None) -> float:
    """Width over height of the rectangle photographed as the quadrilateral ``corners`` (top-left,
    top-right, bottom-right, bottom-left) by a pinhole camera whose centre is the photo's.

    The rectangle's proportions follow from its sides' directions in the camera's frame, which need the
    focal length: the photo's EXIF one (``focal_35mm``, in 35-mm film terms), else the one the sides'
    two vanishing points give (Zhang and He 2007, whiteboard scanning), when it is in
    :data:`SHEET_FOCAL_RANGE` and moving any corner by half a pixel moves it by under 10 % (a sheet
    seen head-on, or only leaned back, has sides parallel in the photo: its vanishing points are at
    infinity), else a phone's, :data:`SHEET_ASSUMED_FOCAL`.  Seen nearly head-on, the proportions hardly
    depend on it.
    """
    centre = np.array([0.5 * (shape[1] - 1), 0.5 * (shape[0] - 1)])
    longer = float(max(shape))

    def normals(quad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        m1, m2, m4, m3 = (np.append(p - centre, 1.0) for p in quad)     # Zhang's m1, m2 top; m3, m4 bottom
        k2 = np.cross(m1, m4) @ m3 / (np.cross(m2, m4) @ m3)
        k3 = np.cross(m1, m4) @ m2 / (np.cross(m3, m4) @ m2)
        return k2 * m2 - m1, k3 * m3 - m1

    def focal2(n2: np.ndarray, n3: np.ndarray) -> float:
        return -(n2[0] * n3[0] + n2[1] * n3[1]) / (n2[2] * n3[2]) if abs(n2[2] * n3[2]) > 1e-12 else -1.0

    n2, n3 = normals(corners)
    if focal_35mm:
        f2 = (focal_35mm / FILM_35MM_DIAGONAL * float(np.hypot(*shape))) ** 2
    else:
        f2 = focal2(n2, n3)
        low, high = SHEET_FOCAL_RANGE
        moved = [focal2(*normals(corners + np.eye(8)[i].reshape(4, 2) * step)) for i in range(8) for step in (-0.5, 0.5)]
        if not ((low * longer) ** 2 <= f2 <= (high * longer) ** 2
                and all(0.81 * f2 <= f <= 1.21 * f2 for f in moved)):
            f2 = (SHEET_ASSUMED_FOCAL * longer) ** 2
    inv = np.array([1 / f2, 1 / f2, 1.0])
    return float(np.sqrt((n2 * n2) @ inv / ((n3 * n3) @ inv)))


def _exif_focal(exif) -> float | None:
    """The focal length in 35-mm film terms (``FocalLengthIn35mmFilm``, mm) of a Pillow ``Exif``, or None."""
    try:
        value = exif.get_ifd(0x8769).get(0xA405)
        return float(value) if value and float(value) > 0 else None
    except Exception:   # EXIF is a hint: a broken block is no reason to fail
        return None


def _ink_box(lit: np.ndarray, c: PrepConfig) -> tuple[list[tuple[int, int, int, int]], int, bool] | None:
    """The box a drawing on a larger page is cut to, as ``[(y0, y1, x0, x1)]``, or the boxes of its parts
    far apart, with the count of small marks left out of them and whether the page's edge was; None
    when they would keep more than ``crop.max_area_fraction`` of the image.

    The ink here is what stands clear of the paper in the inverted, lighting-flattened ``lit``, before
    any stretch: ``min_contrast`` and ``paper_grain_sigmas`` grain deviations below the paper level (the
    page's percentiles are the paper's on a sheet, and its stretched band was noise or nothing).  Its
    components smaller than ``min_component_px`` are dropped; components no wider or taller than
    ``crop.max_speck_px`` (dust), the pixels near the sides (:data:`PAGE_EDGE_BAND_PX`) of components
    running along a side of the image for at least ``crop.page_edge_fraction`` of it (the page's dark
    edge in a scan) and clusters of ink (pieces about ``crop.cluster_gap_px`` apart at most, on a grid
    of 16-px cells) holding less than ``crop.min_cluster_share`` of the largest one's ink do not widen
    the box.  The box bounds the rest, grown by ``crop.margin_px`` and clipped to the image; when it
    keeps too much of the page, each kept cluster's box so grown (overlapping ones merged) is returned
    instead, if together they keep little enough (parts far apart: :func:`_mosaic`).  Linear in the
    page (the merge is quadratic in the clusters, which the 16-px cells and the share bound).
    """
    crop = c.crop
    paper, grain = paper_statistics(lit)
    ink = lit < paper - max(c.contrast.min_contrast, c.paper_grain_sigmas * grain)
    labels, n = ndimage.label(ink, structure=np.ones((3, 3)))
    if n == 0:
        return None
    # The page's own edge (a scanner's lid, the desk beyond the sheet, a dark scanned border) runs along
    # a side of the image; a drawing's strokes leave it at a few points.  Its pixels near the sides are
    # not ink here: a drawing whose strokes touch a dark band along the top of the scan (the banana
    # tree) is one component with it, and stays a drawing once the band is taken away.
    h, w = labels.shape
    along = np.zeros(n + 1)
    for line, length in ((labels[0], w), (labels[-1], w), (labels[:, 0], h), (labels[:, -1], h)):
        along = np.maximum(along, np.bincount(line, minlength=n + 1) / length)
    page_edge = along >= crop.page_edge_fraction
    page_edge[0] = False
    edge = None
    if page_edge.any():
        edge = np.zeros_like(ink)
        b = min(PAGE_EDGE_BAND_PX, h // 2, w // 2)
        for rows, cols in ((slice(0, b), slice(0, w)), (slice(h - b, h), slice(0, w)),
                           (slice(b, h - b), slice(0, b)), (slice(b, h - b), slice(w - b, w))):
            edge[rows, cols] = page_edge[labels[rows, cols]]
        ink &= ~edge
        labels, n = ndimage.label(ink, structure=np.ones((3, 3)))
        if n == 0:
            return None
    marks = np.bincount(labels.ravel(), minlength=n + 1)[1:] >= c.min_component_px
    # Each component's bounding box, (y0, y1, x0, x1): its span, and later whether it reaches past the box.
    bounds = np.array([(sl[0].start, sl[0].stop, sl[1].start, sl[1].stop) for sl in ndimage.find_objects(labels)])
    spans = np.maximum(bounds[:, 1] - bounds[:, 0], bounds[:, 3] - bounds[:, 2])
    strokes = marks & (spans > crop.max_speck_px)
    if not strokes.any():
        return None
    cell = CELL_PX
    hc, wc = -(-h // cell), -(-w // cell)
    padded = np.zeros((hc * cell, wc * cell), dtype=bool)
    padded[:h, :w] = np.concatenate([[False], strokes])[labels]
    counts = padded.reshape(hc, cell, wc, cell).sum(axis=(1, 3))
    # Dilating every occupied cell by `reach` joins cells up to 2·reach + 1 cells apart: about the gap.
    reach = max(0, int(round(crop.cluster_gap_px / (2 * cell))))
    near = ndimage.maximum_filter(counts > 0, size=2 * reach + 1) if reach else counts > 0
    clusters, m = ndimage.label(near, structure=np.ones((3, 3)))
    cluster_ink = ndimage.sum_labels(counts, clusters, index=np.arange(1, m + 1))
    keep = cluster_ink >= crop.min_cluster_share * cluster_ink.max()
    kept_cells = np.concatenate([[False], keep])[clusters]
    if not keep.all():
        padded &= _blocks(kept_cells, cell, cell)
    rows, cols = np.flatnonzero(padded.any(axis=1)), np.flatnonzero(padded.any(axis=0))
    margin = crop.margin_px
    y0, y1 = max(0, rows[0] - margin), min(h, rows[-1] + 1 + margin)
    x0, x1 = max(0, cols[0] - margin), min(w, cols[-1] + 1 + margin)
    boxes = [(int(y0), int(y1), int(x0), int(x1))]
    if (y1 - y0) * (x1 - x0) > crop.max_area_fraction * h * w:
        # Parts of a drawing (or several drawings) far apart on the page: each kept cluster's box,
        # overlapping ones merged, when together they keep at most max_area_fraction of the page.
        pixel_cluster = _blocks(np.where(kept_cells, clusters, 0), cell, cell) * padded
        boxes = _merged_boxes([(max(0, sl[0].start - margin), min(h, sl[0].stop + margin),
                                max(0, sl[1].start - margin), min(w, sl[1].stop + margin))
                               for sl in ndimage.find_objects(pixel_cluster) if sl is not None])
        if len(boxes) < 2 or sum((b[1] - b[0]) * (b[3] - b[2]) for b in boxes) > crop.max_area_fraction * h * w:
            return None
    # What is left out: the specks and small clusters whose bounding box reaches past every box, and
    # the page's edge where it lies outside them.
    inside = np.zeros(n, dtype=bool)
    for by0, by1, bx0, bx1 in boxes:
        inside |= ((bounds[:, 0] >= by0) & (bounds[:, 1] <= by1) & (bounds[:, 2] >= bx0) & (bounds[:, 3] <= bx1))
        if edge is not None:
            edge[by0:by1, bx0:bx1] = False
    return boxes, int(np.count_nonzero(marks & ~inside)), edge is not None and bool(edge.any())


def _merged_boxes(boxes: list[tuple[int, int, int, int]]) -> list[tuple[int, int, int, int]]:
    """``(y0, y1, x0, x1)`` boxes with each group of overlapping ones replaced by its bounding box, again
    until none overlap (a merged box can reach a third one), in the order of their top-left corners."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    b = np.asarray(boxes, np.int64).reshape(-1, 4)
    while len(b) > 1:
        overlap = ((b[:, None, 0] < b[None, :, 1]) & (b[None, :, 0] < b[:, None, 1])
                   & (b[:, None, 2] < b[None, :, 3]) & (b[None, :, 2] < b[:, None, 3]))
        n, group = connected_components(csr_matrix(overlap), directed=False)
        if n == len(b):
            break
        b = np.stack([ndimage.minimum(b[:, 0], group, np.arange(n)), ndimage.maximum(b[:, 1], group, np.arange(n)),
                      ndimage.minimum(b[:, 2], group, np.arange(n)), ndimage.maximum(b[:, 3], group, np.arange(n))],
                     axis=1).astype(np.int64)
    return sorted(tuple(int(v) for v in row) for row in b)


def _mosaic(lit: np.ndarray, boxes: list[tuple[int, int, int, int]], c: PrepConfig, offset: tuple[int, int]
            ) -> tuple[np.ndarray, np.ndarray, list[list[int]], dict]:
    """The ``boxes`` of ``lit``, each contrast-normalised and banded on its own (as if cut out by hand),
    laid side by side in rows (tallest first) with ``crop.margin_px`` of white paper between them.

    Corners sit on multiples of 12, so every downsampling factor cuts each piece into the blocks it
    would cut it into alone.  Returns the grey, the band, each piece's ``[mosaic x, mosaic y, source
    x, source y, width, height]`` (the source corner moved by ``offset``, (x, y): the corner of a
    photographed sheet ``lit`` was cut from) and the band data: the largest piece's, with every piece's in
    ``pieces_band``.  A piece with no band of its own (nothing but paper once it is stretched on its
    own) is left out; when every one is, its error is raised.
    """
    def up(v: int) -> int:
        return -(-v // 12) * 12

    found, errors = [], []
    for y0, y1, x0, x1 in boxes:
        try:
            found.append(((y0, y1, x0, x1), *_grey_and_band(lit[y0:y1, x0:x1], c)))
        except InputError as error:
            errors.append(error)
    if not found:
        raise errors[0]
    gap = c.crop.margin_px
    sizes = [g.shape for _, g, _, _ in found]
    row_limit = max(max(wd for _, wd in sizes), int(np.sqrt(sum((hh + gap) * (wd + gap) for hh, wd in sizes))))
    places: dict[int, tuple[int, int]] = {}
    x = y = row_height = 0
    for i in sorted(range(len(found)), key=lambda i: (-sizes[i][0], i)):
        hh, wd = sizes[i]
        if x > 0 and x + wd > row_limit:
            x, y, row_height = 0, up(y + row_height + gap), 0
        places[i] = (y, x)
        x, row_height = up(x + wd + gap), max(row_height, hh)
    shape = (max(places[i][0] + sizes[i][0] for i in places), max(places[i][1] + sizes[i][1] for i in places))
    grey, mask = np.ones(shape, np.float32), np.zeros(shape, bool)
    pieces = []
    for i, ((y0, y1, x0, x1), g, m, _) in enumerate(found):
        my, mx = places[i]
        grey[my:my + y1 - y0, mx:mx + x1 - x0], mask[my:my + y1 - y0, mx:mx + x1 - x0] = g, m
        pieces.append([mx, my, x0 + offset[0], y0 + offset[1], x1 - x0, y1 - y0])
    bands = [bd for _, _, _, bd in found]
    largest = max(range(len(found)), key=lambda i: found[i][2].sum())
    return grey, mask, pieces, dict(bands[largest], ink_fraction=float(mask.mean()), pieces_band=bands)


def _blocks(cells: np.ndarray, fy: int, fx: int) -> np.ndarray:
    """Each cell's value over its ``fy`` × ``fx`` block of pixels (a cell grid back at pixel size)."""
    return np.repeat(np.repeat(cells, fy, axis=0), fx, axis=1)


def _smoothed(grey: np.ndarray, sigma: float) -> np.ndarray:
    """``grey`` blurred by a Gaussian of ``sigma`` px (itself when ``sigma`` is 0)."""
    return ndimage.gaussian_filter(grey, sigma) if sigma > 0 else grey


def _width_words(width: float, mask: np.ndarray) -> str:
    """How the console names the ink's width: a filled area's skeleton is a few pixels long, so its
    area per skeleton length (thousands of px on a filled square) is no width to show a user.

    Only a width well beyond the ink's extent (twice) means a fill: a 1-px line's estimate (1.2 px)
    exceeds its 1-px extent across, and it is a stroke."""
    across = min(int(np.any(mask, axis=1).sum()), int(np.any(mask, axis=0).sum()))
    if width > 2 * across:
        return f"ink filled in areas up to {across} px across, not drawn in strokes"
    return f"strokes about {width:.1f} px wide"


def stroke_width(mask: np.ndarray) -> float:
    """Mean stroke width of a band: its area over the length of its skeleton (px, diagonal steps √2).

    Parameters
    ----------
    mask : numpy.ndarray
        bool (H, W) narrow band.

    Returns
    -------
    float
        Ink area per px of skeleton length (1.0 for a level one-pixel line, 0.71 for a diagonal one);
        0.0 without ink.
    """
    from skimage.morphology import skeletonize

    area = int(mask.sum())
    if area == 0:
        return 0.0
    rows, cols = np.nonzero(mask)
    sk = skeletonize(mask[rows.min():rows.max() + 1, cols.min():cols.max() + 1])
    # Skeleton length: 4-neighbour links count 1, diagonal steps (no 4-path beside them) √2, so that
    # a diagonal line is as wide as the same line drawn level (per pixel of skeleton it is 1/√2 wide).
    straight = int((sk[:, :-1] & sk[:, 1:]).sum() + (sk[:-1, :] & sk[1:, :]).sum())
    diagonal = int((sk[:-1, :-1] & sk[1:, 1:] & ~sk[:-1, 1:] & ~sk[1:, :-1]).sum()
                   + (sk[:-1, 1:] & sk[1:, :-1] & ~sk[:-1, :-1] & ~sk[1:, 1:]).sum())
    return area / max(1.0, straight + np.sqrt(2.0) * diagonal)


def soft_edges(grey: np.ndarray, mask: np.ndarray) -> float:
    """Share of the pixels bordering the band (8-neighbours outside it) whose grey is between 0.1 and 0.9.

    Anti-aliased and scanned strokes fade into the paper over a pixel or two (0.05–0.96 on the
    validation split and the 13 drawings); aliased ink (each pixel ink or paper) gives 0.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) contrast-normalised grey, 1 = paper.
    mask : numpy.ndarray
        bool (H, W) narrow band.

    Returns
    -------
    float
        In [0, 1]; 0.0 without ink.
    """
    ring = ndimage.binary_dilation(mask, structure=np.ones((3, 3), bool)) & ~mask
    g = np.asarray(grey)[ring]
    return float(((g > 0.1) & (g < 0.9)).mean()) if len(g) else 0.0


def supersample_factor(width: float, soft: float, shape: tuple[int, int], cfg) -> tuple[int, str | None]:
    """The internal resolution factor for strokes ``width`` px wide (1 = none) and a note when capped.

    Parameters
    ----------
    width : float
        Mean stroke width (:func:`stroke_width`).
    soft : float
        :func:`soft_edges` of the band: only aliased ink (at most ``max_soft_edges``) is supersampled.
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


def downsample_factor(width: float, cfg) -> int:
    """The integer shrink factor ``k`` for strokes ``width`` px wide (1 = none).

    Parameters
    ----------
    width : float
        Mean stroke width (:func:`stroke_width`).
    cfg : DownsampleConfig

    Returns
    -------
    int
        ``min(max_factor, floor(width / target_width))`` when ``width ≥ above_width``, else 1.
    """
    if not cfg.enabled or width < cfg.above_width:
        return 1
    return int(max(1, min(cfg.max_factor, np.floor(width / cfg.target_width + 1e-9))))


def downsample(grey: np.ndarray, factor: int) -> np.ndarray:
    """Grey image at 1/``factor`` of the resolution: the mean of each ``factor``² block.

    Parameters
    ----------
    grey : numpy.ndarray
        (H, W) in [0, 1], 1 = paper.
    factor : int
        Internal pixel ``[i, j]`` covers source ``[factor·i, factor·(i + 1))`` (so internal
        ``x = x_source / factor``); the last row and column of blocks are padded with paper.

    Returns
    -------
    numpy.ndarray
        float32 (ceil(H / factor), ceil(W / factor)).
    """
    g = np.asarray(grey, np.float32)
    h, w = g.shape
    hh, ww = -(-h // factor), -(-w // factor)
    padded = np.ones((hh * factor, ww * factor), np.float32)
    padded[:h, :w] = g
    return padded.reshape(hh, factor, ww, factor).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)
