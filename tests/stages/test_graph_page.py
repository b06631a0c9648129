"""Tests of the graph stage's cost on a page: its memory and time follow the ink, not the page's area.

A page holds many drawings (issue #54): arrays of the page's size, copies of the millions of
streamline samples and sorts that grow faster than the ink are what these tests keep out.  The
results themselves do not change (tests/stages/test_graph.py checks the graphs).
"""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import yaml

from stages import field, prep, synthetic
from stages.graph.raw_graph import member_order
from stages.graph.trace import Streamlines, trace_streamlines

ROOT = Path(__file__).resolve().parents[2]


def _cfg(stage: str) -> dict:
    return yaml.safe_load((ROOT / "conf" / stage / "default.yaml").read_text())


def _lines() -> Streamlines:
    d = synthetic.line()
    p = prep.run(_cfg("prep"), image_bytes=d.png_bytes(), image_name="line")
    f = field.run(_cfg("field"), prep=p)
    tc = _cfg("graph")["trace"]
    return trace_streamlines(np.asarray(f["c0"]), np.asarray(f["c2"]), np.asarray(p["mask"]).astype(bool),
                             np.asarray(f["singular"]).astype(bool), np.asarray(f["roots"])[..., 0],
                             step=tc["step"], max_half_samples=tc["max_half_samples"],
                             merge_distance=tc["merge_distance"], merge_cos=tc["merge_cos"],
                             self_merge_lag=tc["self_merge_lag"], tie=tc["tie"])


def test_streamline_columns_are_contiguous():
    """The cross-sections' kernel reads x, y and the tangent's columns without copying them."""
    lines = _lines()
    assert len(lines.xy) > 100
    for a in (lines.xy, lines.tangent):
        assert a.shape == (len(lines.curve), 2)
        assert a[:, 0].flags.c_contiguous and a[:, 1].flags.c_contiguous


def test_stored_streamlines_keep_every_nth_sample_and_the_last():
    """Per-curve indices give what a mask over all samples gives, for any spacing and curve length."""
    from stages.graph.stage import stored_streamlines

    rng = np.random.default_rng(3)
    length = rng.integers(1, 40, 300)
    start = np.r_[0, np.cumsum(length)[:-1]]
    curve = np.repeat(np.arange(300), length).astype(np.int32)
    xy = rng.random((2, int(length.sum()))).astype(np.float32).T
    lines = Streamlines(xy=xy, tangent=xy, start=start, length=length, end_reason=np.zeros((300, 2), np.int8))
    np.testing.assert_array_equal(lines.curve, curve)
    for every in (0, 1, 2, 5, 7, 100):
        local = np.arange(len(xy)) - start[curve]
        take = (local % max(1, every) == 0) | (local == length[curve] - 1)
        s_xy, s_off = stored_streamlines(lines, every)
        np.testing.assert_array_equal(s_xy, xy[take])
        np.testing.assert_array_equal(s_off, np.r_[0, np.cumsum(np.bincount(curve[take], minlength=300))])
        assert s_xy.dtype == np.float32 and s_xy.flags.c_contiguous


def test_member_order_is_lexsort_with_ties_and_rounded_keys():
    """The one-key sort gives lexsort's order, also where keys tie or round together (its fallback)."""
    rng = np.random.default_rng(5)
    n = 20000
    mc = rng.integers(0, 500, n)
    mp = rng.integers(0, 60, n) + rng.random(n)
    cases = [(mc, mp),
             (mc, np.floor(mp)),                                    # many exact ties
             (mc * 10**7, mp + rng.integers(0, 2, n) * 1e-9),       # distinct params, equal keys
             (mc[:1], mp[:1]), (mc[:0], mp[:0])]
    for c, p in cases:
        np.testing.assert_array_equal(member_order(c, p), np.lexsort((p, c)))


