"""Decoding: the file's bytes → grey levels in [0, 1] over white, upright as a viewer shows them.

Any Pillow format (PNG, JPEG, TIFF, BMP, WebP, AVIF; HEIC through the optional ``pillow-heif``), any
mode (palette, 16-bit, float, with alpha) comes out as one float64 grey, 1 = paper white; an EXIF
orientation is applied, the first page of a multi-page file is read, and the photo's focal length (EXIF)
is kept for a photographed sheet's proportions (:mod:`~stages.prep.sheet_flatten`).  Bad input is one
clear :class:`~stages.errors.InputError` line: an empty file, no image, a corrupt one, or more pixels
than ``prep.max_page_pixels`` (checked before the pixel data are decoded).

Choices made on purpose
-----------------------
* **Alpha** is composited over white (the authors' detector ignores alpha, which their issue #7
  traces to blank predictions on transparent PNGs) — over black when the opaque strokes on a mostly
  transparent page are lighter than mid-grey (white line art for a dark background), which the
  inversion (:mod:`~stages.prep.invert`) then turns into ink on paper.
"""

from __future__ import annotations

import io
import warnings

import numpy as np

from stages.errors import InputError
from stages.prep.invert import MID_GREY


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
        photographed sheet's proportions (:func:`~stages.prep.sheet_flatten.sheet_aspect`); None when the
        file has none.

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


def _exif_focal(exif) -> float | None:
    """The focal length in 35-mm film terms (``FocalLengthIn35mmFilm``, mm) of a Pillow ``Exif``, or None."""
    try:
        value = exif.get_ifd(0x8769).get(0xA405)
        return float(value) if value and float(value) > 0 else None
    except Exception:   # EXIF is a hint: a broken block is no reason to fail
        return None
