"""stages.prep.decode: bytes of any image kind → grey over white, upright, with its notes and focal length."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from stages.errors import InputError
from stages.prep.decode import decode_image


def _encode(img: Image.Image, fmt: str = "PNG", **kw) -> bytes:
    buf = io.BytesIO()
    img.save(buf, fmt, **kw)
    return buf.getvalue()


def test_a_grey_png_is_its_levels_over_255():
    px = np.array([[0, 128, 255], [255, 64, 32]], np.uint8)
    grey, mode, notes, focal = decode_image(_encode(Image.fromarray(px, "L")), 100)
    assert grey.dtype == np.float64 and mode == "L" and notes == [] and focal is None
    np.testing.assert_array_equal(grey, px / 255.0)


def test_sixteen_bit_uses_its_whole_range():
    px = np.array([[0, 32768], [65535, 65535]], np.uint16)
    grey = decode_image(_encode(Image.fromarray(px)), 100)[0]
    np.testing.assert_allclose(grey, px / 65535.0)


def test_black_strokes_on_a_transparent_page_are_read_over_white():
    rgba = np.zeros((4, 8, 4), np.uint8)        # transparent black ...
    rgba[1:3, 2:6, 3] = 255                     # ... with an opaque black stroke
    grey, mode, _, _ = decode_image(_encode(Image.fromarray(rgba, "RGBA")), 100)
    assert mode == "RGBA"
    assert (grey[1:3, 2:6] == 0).all() and (grey[0] == 1).all()


def test_white_strokes_on_a_transparent_page_are_read_over_black():
    """White line art made for a dark background would vanish on white: it is read over black (and the
    inversion turns it into ink on paper)."""
    rgba = np.zeros((4, 8, 4), np.uint8)
    rgba[1:3, 2:6] = 255                        # opaque white stroke, the rest transparent
    grey = decode_image(_encode(Image.fromarray(rgba, "RGBA")), 100)[0]
    np.testing.assert_allclose(grey[1:3, 2:6], 1.0)
    assert (grey[0] == 0).all()


def test_the_exif_orientation_is_applied():
    px = np.full((2, 3), 255, np.uint8)
    px[0, 0] = 0                                # the stored image's top-left pixel
    exif = Image.Exif()
    exif[0x0112] = 6                            # shown turned 90° clockwise
    grey = decode_image(_encode(Image.fromarray(px, "L"), exif=exif), 100)[0]
    assert grey.shape == (3, 2)
    assert grey[0, 1] == 0 and grey.sum() == 5  # the top-left pixel is now at the top right


def test_the_focal_length_in_35mm_terms_is_read_from_exif():
    exif = Image.Exif()
    exif.get_ifd(0x8769)[0xA405] = 34
    data = _encode(Image.fromarray(np.full((8, 8), 200, np.uint8), "L"), "JPEG", exif=exif)
    assert decode_image(data, 100)[3] == 34.0


def test_of_several_pages_the_first_is_read_and_a_note_says_so():
    pages = [Image.fromarray(np.full((4, 4), v, np.uint8), "L") for v in (0, 255)]
    buf = io.BytesIO()
    pages[0].save(buf, "TIFF", save_all=True, append_images=pages[1:])
    grey, _, notes, _ = decode_image(buf.getvalue(), 100)
    assert (grey == 0).all() and notes == ["2 pages (frames) in the file: the first is vectorised"]


@pytest.mark.parametrize("data, limit, message", [(b"", 100, "empty file"), (b"not an image", 100, "not an image"),
                                                  (None, 99, "image too large")])
def test_bad_input_is_one_clear_error(data, limit, message):
    data = data if data is not None else _encode(Image.fromarray(np.zeros((10, 10), np.uint8), "L"))
    with pytest.raises(InputError, match=message):
        decode_image(data, limit)