def test_singular_ends_need_no_image_sized_distance_transform():
    """Which vertices are next to a singularity is found from the singular pixels, not from a distance
    transform of the whole page (memory of the page's area: 8 bytes a pixel and more)."""
    from stages.graph.ends import join_singular_ends

    band = np.zeros((3000, 3000), bool)
    band[100:110, 100:140] = True
    singular = np.zeros_like(band)
    singular[105, 120] = True
    xy = np.array([[113.5, 105.5], [118.5, 105.5], [122.5, 105.5], [127.5, 105.5]])
    width = np.full(4, 4.0)
    edges = np.array([[0, 1], [2, 3]])
    tracemalloc.start()
    added = join_singular_ends(xy, width, edges, np.zeros(4, np.uint8), band, singular, 10.0, 20)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    np.testing.assert_array_equal(added, [[1, 2]])        # the two ends either side are joined
    assert peak < 4 * band.size                            # the page's pixels at 8 bytes each: 72 MB


def _field_on_page(size: int = 3000):
    """The line drawing's field and band, placed in a ``size`` × ``size`` page (complex64, 0 off the band,
    as the field stage stores them)."""
    d = synthetic.line()
    p = prep.run(_cfg("prep"), image_bytes=d.png_bytes(), image_name="line")
    f = field.run(_cfg("field"), prep=p)
    small = {"band": np.asarray(p["mask"]).astype(bool), "singular": np.asarray(f["singular"]).astype(bool),
             "c0": np.asarray(f["c0"]), "c2": np.asarray(f["c2"]), "seed": np.asarray(f["roots"])[..., 0]}
    h, w = small["band"].shape
    page = {}
    for k, a in small.items():
        page[k] = np.zeros((size, size), a.dtype)
        page[k][100:100 + h, 200:200 + w] = a
    return page


def _trace_and_sections(page, c0, c2):
    from stages.graph.raw_graph import build_cross_sections

    tc, sc = _cfg("graph")["trace"], _cfg("graph")["sections"]
    lines = trace_streamlines(c0, c2, page["band"], page["singular"], page["seed"], step=tc["step"],
                              max_half_samples=tc["max_half_samples"], merge_distance=tc["merge_distance"],
                              merge_cos=tc["merge_cos"], self_merge_lag=tc["self_merge_lag"], tie=tc["tie"])
    raw = build_cross_sections(c0, c2, page["band"], page["singular"], lines, step=tc["step"],
                               station_spacing=sc["station_spacing"], cover_factor=sc["cover_factor"],
                               min_station_gap=sc["min_station_gap"], max_gap=sc["max_gap"],
                               max_section_length=sc["max_section_length"], ambiguity=sc["ambiguity"],
                               tie=tc["tie"], lane_pad=sc["lane_pad"])
    return lines, raw


def test_trace_and_sections_copy_no_page_sized_field():
    """The field stage's complex64 images, 0 off the band, are read as they are: no complex128 copies of
    c0 and c2 (32 bytes a pixel of the page), no page-sized seed directions, an int32 cell lookup.  The kernels widen each
    value exactly, so the streamlines and cross-sections are those of complex128 copies, and of a field
    that is not 0 off the band (copied, then read as 0 there)."""
    page = _field_on_page()
    tracemalloc.start()
    lines, raw = _trace_and_sections(page, page["c0"], page["c2"])
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert len(lines.xy) > 100 and len(raw.xy) > 10
    # the kernels' int32 pixel lookups (the trace's ``head``, the cells' ``bidx``) are 4 bytes a pixel; the
    # copies were 60 (540 MB here)
    assert peak < 5 * page["band"].size
    noisy = {k: np.where(page["band"], page[k], 1 + 2j).astype(np.complex128) for k in ("c0", "c2")}
    for c0, c2 in ((page["c0"].astype(np.complex128), page["c2"].astype(np.complex128)),
                   (noisy["c0"], noisy["c2"])):
        lines2, raw2 = _trace_and_sections(page, c0, c2)
        for a, b in ((lines.xy, lines2.xy), (lines.tangent, lines2.tangent), (lines.curve, lines2.curve),
                     (raw.xy, raw2.xy), (raw.width, raw2.width), (raw.root, raw2.root), (raw.edges, raw2.edges),
                     (raw.member_param, raw2.member_param)):
            np.testing.assert_array_equal(a, b)


