"""prep: every input kind decodes to the same drawing; every bad input is one clear error."""

from __future__ import annotations

import io

import numpy as np
import pytest
import yaml
from PIL import Image, ImageDraw
from scipy import ndimage

from pipeline.engine.config import CONF_DIR as REPO_CONF
from stages import prep, synthetic
from stages.errors import InputError

from photos import photographed

CFG = yaml.safe_load((REPO_CONF / "prep" / "default.yaml").read_text())


def _encode(img: Image.Image, fmt: str, **kw) -> bytes:
    buf = io.BytesIO()
    img.save(buf, fmt, **kw)
    return buf.getvalue()


@pytest.fixture(scope="module")
def drawing():
    return synthetic.line(size=48, angle=30, width=4)


def _variants(grey: np.ndarray) -> dict[str, bytes]:
    g8 = np.round(grey * 255).astype(np.uint8)
    ink = 255 - g8
    rgba = np.zeros(grey.shape + (4,), np.uint8)  # black strokes on a transparent background
    rgba[..., 3] = ink
    g16 = (grey.astype(np.float64) * 65535).round().astype(np.uint16)
    return {
        "png-grey": _encode(Image.fromarray(g8, "L"), "PNG"),
        "png-rgb": _encode(Image.fromarray(np.stack([g8] * 3, -1), "RGB"), "PNG"),
        "png-palette": _encode(Image.fromarray(g8, "L").convert("P"), "PNG"),
        "png-rgba": _encode(Image.fromarray(rgba, "RGBA"), "PNG"),
        "png-grey-alpha": _encode(Image.fromarray(np.stack([np.zeros_like(g8), ink], -1), "LA"), "PNG"),
        "png-16bit": _encode(Image.fromarray(g16), "PNG"),
        "tiff-16bit": _encode(Image.fromarray(g16), "TIFF"),
        "tiff-8bit": _encode(Image.fromarray(g8, "L"), "TIFF"),
        "jpeg": _encode(Image.fromarray(g8, "L"), "JPEG", quality=95),
        "bmp": _encode(Image.fromarray(np.stack([g8] * 3, -1), "RGB"), "BMP"),
    }


@pytest.mark.parametrize("kind", list(_variants(np.ones((2, 2), np.float32))))
def test_every_input_kind_gives_the_same_band(drawing, kind):
    data = _variants(drawing.grey)[kind]
    ref = prep.run(CFG, _variants(drawing.grey)["png-grey"])
    out = prep.run(CFG, data)
    assert out["grey"].dtype == np.float32 and out["grey"].shape == drawing.grey.shape
    assert out["mask"].dtype == bool
    # Same ink everywhere (JPEG may move an edge pixel or two).
    assert np.sum(out["mask"] != ref["mask"]) <= (6 if kind == "jpeg" else 0)
    assert out["mask"].sum() > 100


@pytest.mark.parametrize("fmt", ["HEIF", "AVIF", "WEBP"])
def test_a_phones_heic_and_avif_and_webp_give_the_band_of_the_png(drawing, fmt):
    """A phone's HEIC photo (through the optional pillow-heif), AVIF and WebP: the band of the same
    drawing as a PNG, but for an edge pixel or two of the lossy codecs."""
    if fmt == "HEIF":
        pillow_heif = pytest.importorskip("pillow_heif", reason="pillow-heif is not installed (the `heic` extra)")
        pillow_heif.register_heif_opener()
    g8 = np.round(drawing.grey * 255).astype(np.uint8)
    data = _encode(Image.fromarray(np.stack([g8] * 3, -1), "RGB"), fmt, quality=95)
    ref = prep.run(CFG, _variants(drawing.grey)["png-grey"])
    out = prep.run(CFG, data)
    assert np.sum(out["mask"] != ref["mask"]) <= 6


def test_a_heic_photo_without_pillow_heif_is_one_line_saying_what_to_install(monkeypatch):
    """Pillow reads no HEIC: without pillow-heif the error names it (it said "not an image")."""
    import sys

    heic = b"\x00\x00\x00\x1cftypheic" + bytes(100)
    monkeypatch.setitem(sys.modules, "pillow_heif", None)      # as if not installed
    with pytest.raises(InputError, match="HEIC/HEIF photo: reading it needs the optional pillow-heif"):
        prep.run(CFG, heic)


def test_alpha_is_composited_over_white(drawing):
    out = prep.run(CFG, _variants(drawing.grey)["png-rgba"])
    assert out["grey"][0, 0] == pytest.approx(1.0)  # transparent corner reads as paper
    assert out.data["mode"] == "RGBA"


def test_white_line_art_on_a_transparent_page_is_read_as_ink(drawing):
    """White strokes on a transparent page (line art for a dark background) would vanish over white:
    they give the band of the same strokes drawn black, with the inversion said."""
    g8 = np.round(drawing.grey * 255).astype(np.uint8)
    white_art = np.zeros(g8.shape + (4,), np.uint8)
    white_art[..., :3] = 255
    white_art[..., 3] = 255 - g8
    out = prep.run(CFG, _encode(Image.fromarray(white_art, "RGBA"), "PNG"))
    ref = prep.run(CFG, _variants(drawing.grey)["png-rgba"])
    np.testing.assert_array_equal(out.arrays["mask"], ref.arrays["mask"])
    assert any("inverted" in n for n in out.notes) and not any("inverted" in n for n in ref.notes)


def test_faint_pencil_is_stretched_to_the_same_band(drawing):
    faint = 1 - 0.3 * (1 - drawing.grey)  # light grey strokes, never darker than 0.7
    ref = prep.run(CFG, _variants(drawing.grey)["png-grey"])
    out = prep.run(CFG, _variants(faint)["png-grey"])
    assert np.sum(out["mask"] != ref["mask"]) <= 4


def test_pinhole_is_repaired_and_real_hole_kept():
    grey = np.ones((40, 40), np.float32)
    grey[10:30, 10:30] = 0.0
    grey[20, 20] = 1.0  # pinhole inside a blob
    grey[14:18, 22:27] = 1.0  # real hole (20 pixels)
    mask = prep.narrow_band(grey, CFG["threshold"], 3, 6, 1, CFG["repair_max_grey"])
    assert mask[20, 20]
    assert not mask[15, 24]


def _teardrop_loop() -> np.ndarray:
    """A thin closed loop (an eye drawn as a teardrop) with a one-pixel-wide paper slit inside."""
    grey = np.ones((24, 40), np.float32)
    grey[8:14, 6:34] = 0.0
    grey[11, 9:31] = 1.0  # the slit: white paper, ink above and below
    return grey


def test_paper_slit_inside_a_narrow_loop_is_kept():
    grey = _teardrop_loop()
    mask = prep.narrow_band(grey, CFG["threshold"], 3, 6, 1, CFG["repair_max_grey"])
    assert not mask[11, 9:31].any()
    # the plain neighbour rule (repair_max_grey = 1) fills the slit: the loop becomes a blob
    assert prep.narrow_band(grey, CFG["threshold"], 3, 6, 1, 1.0)[11, 9:31].all()