def test_stored_streamlines_index_in_chunks():
    """The stored subsample's index is built a chunk of curves at a time (:data:`STORED_CHUNK`): the whole
    index and its int64 temporaries were the graph's peak on a 4x4 page."""
    from stages.graph import stage

    rng = np.random.default_rng(7)
    length = rng.integers(1, 60, 200_000)
    start = np.r_[0, np.cumsum(length)[:-1]]
    n = int(length.sum())
    xy = rng.random((2, n), dtype=np.float32).T
    lines = Streamlines(xy=xy, tangent=xy, start=start, length=length,
                        end_reason=np.zeros((len(length), 2), np.int8))
    tracemalloc.start()
    s_xy, _ = stage.stored_streamlines(lines, 1)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    np.testing.assert_array_equal(s_xy, xy)
    # the kept samples themselves (8 bytes each) and one chunk's temporaries of 2**20 samples; the whole
    # index took 6 int64s a sample (6 M samples here)
    assert peak < s_xy.nbytes + 80 * 2**20


def test_stored_streamlines_chunks_give_the_same_samples():
    """Any chunk size (curves are never split) gives the same stored subsample."""
    from stages.graph import stage

    rng = np.random.default_rng(8)
    length = rng.integers(0, 60, 3000)
    start = np.r_[0, np.cumsum(length)[:-1]]
    xy = rng.random((2, int(length.sum())), dtype=np.float32).T
    lines = Streamlines(xy=xy, tangent=xy, start=start, length=length,
                        end_reason=np.zeros((len(length), 2), np.int8))
    old_chunk = stage.STORED_CHUNK
    try:
        for chunk in (1, 7, 1000):
            stage.STORED_CHUNK = chunk
            for every in (1, 3, 5):
                a, oa = stage.stored_streamlines(lines, every)
                stage.STORED_CHUNK = old_chunk
                b, ob = stage.stored_streamlines(lines, every)
                stage.STORED_CHUNK = chunk
                np.testing.assert_array_equal(a, b)
                np.testing.assert_array_equal(oa, ob)
    finally:
        stage.STORED_CHUNK = old_chunk


def test_streamline_samples_are_dropped_before_the_clean_up(monkeypatch):
    """The crossings' sort and the clean-up read the cross-sections alone: the streamlines' samples (20
    bytes each, 0.7 GB on a 4x4 page) are released once the cross-sections' kernel and the stored
    subsample are done, not held to the end."""
    import gc
    import weakref

    from stages import graph
    from stages.graph import cleanup, raw_graph, stage

    d = synthetic.line()
    p = prep.run(_cfg("prep"), image_bytes=d.png_bytes(), image_name="line")
    f = field.run(_cfg("field"), prep=p)
    refs, alive = [], []
    trace = stage.trace_streamlines

    def traced(*args, **kwargs):
        lines = trace(*args, **kwargs)
        refs.append(weakref.ref(lines.xy.base if lines.xy.base is not None else lines.xy))
        return lines

    def check(fn):
        def checked(*args, **kwargs):
            gc.collect()
            alive.append(refs[0]() is not None)
            return fn(*args, **kwargs)
        return checked

    monkeypatch.setattr(stage, "trace_streamlines", traced)
    # the crossings' sort (millions of rows on a page) and the clean-up run without the samples
    monkeypatch.setattr(raw_graph, "member_order", check(raw_graph.member_order))
    monkeypatch.setattr(cleanup, "merge_close_vertices", check(cleanup.merge_close_vertices))
    out = graph.run(_cfg("graph"), prep=p, field=f)
    assert len(out["streamline_xy"]) > 100
    assert alive == [False, False]


def test_sub_cell_index_takes_one_array_of_cell_starts():
    """The cross-sections' sub-cell index fills its cells from the last sample down, with no copy of
    its cell starts (16 int64s a band pixel: 0.13 GB on a 4x4 page).  Measured in a fresh process:
    numba's arrays are not seen by tracemalloc."""
    import subprocess
    import sys

    code = """
import resource, numpy as np
from stages.graph.cross_section import _cell_index
def rss():
    with open('/proc/self/statm') as f:
        return int(f.read().split()[1]) * resource.getpagesize()
band = np.ones((4, 4), bool)
_cell_index(np.full(3, 1.5, np.float32), np.full(3, 1.5, np.float32), band)
band = np.ones((1000, 1000), bool)
sx = np.full(1000, 10.5, np.float32)
# the peak so far (a kernel compiled on the first call when no shipped one loads) is cleared: only
# the call below counts (Linux >= 4.0: '5' resets VmHWM)
with open('/proc/self/clear_refs', 'w') as f:
    f.write('5')
before = rss()
_cell_index(sx, sx, band)
with open('/proc/self/status') as f:
    hwm = next(int(line.split()[1]) * 1024 for line in f if line.startswith('VmHWM'))
print((hwm - before) / (16 * 8 * band.size))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    # the cell starts once (1.0) and the pixels' int32 index; a copy of the starts made it 2.0
    assert float(out.stdout.split()[-1]) < 1.5


def test_cross_sections_kernel_holds_no_curve_id_a_sample_and_int32_ids():
    """The cross-sections' kernel finds a sample's curve from the curves' starts (no curve id a sample:
    0.14 GB on a 4x4 page, dropped before it runs), counts its cells and keeps its crossings' vertex and
    curve ids in int32 (−36 MB and −43 to −64 MB at its peak there); :func:`raw_graph` widens the ids to
    int64 once the samples are gone, so the raw graph is the one of per-sample ids."""
    from stages.graph.cross_section import _cell_index
    from stages.graph.raw_graph import raw_graph, take_cross_sections

    d = synthetic.line()
    p = prep.run(_cfg("prep"), image_bytes=d.png_bytes(), image_name="line")
    f = field.run(_cfg("field"), prep=p)
    band = np.asarray(p["mask"]).astype(bool)
    lines = _lines()
    assert _cell_index(np.ascontiguousarray(lines.xy[:, 0]), np.ascontiguousarray(lines.xy[:, 1]),
                       band)[1].dtype == np.int32
    s = _cfg("graph")["sections"]
    t = _cfg("graph")["trace"]
    params = dict(step=t["step"], tie=t["tie"], **{k: s[k] for k in (
        "station_spacing", "cover_factor", "min_station_gap", "max_gap", "max_section_length", "ambiguity",
        "lane_pad")})
    sections = take_cross_sections(np.asarray(f["c0"]), np.asarray(f["c2"]), band,
                                   np.asarray(f["singular"]).astype(bool), lines,
                                   **params)
    mv, mc = sections[5], sections[6]
    assert len(mv) > 10 and mv.dtype == np.int32 and mc.dtype == np.int32
    assert np.all(mc < len(lines.start))
    raw = raw_graph(sections)
    assert raw.member_vertex.dtype == np.int64 and raw.member_curve.dtype == np.int64
    assert np.array_equal(raw.member_curve, mc) and np.array_equal(raw.member_vertex, mv)


# A wide straight band under the uniform field z⁴ − 1 (roots ±1, ±i): one 1000-px lane per half row and
# pixel row, 4 M samples on a 256 × 2048 page, traced and cut in a fresh process whose peak (VmHWM, reset
# by '5' to /proc/self/clear_refs, Linux >= 4.0) counts numba's arrays, which tracemalloc does not see.
_WIDE = """
import gc, sys, numpy as np
from stages.graph.trace import trace_streamlines
from stages.graph.raw_graph import take_cross_sections
def status(k):
    with open('/proc/self/status') as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith(k))