def test_grey_pencil_pinholes_in_a_slit_are_still_repaired():
    grey = _teardrop_loop()
    grey[11, 9:31] = 0.75  # light pencil texture, lighter than the ink threshold but not paper
    assert prep.narrow_band(grey, CFG["threshold"], 3, 6, 1, CFG["repair_max_grey"])[11, 9:31].all()


@pytest.mark.parametrize("data, message", [
    (b"", "empty file"),
    (b"this is not an image at all", "not an image"),
    (b"\x89PNG\r\n\x1a\n" + b"\x00" * 40, "image"),
])
def test_bad_bytes_give_one_clear_error(data, message):
    with pytest.raises(InputError, match=message) as info:
        prep.run(CFG, data)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("value, message", [(255, "blank"), (0, "ink")])
def test_all_white_and_all_black(value, message):
    data = _encode(Image.fromarray(np.full((32, 32), value, np.uint8), "L"), "PNG")
    with pytest.raises(InputError, match=message):
        prep.run(CFG, data)


def test_light_strokes_on_dark_paper_are_inverted_and_said(drawing):
    """Chalk on a blackboard, a negative: the same band as the drawing on white, with a note; with
    ``invert: never`` the dark page is read as it is (no stroke stands out of it)."""
    g8 = np.round(drawing.grey * 255).astype(np.uint8)
    normal = prep.run(CFG, _encode(Image.fromarray(g8, "L"), "PNG"))
    negative = _encode(Image.fromarray(255 - g8, "L"), "PNG")
    inverted = prep.run(CFG, negative)
    np.testing.assert_array_equal(inverted.arrays["mask"], normal.arrays["mask"])
    assert any("light strokes on dark paper" in n and "inverted" in n for n in inverted.notes)
    assert not any("invert" in n for n in normal.notes)
    forced = prep.run({**CFG, "invert": "always"}, negative)
    np.testing.assert_array_equal(forced.arrays["mask"], normal.arrays["mask"])
    with pytest.raises(InputError):
        prep.run({**CFG, "invert": "never"}, negative)
    with pytest.raises(InputError, match="prep.invert"):
        prep.run({**CFG, "invert": "yes"}, negative)


def test_huge_image_is_refused_before_decoding():
    data = _encode(Image.fromarray(np.full((400, 500), 255, np.uint8), "L"), "PNG")
    with pytest.raises(InputError, match="too large.*prep.max_page_pixels"):
        prep.run(dict(CFG, max_page_pixels=100_000), data)


def test_a_page_over_max_pixels_is_worked_on_when_its_drawing_fits_after_the_crop():
    """``max_pixels`` bounds what the later stages work on, after the crop and resampling (a sketch
    on an A4 sheet scanned at 600 dpi is 35 Mpx, its box a few); ``max_page_pixels`` bounds decoding.
    A drawing that fills a page too large for ``max_pixels`` is refused in one line naming it."""
    sheet = _encode(_sheet_with_drawing(), "PNG")                       # 1400×1000, a 240-px drawing
    art = prep.run(dict(CFG, max_pixels=200_000), sheet)
    assert art.data["origin"] is not None and art.arrays["grey"].size <= 200_000
    full = _encode(_sheet_with_drawing(size=(300, 280), at=(20, 20)), "PNG")   # fills its page
    with pytest.raises(InputError, match=r"too large to work on: 300x280 = 84000 pixels .*prep.max_pixels=50000"):
        prep.run(dict(CFG, max_pixels=50_000), full)


def _sparse_page(size: int, rows: list[int]) -> bytes:
    """Black 2-px horizontal lines on a white page: well below 0.5 % ink."""
    g = np.full((size, size), 255, np.uint8)
    for r in rows:
        g[r:r + 2, size // 10: size - size // 10] = 0
    return _encode(Image.fromarray(g, "L"), "PNG")


@pytest.mark.parametrize("size, rows", [(600, [300]), (1000, [200, 500, 800])])
def test_sparse_drawing_is_not_blank(size, rows):
    """A drawing of one line is a drawing: the blank check must not fire before the sparse-ink fallback."""
    art = prep.run(CFG, _sparse_page(size, rows))
    assert art.arrays["mask"].sum() == pytest.approx(len(rows) * 2 * (size - 2 * (size // 10)), rel=0.05)
    assert art.arrays["grey"].min() == 0.0 and art.arrays["grey"].max() == 1.0


def test_a_drawing_on_a_larger_page_is_cropped_to_its_ink_and_says_so():
    """A sketch on a scanned sheet: the grey and band are cut to the ink's box grown by margin_px, and
    ``origin`` says where it was; a drawing that fills its image, or crop disabled, keeps the page."""
    alone = prep.run(CFG, synthetic.tee(size=64).png_bytes())
    tee = np.asarray(Image.open(io.BytesIO(synthetic.tee(size=64).png_bytes())).convert("L"))
    page = np.full((600, 500), 255, np.uint8)
    page[300:364, 100:164] = tee
    art = prep.run(CFG, _encode(Image.fromarray(page, "L"), "PNG"))
    rows, cols = np.nonzero(alone.arrays["mask"])
    m = CFG["crop"]["margin_px"]
    x0, y0 = 100 + cols.min() - m, 300 + rows.min() - m
    assert art.data["origin"] == [x0, y0] and (art.data["height"], art.data["width"]) == (600, 500)
    assert art.arrays["mask"].shape == (rows.max() - rows.min() + 1 + 2 * m, cols.max() - cols.min() + 1 + 2 * m)
    np.testing.assert_array_equal(np.nonzero(art.arrays["mask"])[0] + y0, rows + 300)
    assert any("prep.crop" in n for n in art.notes)
    assert alone.data["origin"] is None and alone.arrays["mask"].shape == (64, 64)
    off = prep.run(dict(CFG, crop=dict(CFG["crop"], enabled=False)), _encode(Image.fromarray(page, "L"), "PNG"))
    assert off.data["origin"] is None and off.arrays["mask"].shape == (600, 500)


def test_pillow_decompression_limit_names_the_limit_that_applies(monkeypatch):
    """Over Pillow's own pixel limit the message names it, not prep.max_pixels (raising that would not help)."""
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)
    data = _encode(Image.fromarray(np.full((100, 100), 255, np.uint8), "L"), "PNG")  # 10000 > 2 × 1000
    with pytest.raises(InputError, match="Pillow's decompression-bomb limit of 1000 pixels") as info:
        prep.run(dict(CFG, max_page_pixels=10**9), data)
    assert "\n" not in str(info.value)


def _grainy_pencil(grain: float) -> np.ndarray:
    """A faint 3-px square outline (0.23 below the paper) on 200×200 paper with Gaussian grain."""
    ink = np.zeros((200, 200))
    ink[40:160, 40:160] = 1.0
    ink[43:157, 43:157] = 0.0
    rng = np.random.default_rng(3)
    return np.clip(0.86 - 0.23 * ink + rng.normal(0, grain, ink.shape), 0, 1)


def test_paper_grain_does_not_become_band():
    clean = prep.run(CFG, _variants(_grainy_pencil(0.0).astype(np.float32))["png-grey"])["mask"]
    out = prep.run(CFG, _variants(_grainy_pencil(0.05).astype(np.float32))["png-grey"])
    # Without the grain rule (paper_grain_sigmas 0) half of this page was band.
    assert out["mask"].mean() < 2 * clean.mean()
    assert (out["mask"] & clean).sum() > 0.5 * clean.sum()     # the line is still there
    assert out.data["paper_grain"] > 0.1 and out.data["band_threshold"] < CFG["threshold"]


def test_clean_paper_keeps_the_configured_threshold(drawing):
    out = prep.run(CFG, _variants(drawing.grey)["png-grey"])
    assert out.data["paper_grain"] == 0.0 and out.data["band_threshold"] == CFG["threshold"]


def test_a_faint_line_on_grainy_paper_stays_one_band():
    """Where the grain lowers the threshold, the band is found on the grey smoothed by
    ``grain_smoothing``: a faint 3-px outline on heavy grain is one component about 3 px wide, not
    the 1-px broken chain of its darkest grains (a 3-stroke pencil drawing of the validation split
    came out as 109 curves)."""
    from scipy import ndimage

    png = _variants(_grainy_pencil(0.07).astype(np.float32))["png-grey"]
    out = prep.run(CFG, png)
    assert CFG["grain_smoothing"] > 0 and out.data["band_smoothing"] == CFG["grain_smoothing"]
    assert ndimage.label(out["mask"], np.ones((3, 3)))[1] == 1
    assert 2.5 < out.data["stroke_width"] < 3.5
    assert out["grey"].std() > 0.05                      # the grey itself is not smoothed
    broken = prep.run({**CFG, "grain_smoothing": 0.0}, png)
    assert ndimage.label(broken["mask"], np.ones((3, 3)))[1] > 10 and broken.data["band_smoothing"] == 0.0
    # clean paper: no smoothing, the configured threshold
    assert prep.run(CFG, _variants(_grainy_pencil(0.0).astype(np.float32))["png-grey"]).data["band_smoothing"] == 0.0


def test_grain_rule_off_is_the_plain_threshold():
    # (supersampling off: the grain specks read as thin strokes, and its blur would hide the failure)
    cfg = {**CFG, "paper_grain_sigmas": 0, "supersample": {**CFG["supersample"], "enabled": False}}
    out = prep.run(cfg, _variants(_grainy_pencil(0.05).astype(np.float32))["png-grey"])
    assert out["mask"].mean() > 0.2        # the failure the rule exists for


def _aliased_ellipse(width: int = 1) -> bytes:
    """A 1-px aliased grey ellipse (no anti-aliasing: diagonal pixel steps) and a line, as PNG."""
    img = Image.new("L", (240, 200), 255)
    d = ImageDraw.Draw(img)
    d.ellipse([20, 30, 220, 170], outline=110, width=width)
    d.line([(60, 100), (180, 110)], fill=110, width=width)
    return _encode(img, "PNG")


def test_thin_aliased_strokes_are_supersampled_pixel_aligned():
    out = prep.run(CFG, _aliased_ellipse())
    assert 0.7 < out.data["stroke_width"] < 1.05          # 1-px ink, partly diagonal (1/√2 per px)
    s = out.data["scale"]
    assert s == 2 and out["grey"].shape == (400, 480) and out["mask"].shape == (400, 480)
    assert (out.data["height"], out.data["width"]) == (200, 240)      # the drawing's size, for the SVG
    assert any("2x resolution" in n for n in out.notes)
    # Pixel-aligned: source pixel (x=120, y=30), on the ellipse's top, covers internal [240, 242) x [60, 62).
    assert out["mask"][60:62, 240:242].all()
    # The band is several internal pixels wide and one 8-connected piece per stroke, not a staircase.
    from scipy import ndimage
    assert ndimage.label(out["mask"], structure=np.ones((3, 3)))[1] == 2
    off = prep.run({**CFG, "supersample": {**CFG["supersample"], "enabled": False}}, _aliased_ellipse())
    assert off.data["scale"] == 1 and off["grey"].shape == (200, 240)


def test_normal_strokes_are_not_supersampled(drawing):
    out = prep.run(CFG, _variants(drawing.grey)["png-grey"])
    assert out.data["scale"] == 1 and out.data["stroke_width"] >= CFG["supersample"]["below_width"]
    assert out["grey"].shape == drawing.grey.shape and not out.notes


def test_supersampling_is_capped_by_max_pixels_and_says_so():
    cfg = {**CFG, "supersample": {**CFG["supersample"], "max_pixels": 100_000}}   # 4 x 48,000 px is more
    out = prep.run(cfg, _aliased_ellipse())
    assert out.data["scale"] == 1 and out["grey"].shape == (200, 240)
    assert any("max_pixels" in n and "allows 1x" in n for n in out.notes)


def test_anti_aliased_thin_strokes_are_not_supersampled():
    """The same 1.5-px ellipse drawn anti-aliased fades into the paper: the field resolves it (and on
    the validation split's thin anti-aliased drawings supersampling lowered the junction F1)."""
    big = Image.new("L", (960, 800), 255)
    ImageDraw.Draw(big).ellipse([80, 120, 880, 680], outline=0, width=6)
    data = _encode(big.resize((240, 200), Image.LANCZOS), "PNG")
    out = prep.run(CFG, data)
    assert out.data["stroke_width"] < CFG["supersample"]["below_width"]
    assert out.data["scale"] == 1 and out["grey"].shape == (200, 240)
    assert prep.soft_edges(out["grey"], out["mask"]) > CFG["supersample"]["max_soft_edges"]


def _wide_ellipse(size: tuple[int, int] = (1001, 803), width: int = 16) -> bytes:
    """A ``width``-px anti-aliased ellipse and line on an odd-sized page (a high-resolution scan)."""
    w, h = size
    big = Image.new("L", (2 * w, 2 * h), 255)
    d = ImageDraw.Draw(big)
    d.ellipse([200, 240, 2 * w - 200, 2 * h - 240], outline=0, width=2 * width)
    d.line([(600, h), (2 * w - 600, h + 100)], fill=0, width=2 * width)
    return _encode(big.resize((w, h), Image.LANCZOS), "PNG")


def test_wide_strokes_are_downsampled_pixel_aligned():
    out = prep.run(CFG, _wide_ellipse())
    width = out.data["stroke_width"]
    assert 14 < width < 19
    k = int(width // CFG["downsample"]["target_width"])
    assert k == 4 and out.data["scale"] == 0.25
    # ceil(803 / 4) x ceil(1001 / 4): the last blocks padded with paper, no ink lost
    assert out["grey"].shape == (201, 251) and out["mask"].shape == (201, 251)
    assert (out.data["height"], out.data["width"]) == (803, 1001)
    assert any("1/4 resolution" in n for n in out.notes)
    # Block means: internal pixel [i, j] is the mean of source [4i, 4i + 4) x [4j, 4j + 4).
    src = prep.run({**CFG, "downsample": {**CFG["downsample"], "enabled": False}}, _wide_ellipse())
    assert src.data["scale"] == 1 and src["grey"].shape == (803, 1001)
    np.testing.assert_allclose(out["grey"][50, 60], src["grey"][200:204, 240:244].mean(), atol=1e-5)
    np.testing.assert_allclose(out["grey"][-1, -1], (src["grey"][800:803, 1000].sum() + 13) / 16, atol=1e-5)
    # The band keeps the strokes: about a quarter of their width, each one piece.
    from scipy import ndimage
    assert ndimage.label(out["mask"], structure=np.ones((3, 3)))[1] == 2     # the ellipse, the line inside
    assert 3 < prep.stroke_width(out["mask"]) < 5.5


def test_a_filled_area_is_not_called_a_stroke_thousands_of_pixels_wide():
    """A filled square's skeleton is a few pixels long, so area over skeleton length is no width: the
    console says filled areas and their size instead (it said "strokes about 37279.2 px wide")."""
    page = Image.new("L", (500, 500), 255)
    ImageDraw.Draw(page).rectangle([100, 100, 399, 399], fill=0)
    out = prep.run(CFG, _encode(page, "PNG"))
    assert out.data["scale"] < 1 and out.data["stroke_width"] > 300     # the estimate itself is unchanged
    assert len(out.notes) == 1 and "px wide" not in out.notes[0]
    assert "filled in areas up to 300 px across" in out.notes[0]
    assert prep.run(CFG, _wide_ellipse()).notes[0].startswith("strokes about 15.2 px wide")   # strokes stay strokes
    # A 1-px line alone in a 3-px strip: its width estimate (1.2 px) exceeds its 1-px extent, still a stroke.
    strip = np.full((3, 1000), 255, np.uint8)
    strip[1, 100:900] = 0
    note = prep.run(CFG, _encode(Image.fromarray(strip), "PNG")).notes[0]
    assert note.startswith("strokes about 1.") and "filled" not in note


def _pencil_page(shadow: float) -> np.ndarray:
    """Grey strokes (a loop, a zigzag, a line) on 0.92 paper, darkened by ``shadow`` towards one corner."""
    page = Image.new("L", (420, 360), 235)
    d = ImageDraw.Draw(page)
    d.ellipse([40, 40, 200, 170], outline=150, width=3)
    d.line([(230, 60), (280, 160), (330, 60), (380, 160)], fill=150, width=3)
    d.line([(50, 280), (380, 240)], fill=150, width=3)
    a = np.asarray(page, np.float64) / 255.0
    y, x = np.mgrid[0:360, 0:420]
    return a * (1.0 - shadow * (x / 420.0) * (0.4 + 0.6 * y / 360.0))


def test_even_lighting_is_left_exactly_as_it_is():
    grey = _pencil_page(0.0)
    out, variation = prep.flatten_lighting(grey, 81, 0.15)
    assert out is grey and variation < 0.02


@pytest.mark.parametrize("shape", [(20, 10000), (10000, 7), (1, 1), (3, 600)])
def test_the_lighting_estimate_takes_strips_and_specks(shape):
    """A strip thinner than the shrinking block (a 10000×20 scan of one line) once failed to reshape."""
    grey = np.full(shape, 0.9)
    grey[shape[0] // 2, : shape[1] // 2] = 0.2
    out, variation = prep.flatten_lighting(grey, 81, 0.12)
    assert out is grey and variation < 0.12
    shaded = grey * np.linspace(1.0, 0.5, shape[1])[None, :]
    out, variation = prep.flatten_lighting(shaded, 81, 0.12)
    assert out.shape == shape and np.isfinite(out).all()


def test_a_black_fill_wider_than_the_window_is_ink_not_shade():
    """A filled disc 200 px across (wider than the 81-px window) survives the closing; it is darker
    than paper in any shade, so it is neither counted as uneven light nor lightened under a shadow."""
    grey = _pencil_page(0.0)
    y, x = np.mgrid[0:360, 0:420]
    disc = np.hypot(x - 300, y - 250) < 100
    grey[disc] = 0.1
    out, variation = prep.flatten_lighting(grey, 81, 0.15)
    assert out is grey and variation < 0.02
    shade = 1.0 - 0.4 * (x / 420.0) * (0.4 + 0.6 * y / 360.0)
    out, variation = prep.flatten_lighting(grey * shade, 81, 0.15)
    assert variation > 0.2 and out[disc].max() < 0.35      # still ink after the division


def _page_mask(art) -> np.ndarray:
    """A prep's band on the whole drawing (a cropped prep's box put back where ``origin`` says, a
    mosaic's pieces where theirs do)."""
    mask = np.zeros((art.data["height"], art.data["width"]), bool)
    x0, y0 = art.data["origin"] or (0, 0)
    for mx, my, sx, sy, w, h in art.data.get("pieces") or [[0, 0, x0, y0, *art["mask"].shape[::-1]]]:
        mask[sy:sy + h, sx:sx + w] = art["mask"][my:my + h, mx:mx + w]
    return mask


def test_a_shadow_is_divided_out_and_the_strokes_are_found_as_without_it():
    """A pencil drawing under a 40 % shadow (a photographed sketch): without the lighting rule the
    threshold finds no ink, or the shadow; with it, the band is the one of the evenly lit drawing."""
    even = prep.run(CFG, _encode(Image.fromarray((_pencil_page(0.0) * 255).astype(np.uint8)), "PNG"))
    png = _encode(Image.fromarray((_pencil_page(0.4) * 255).astype(np.uint8)), "PNG")
    flat, variation = prep.flatten_lighting(_pencil_page(0.4), 81, 0.15)
    assert variation > 0.25
    paper = _pencil_page(0.0) > 0.85
    assert np.ptp(np.percentile(flat[paper], [5, 95])) < 0.03          # the paper is flat again
    shadowed = prep.run(CFG, png)
    assert any("uneven lighting" in n for n in shadowed.notes)
    # the same ink pixels as the evenly lit drawing, give or take its edges
    agree = (shadowed["mask"] == even["mask"]).mean()
    assert agree > 0.995 and abs(int(shadowed["mask"].sum()) - int(even["mask"].sum())) < 0.1 * even["mask"].sum()
    off = {**CFG, "lighting": {**CFG["lighting"], "enabled": False}}
    try:
        unflattened = _page_mask(prep.run(off, png))    # its few dark specks are cropped to (prep.crop)
        assert (unflattened == even["mask"]).mean() < agree                # the rule is what made them agree
    except InputError as exc:                                               # or nothing was found at all
        assert "no ink" in str(exc)


def test_strokes_below_the_downsampling_width_keep_the_resolution():
    out = prep.run(CFG, _wide_ellipse(width=5))
    assert out.data["stroke_width"] < CFG["downsample"]["above_width"]
    assert out.data["scale"] == 1 and out["grey"].shape == (803, 1001) and not out.notes
    from stages.config import from_section
    c = from_section(prep.DownsampleConfig, CFG["downsample"], "prep.downsample")
    # k = floor(width / target_width), from above_width on, at most max_factor
    assert [prep.downsample_factor(w, c) for w in (6.9, 7.0, 10.4, 10.5, 15.0, 100.0)] == [1, 2, 2, 3, 4, 4]


def _sheet_with_drawing(size=(1400, 1000), at=(300, 200), level=0, grain=0.0, seed=0):
    """A white sheet (with paper grain of ``grain`` grey levels) and a 240×240 drawing of grey ``level``
    (a square and a circle, 3 px strokes: ~4,000 ink pixels) whose corner is at ``at`` (x, y)."""
    rng = np.random.default_rng(seed)
    page = np.clip(rng.normal(250 if grain else 255, grain, size[::-1]), 0, 255) if grain else np.full(size[::-1], 255.0)
    img = Image.fromarray(page.astype(np.uint8), "L")
    d = ImageDraw.Draw(img)
    x, y = at
    d.rectangle([x + 20, y + 20, x + 220, y + 160], outline=level, width=3)
    d.ellipse([x + 60, y + 100, x + 200, y + 230], outline=level, width=3)
    return img


def test_dust_far_from_the_drawing_does_not_keep_the_whole_sheet():
    """Scanner dust on a sheet: specks no larger than ``crop.max_speck_px`` and clusters with under
    ``crop.min_cluster_share`` of the drawing's ink do not widen the crop's box, and the note counts
    them; with both rules off (stop 43's box) the specks spread the box over the sheet and nothing is
    cropped."""
    clean = prep.run(CFG, _encode(_sheet_with_drawing(), "PNG"))
    dusty = _sheet_with_drawing()
    d = ImageDraw.Draw(dusty)
    for cx, cy in [(50, 60), (1300, 80), (1250, 900), (80, 950)]:
        d.ellipse([cx - 5, cy - 5, cx + 5, cy + 5], fill=0)   # 11-px specks
    d.line([(1000, 700), (1030, 722)], fill=0, width=1)          # a 37-px hair: ~1 % of the drawing's ink
    art = prep.run(CFG, _encode(dusty, "PNG"))
    assert clean.data["origin"] is not None and art.data["origin"] == clean.data["origin"]
    np.testing.assert_array_equal(art.arrays["mask"], clean.arrays["mask"])
    assert any("5 small marks far from it left out" in n for n in art.notes), art.notes
    # With both rules off (stop 43's box) the specks spread the box over the sheet: each is then a piece
    # of a mosaic (stop 44 worked on the whole sheet).
    old = dict(CFG, crop=dict(CFG["crop"], max_speck_px=0, min_cluster_share=0.0))
    assert len(prep.run(old, _encode(dusty, "PNG")).data["pieces"]) == 6


def test_the_dark_edge_of_a_scanned_page_does_not_keep_the_whole_sheet():
    """A scan's dark page edge (a 14-px strip along 80 % of the left side, darkest at the border) runs
    along ``crop.page_edge_fraction`` of a side or more: it is left out of the box like dust, and said."""
    clean = prep.run(CFG, _encode(_sheet_with_drawing(), "PNG"))
    px = np.asarray(_sheet_with_drawing()).copy()
    px[100:900, :14] = np.linspace(40, 200, 14).astype(np.uint8)[None, :]
    art = prep.run(CFG, _encode(Image.fromarray(px, "L"), "PNG"))
    assert clean.data["origin"] is not None and art.data["origin"] == clean.data["origin"]
    np.testing.assert_array_equal(art.arrays["mask"], clean.arrays["mask"])
    assert any("the page's dark edge left out" in n for n in art.notes), art.notes
    kept = prep.run(dict(CFG, crop=dict(CFG["crop"], page_edge_fraction=0.9)), _encode(Image.fromarray(px, "L"), "PNG"))
    assert kept.data["origin"] is None and [p[2] for p in kept.data["pieces"]] == [0, 288]  # the edge, the drawing


def test_a_drawing_touching_a_dark_band_along_the_scan_is_not_taken_for_the_page_edge():
    """The banana tree of the scanned samples touches a dark band along the top of its scan: one
    component, running along the side. Only its pixels near the side are the page's edge; the rest is
    the drawing, which must not be left out (with a short stroke far from it, that left a crop to the
    stroke, or a mosaic of it alone, and no drawing)."""
    px = np.asarray(_sheet_with_drawing(size=(1000, 1400))).copy()
    px[:30, :] = np.linspace(150, 60, 30).astype(np.uint8)[:, None]          # darkest at the border
    px[:222, 399:402] = 0                                                     # a stroke up into the band
    px[1300:1303, 850:900] = 0                                                # a short stroke far away
    art = prep.run(CFG, _encode(Image.fromarray(px, "L"), "PNG"))
    drawing = np.asarray(_sheet_with_drawing(size=(1000, 1400))) < 128
    assert (_page_mask(art) & drawing).sum() >= 0.95 * drawing.sum()


def test_a_stroke_far_from_the_drawing_is_kept_in_the_box():
    """A short stroke of the drawing far from the rest (a stray line of the popsicle in the validation
    split, 8 % of its ink) is not dust: the box reaches it."""
    img = _sheet_with_drawing(size=(2000, 1600))
    ImageDraw.Draw(img).line([(900, 800), (960, 830)], fill=0, width=3)
    art = prep.run(CFG, _encode(img, "PNG"))
    x0, y0 = art.data["origin"]
    h, w = art.arrays["mask"].shape
    assert x0 + w >= 960 + CFG["crop"]["margin_px"] and y0 + h >= 830 + CFG["crop"]["margin_px"]
    assert not any("left out" in n for n in art.notes)


def test_faint_pencil_on_a_grainy_sheet_is_found_and_cropped():
    """Faint pencil (grey 200) on a large grainy sheet with a few black noise pixels: the page's
    percentiles are all paper, and its darkest pixel is noise, so the page-wide stretch found no ink
    ("blank image", as validation drawings on 2×–3× sheets did). The box is found on the unstretched
    grey, and the band inside it is the drawing's."""
    img = _sheet_with_drawing(level=200, grain=3.0)
    px = np.asarray(img).copy()
    rng = np.random.default_rng(1)
    px[rng.integers(0, 1000, 30), rng.integers(0, 1400, 30)] = 0
    art = prep.run(CFG, _encode(Image.fromarray(px, "L"), "PNG"))
    assert art.data["origin"] is not None
    full = _page_mask(art)
    ref = np.asarray(_sheet_with_drawing()) < 128
    assert (full & ref).sum() >= 0.9 * ref.sum() and (full & ~ref).sum() <= 0.2 * ref.sum()


def test_faint_sparse_pencil_on_a_sheet_too_small_to_crop_is_not_blank():
    """A faint pencil circle (grey 200, 2 px) on a grainy sheet with a few black noise pixels, its box
    over ``crop.max_area_fraction`` (not cropped) and its ink under the 0.5 % of the page's low
    percentile: the page-wide stretch falls back to the ink's own levels, and black is not the darkest
    noise pixel (which left every stroke lighter than the threshold: "blank image", as a validation
    drawing on a sheet twice its size did)."""
    def sheet(level, grain):
        rng = np.random.default_rng(0)
        page = np.clip(rng.normal(250, grain, (800, 800)), 0, 255) if grain else np.full((800, 800), 255.0)
        img = Image.fromarray(page.astype(np.uint8), "L")
        ImageDraw.Draw(img).ellipse([200, 200, 600, 600], outline=level, width=2)
        return np.asarray(img).copy()

    px = sheet(200, 3.0)
    rng = np.random.default_rng(1)
    px[rng.integers(0, 800, 10), rng.integers(0, 800, 10)] = 0
    art = prep.run(CFG, _encode(Image.fromarray(px, "L"), "PNG"))
    assert art.data["origin"] is None
    ref = sheet(0, 0.0) < 128
    mask = art.arrays["mask"]
    assert (mask & ref).sum() >= 0.9 * ref.sum() and (mask & ~ref).sum() <= 0.1 * ref.sum()


def _two_drawings_far_apart(size=(1600, 2000), second=(1200, 1650)):
    """``_sheet_with_drawing``'s sheet with a second drawing (a cross in a triangle) whose corner is at
    ``second``: together their boxes hold ~7 % of the page, the box round both ~60 %."""
    img = _sheet_with_drawing(size=size, at=(100, 150))
    d = ImageDraw.Draw(img)
    x, y = second
    d.polygon([(x + 20, y + 200), (x + 120, y + 20), (x + 220, y + 200)], outline=0, width=3)
    d.line([(x + 70, y + 90), (x + 170, y + 190)], fill=0, width=3)
    d.line([(x + 70, y + 190), (x + 170, y + 90)], fill=0, width=3)
    return img


def test_drawings_far_apart_on_a_page_are_worked_on_side_by_side():
    """Two drawings in opposite corners of a sheet: their common box keeps most of the page (stop 44
    worked on all of it: 33 s for the elephant and the kitten on an A4 sheet, 14 s apart), so each
    one's box is a piece of a mosaic laid out on paper; the band of each piece is the band of that
    drawing cropped alone, and ``to_source``/``to_internal`` map each piece's pixels to its own place."""
    img = _two_drawings_far_apart()
    art = prep.run(CFG, _encode(img, "PNG"))
    pieces = art.data["pieces"]
    assert art.data["origin"] is None and len(pieces) == 2, art.data
    assert any("2 parts far apart on the page" in n and "prep.crop" in n for n in art.notes), art.notes
    assert art["mask"].size < 0.2 * 1600 * 2000
    ref = np.asarray(img) < 128
    np.testing.assert_array_equal(_page_mask(art), ref)
    m = CFG["crop"]["margin_px"]
    # Each piece is its drawing's box grown by the margin, in source pixels, on multiples of 12 in the mosaic.
    boxes = sorted((sx, sy, w, h) for _, _, sx, sy, w, h in pieces)
    for (sx, sy, w, h), (rows, cols) in zip(boxes, (np.nonzero(ref[:1000, :1000]), np.nonzero(ref[1000:, 1000:]))):
        top = 0 if sy < 1000 else 1000
        assert (sx, sy, w, h) == (cols.min() + top - m, rows.min() + top - m, np.ptp(cols) + 1 + 2 * m, np.ptp(rows) + 1 + 2 * m)
    assert all(mx % 12 == 0 and my % 12 == 0 for mx, my, *_ in pieces)
    for mx, my, sx, sy, w, h in pieces:
        source = np.array([[sx + 3.5, sy + 7.25], [sx + w - 0.5, sy + h - 0.5]])
        internal = prep.to_internal(source, art.data)
        np.testing.assert_allclose(internal, source - [sx, sy] + [mx, my])
        np.testing.assert_allclose(prep.to_source(internal, art.data), source)
    # A point on the paper laid between pieces goes with the nearest piece.
    (ax, ay, asx, asy, aw, ah), = [p for p in pieces if p[0] == 0 and p[1] == 0]
    np.testing.assert_allclose(prep.to_source([[aw + 2.0, 5.0]], art.data), [[asx + aw + 2.0, asy + 5.0]])
    # One drawing on the page, or crop off: as before.
    off = prep.run(dict(CFG, crop=dict(CFG["crop"], enabled=False)), _encode(img, "PNG"))
    assert "pieces" not in off.data and off["mask"].shape == (2000, 1600)


def test_a_mosaic_is_not_made_when_the_pieces_would_keep_much_of_the_page():
    """Pieces holding more than ``crop.max_area_fraction`` of the page together: the page is kept."""
    img = _two_drawings_far_apart(size=(650, 760), second=(380, 500))
    art = prep.run(CFG, _encode(img, "PNG"))
    assert "pieces" not in art.data and art.data["origin"] is None and art["mask"].shape == (760, 650)


def _photographed_sheet():
    """900×1200: a 660×900 sheet lit unevenly (204 to 242 across), photographed upright on a darker
    desk round it on every side (``photos.photographed``), ``_sheet_with_drawing``'s drawing on it at
    (330, 450) in the photograph; the sheet, and the drawing's ink in the photograph."""
    sheet = _sheet_with_drawing(size=(660, 900), at=(210, 300))
    return (*photographed(sheet, 0, (450, 600), size=(900, 1200)), sheet)


def _flat_ink(sheet: Image.Image, art) -> np.ndarray:
    """The ``sheet``'s ink (darker than 128) in the pixels of a prep that flattened its photograph: the
    sheet scaled to the flattened rectangle."""
    ink = Image.fromarray((np.asarray(sheet) < 128).astype(np.uint8) * 255)
    return np.asarray(ink.resize((art.data["width"], art.data["height"]), Image.BILINEAR)) > 127


def _on_the_ink(page: np.ndarray, ink: np.ndarray, found: float, near_px: int = 2) -> None:
    """The band ``page`` covers ``found`` of ``ink``, and hardly anything (2 %) farther than ``near_px``."""
    near = ndimage.binary_dilation(ink, iterations=near_px)
    assert (page & ink).sum() >= found * ink.sum(), ((page & ink).sum(), ink.sum())
    assert (page & ~near).sum() <= 0.02 * ink.sum(), ((page & ~near).sum(), ink.sum())


def test_a_photographed_sheet_is_cut_out_of_the_desk_round_it_and_flattened():
    """A photograph of a sheet on a desk: the desk, divided by its own brightness with the lighting,
    became speckle, and the sheet's border a frame of band (stop 44: 83 curves at 1/4 resolution along
    the border of ``photo_desk.png``). The sheet is found first, on the grey as photographed, and, seen
    whole, flattened: the drawing is the sheet's rectangle, the band is the drawing's alone, at full
    resolution, where it is on the sheet, and the console says so."""
    img, _, sheet = _photographed_sheet()
    art = prep.run(CFG, _encode(img, "PNG"))
    line, = [n for n in art.notes if "a sheet on a darker ground" in n]
    assert "flattened" in line and "prep.crop.sheet_flatten" in line, line
    assert art.data["scale"] == 1.0 and abs(art.data["height"] - 900) <= 2 and abs(art.data["width"] - 660) <= 2
    np.testing.assert_allclose(art.data["sheet_corners"], [[120, 150], [780, 150], [780, 1050], [120, 1050]], atol=1.5)
    x0, y0 = art.data["origin"]
    assert 150 <= x0 <= 210 and 240 <= y0 <= 300   # the drawing's box on the sheet (crop.margin_px round it)
    _on_the_ink(_page_mask(art), _flat_ink(sheet, art), 0.95)
    off = prep.run(dict(CFG, crop=dict(CFG["crop"], enabled=False)), _encode(img, "PNG"))
    assert off.data["origin"] is None and not any("darker ground" in n for n in off.notes)


def test_a_dark_edge_along_one_side_is_not_a_desk():
    """A scan's dark strip down one side, narrow or 120 px wide, runs along a quarter of the border, not
    ``crop.sheet_rim_share`` of it: no sheet is cut out (the page-edge rule handles it)."""
    for width in (40, 120):
        px = np.asarray(_sheet_with_drawing()).copy()
        px[:, :width] = 60
        art = prep.run(CFG, _encode(Image.fromarray(px, "L"), "PNG"))
        assert not any("darker ground" in n for n in art.notes), (width, art.notes)


def test_lighting_that_darkens_one_side_of_a_page_is_not_a_desk():
    """A page lit from one corner (paper from 0.95 down to 0.55): its darker side is solid, along half
    the border, and 0.2 below the paper, as a desk is; but it darkens slowly, with no step at the
    sheet's edge.  Taken for a desk, it was painted over with the strokes on it."""
    px = np.asarray(_sheet_with_drawing(size=(1000, 1300), at=(150, 900))).astype(float)
    yy, xx = np.mgrid[0:1300, 0:1000]
    px *= 0.95 - 0.2 * xx / 1000 - 0.2 * yy / 1300
    art = prep.run(CFG, _encode(Image.fromarray(px.astype(np.uint8), "L"), "PNG"))
    assert not any("darker ground" in n for n in art.notes), art.notes
    drawing = np.asarray(_sheet_with_drawing(size=(1000, 1300), at=(150, 900))) < 128
    assert (_page_mask(art) & drawing).sum() >= 0.95 * drawing.sum()


def test_a_turned_sheet_on_a_desk_over_most_of_the_photograph_is_straightened():
    """A phone photo of a sheet turned by 15° on a desk that covers most of it.  The desk made the paper
    level dark (the photo was inverted) and kept the box whole; now the sheet is found before the
    inversion and flattened upright: the drawing is the sheet at its own size, the band on its ink.
    With ``crop.sheet_flatten=false`` it is cut out as it lies, the desk in its box painted as paper, in
    the photograph's pixels."""
    sheet = _sheet_with_drawing(size=(600, 800), at=(180, 280))
    img, drawing = photographed(sheet, 15, (500, 650))
    art = prep.run(CFG, _encode(img, "PNG"))
    assert any("flattened" in n for n in art.notes) and not any("invert" in n for n in art.notes), art.notes
    assert abs(art.data["height"] - 800) <= 3 and abs(art.data["width"] - 600) <= 3
    _on_the_ink(_page_mask(art), _flat_ink(sheet, art), 0.9)
    cut = prep.run(dict(CFG, crop=dict(CFG["crop"], sheet_flatten=False)), _encode(img, "PNG"))
    assert any("a sheet on a darker ground" in n and "painted as paper" in n for n in cut.notes), cut.notes
    assert (cut.data["height"], cut.data["width"]) == (1300, 1000) and "sheet_corners" not in cut.data
    _on_the_ink(_page_mask(cut), drawing, 0.9)


def test_a_sheet_running_off_the_photograph_is_cut_out_as_it_lies():
    """The sheet turned by −8° and running off the photograph at its top and left: its corners are not
    all seen, so it is not flattened; it is cut out, the desk in its box painted as paper, and its box
    starts at the photograph's edge (one cell in); the band is the drawing's, in the photograph's pixels."""
    img, drawing = photographed(_sheet_with_drawing(size=(600, 800), at=(180, 280)), -8, (330, 420))
    art = prep.run(CFG, _encode(img, "PNG"))
    sheet_line, = [n for n in art.notes if "darker ground" in n]
    assert "painted as paper" in sheet_line and "flattened" not in sheet_line, sheet_line
    assert sheet_line.split("box at (")[1].startswith("16, 16)"), sheet_line
    assert art.data["origin"] is not None and "pieces" not in art.data    # no piece of the desk beside it
    _on_the_ink(_page_mask(art), drawing, 0.9)


@pytest.mark.parametrize("angle, tilt, exif, tolerance", [(10, 30, None, 0.01), (-20, -35, None, 0.01),
                                                    (0, 30, 34, 0.015), (0, 20, None, 0.04)])
def test_a_sheet_photographed_at_an_angle_is_flattened_to_its_proportions(angle, tilt, exif, tolerance):
    """A phone held at an angle over the sheet (its top 20-35° farther, the sheet also turned): the
    flattened rectangle has the sheet's proportions, from the focal length its corners give (1 %).  With
    the sheet only leaned back, its sides left and right meet in the photo but top and bottom stay
    parallel: the focal length is not determined, and the JPEG's EXIF one is taken (34 mm in 35-mm
    terms: this camera's, whose focal length is the photo's longer side, 1300 px), or without EXIF a
    phone's (4 %: a phone's is 0.75 of the longer side).  The band lies on the sheet's ink (in
    perspective, the far side's strokes come out thinner, so 3 px)."""
    sheet = _sheet_with_drawing(size=(600, 800), at=(180, 280))
    img, _ = photographed(sheet, angle, (500, 650), tilt=tilt)
    if exif:
        tags = Image.Exif()
        tags.get_ifd(0x8769)[0xA405] = exif          # FocalLengthIn35mmFilm
        png = _encode(img, "JPEG", quality=92, exif=tags)
    else:
        png = _encode(img, "PNG")
    art = prep.run(CFG, png)
    assert any("flattened" in n for n in art.notes), art.notes
    assert abs(art.data["width"] / art.data["height"] - 0.75) <= tolerance * 0.75, (art.data["width"], art.data["height"])
    _on_the_ink(_page_mask(art), _flat_ink(sheet, art), 0.85, near_px=3)


def test_the_proportions_of_a_sheet_from_its_corners_in_a_photograph():
    """``sheet_aspect`` on exact corners (the camera of ``photos.photographed``): a 600×800 sheet
    turned and leaned by various angles comes back at 0.75 to 0.2 %; seen head-on, turned, too."""
    from photos import sheet_to_photo
    from stages.prep.sheet_flatten import sheet_aspect

    for angle, tilt in ((0, 0.001), (12, 0.001), (10, 30), (-25, 40), (30, -20), (5, 15)):
        hom = sheet_to_photo((600, 800), angle, tilt, (520, 640), (1000, 1300))
        corners = np.c_[[-0.5, 599.5, 599.5, -0.5], [-0.5, -0.5, 799.5, 799.5], np.ones(4)] @ hom.T
        aspect = sheet_aspect(corners[:, :2] / corners[:, 2:], (1300, 1000))
        assert abs(aspect - 0.75) < 0.0015, (angle, tilt, aspect)


def test_a_torn_corner_of_a_photographed_sheet_is_painted_as_paper():
    """A sheet with a corner torn off, the desk showing through: its sides are found on the edge that is
    left (the hull's quadrilateral cut the corner off), so it is flattened to its own rectangle, and the
    desk inside it is painted as paper: no band off the drawing's ink.  A larger tear leaves too much of
    the edge off four straight sides: the sheet is cut out as it lies, with the same band."""
    sheet = _sheet_with_drawing(size=(600, 800), at=(180, 280))
    img, drawing = photographed(sheet, 6, (500, 650))
    # The sheet's top-left corner is at (160, 284) in the photograph (600×800 turned 6° round (500, 650)).
    for tear, flattened in (([(120, 250), (240, 250), (225, 290), (200, 300), (175, 370), (120, 370)], True),
                            ([(120, 240), (300, 240), (280, 300), (230, 330), (180, 420), (120, 420)], False)):
        px = np.asarray(img).copy()
        torn = Image.new("L", img.size, 0)
        ImageDraw.Draw(torn).polygon(tear, fill=255)
        px[np.asarray(torn) > 0] = 70
        art = prep.run(CFG, _encode(Image.fromarray(px, "L"), "PNG"))
        assert any("darker ground" in n for n in art.notes), art.notes
        assert any("flattened" in n for n in art.notes) == flattened, art.notes
        if flattened:
            np.testing.assert_allclose(art.data["sheet_corners"][0], [159.8, 283.6], atol=1.0)
            assert abs(art.data["height"] - 800) <= 3 and abs(art.data["width"] - 600) <= 3
            _on_the_ink(_page_mask(art), _flat_ink(sheet, art), 0.9)
        else:
            _on_the_ink(_page_mask(art), drawing, 0.9)


def test_a_lighter_patch_of_desk_joining_the_sheet_does_not_run_it_off_the_photograph():
    """A lighter desk (wood grain, a patch of light): a bright strip 40 px wide from the sheet's left edge
    to the photograph's joins the sheet's cells, so the sheet seemed to run off the photo and was cut out
    as it lay, its box out to the border.  The sheet less the strip (the ground's opening cuts it) is seen
    whole: it is flattened to its own rectangle, the band on its ink."""
    sheet = _sheet_with_drawing(size=(600, 800), at=(180, 280))
    img, _ = photographed(sheet, 4, (500, 650))
    px = np.asarray(img).copy()
    px[500:540, :190] = 165          # up to the sheet's left edge (x ≈ 190 there)
    art = prep.run(CFG, _encode(Image.fromarray(px, "L"), "PNG"))
    assert any("flattened" in n for n in art.notes), art.notes
    assert abs(art.data["height"] - 800) <= 3 and abs(art.data["width"] - 600) <= 3
    _on_the_ink(_page_mask(art), _flat_ink(sheet, art), 0.9)


def test_a_drawing_on_a_photographed_sheet_is_cropped_in_the_sheets_pixels():
    """The crop's console line gives the drawing's box on the flattened sheet (it gave the sheet's)."""
    img, _, sheet = _photographed_sheet()
    notes = prep.run(CFG, _encode(img, "PNG")).notes
    ink = np.asarray(sheet) < 128
    rows, cols = np.flatnonzero(ink.any(axis=1)), np.flatnonzero(ink.any(axis=0))
    line, = [n for n in notes if "the drawing fills" in n]
    x, y = (int(v) for v in line.split("box at (")[1].split(")")[0].split(", "))
    assert abs(cols[0] - CFG["crop"]["margin_px"] - x) <= 3 and abs(rows[0] - CFG["crop"]["margin_px"] - y) <= 3, line


def test_an_inverted_drawing_with_hatching_is_not_taken_for_a_photographed_sheet():
    """Chalk on a blackboard with a densely hatched patch: a bright solid region on dark ground along the
    whole border, as a sheet on a desk is, but its cells are not plain paper: the page is inverted and
    kept whole."""
    px = np.asarray(_sheet_with_drawing(size=(1000, 1000), at=(600, 600))).copy()
    for x in range(150, 550, 6):
        px[150:550, x:x + 3] = 0
    art = prep.run(CFG, _encode(Image.fromarray(255 - px, "L"), "PNG"))
    assert not any("darker ground" in n for n in art.notes), art.notes
    assert any("inverted" in n for n in art.notes) and art.data["origin"] is None


def test_two_drawings_far_apart_on_a_photographed_sheet_come_back_on_the_sheet():
    """The sheet cut out of the desk and flattened, then its two drawings far apart laid side by side:
    each piece's corner on the flattened sheet is its corner on the sheet moved by the rim left out."""
    sheet = _two_drawings_far_apart(size=(1500, 1840), second=(950, 1370))
    img, _ = photographed(sheet, 0, (800, 1000), size=(1600, 2000))
    art = prep.run(CFG, _encode(img, "PNG"))
    assert any("flattened" in n for n in art.notes) and len(art.data["pieces"]) == 2, art.notes
    _on_the_ink(_page_mask(art), _flat_ink(sheet, art), 0.95)