def page(h, w, rows, cols):
    band = np.zeros((h, w), bool)
    band[rows[0]:rows[1], cols[0]:cols[1]] = True
    c0 = np.where(band, np.complex64(-1), np.complex64(0))
    return band, c0, np.zeros_like(c0), np.zeros_like(band), np.where(band, np.complex64(1), np.complex64(0))
kw = dict(step=0.1, max_half_samples=10000, merge_distance=0.1, merge_cos=0.98, self_merge_lag=30, tie=1e-3)
sk = dict(step=0.1, tie=1e-3, station_spacing=1.0, cover_factor=0.6, min_station_gap=0.3, max_gap=1.5,
          max_section_length=30.0, ambiguity=0.1, lane_pad=0.5)
band, c0, c2, sing, seed = page(16, 64, (4, 12), (4, 60))     # compiled here when no shipped kernel loads
take_cross_sections(c0, c2, band, sing, trace_streamlines(c0, c2, band, sing, seed, **kw), **sk)
band, c0, c2, sing, seed = page(256, 2048, (28, 228), (24, 2024))
def peak(run):
    gc.collect()
    with open('/proc/self/clear_refs', 'w') as f:
        f.write('5')
    before = status('VmRSS')
    out = run()
    return out, status('VmHWM') - before, status('VmRSS') - before
lines, trace_peak, trace_held = peak(lambda: trace_streamlines(c0, c2, band, sing, seed, **kw))
n = len(lines.xy)
if sys.argv[1] == 'trace':
    print(n, trace_peak / n, trace_held / n)
else:
    s, sec_peak, _ = peak(lambda: take_cross_sections(c0, c2, band, sing, lines, **sk))
    # what the kernel needs: the pixels' int32 index, 16 int32 cell starts a band pixel, an int32 sample
    # id a sample, the crossings' int32 vertex, int32 curve and float64 parameter
    need = 4 * band.size + 64 * int(band.sum()) + 4 * n + 16 * len(s[5])
    print(n, (sec_peak - need) / n)
"""


def _wide(what: str) -> list[float]:
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _WIDE, what], capture_output=True, text=True, cwd=ROOT, check=True)
    return [float(v) for v in out.stdout.split()]


def test_trace_holds_20_bytes_a_sample():
    """The trace kernel keeps x, y, the tangent and the pixels' lists, 20 bytes a sample: no curve id and no
    in-curve step a sample (they follow from the sample's id), and writes (2, N) rows, not stacked after
    it.  Was 28 bytes in the kernel and 28 again at the stack (20 held + 8): 0.96 GB on a 4x4 page."""
    n, peak, held = _wide("trace")
    assert n > 3_000_000
    assert peak < 25          # measured 22.1 (30.2 on the old kernel and its stack)
    assert held < 18.5        # x, y, tangent: 16 (20.6 with the curve ids)


def test_cross_sections_hold_a_bit_a_sample_beside_their_index():
    """Beside its sub-cell index and its crossings, the cross-sections' kernel holds one bit a sample (which
    are covered) and never two crossing buffers at once (room for a crossing every 4 samples from the
    start).  Was a byte a sample and the doubling's old and new buffers: +3.4 bytes a sample here."""
    n, extra = _wide("sections")
    assert n > 3_000_000
    assert extra < 1.0        # measured −0.3 (3.4 on the old kernel)


def test_streamlines_keep_no_curve_id_a_sample():
    """The curve ids are made on demand from the curves' starts and lengths, not stored a sample."""
    import dataclasses

    assert "curve" not in {f.name for f in dataclasses.fields(Streamlines)}
    lines = _lines()
    np.testing.assert_array_equal(lines.curve, np.repeat(np.arange(len(lines.start)), lines.length))
    assert lines.curve.dtype == np.int32
