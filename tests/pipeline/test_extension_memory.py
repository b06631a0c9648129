"""The extension's memory, and its artifact's save: what a 4×4 page's keypoints child peaked on.

The child ran the extension on top of the network's kept heap and then saved two complex64 page
arrays; on the 4×4 elephant page (2000×3012) it peaked at 1.50 GB, above the main process
(stages/DECISIONS.md, extension).  Measured here with tracemalloc, which sees numpy's and scipy's arrays
(allocated before it starts: not counted), so the bounds are in the arrays' own bytes.
"""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import yaml
import zarr

from pipeline.engine.store import ArtifactStore
from stages import extension, synthetic
from stages.artifact import Artifact

ROOT = Path(__file__).resolve().parents[2]
CFG = yaml.safe_load((ROOT / "conf" / "extension" / "default.yaml").read_text())


def _peak(fn, *args, **kwargs):
    """``fn``'s result and the most bytes its allocations held at once."""
    tracemalloc.start()
    try:
        out = fn(*args, **kwargs)
        return out, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_the_extension_holds_no_complex128_page():
    """A page mostly paper (a drawing in its corner): the stage's memory is its two complex64 page
    outputs and little more.  Complex128 pages, then their complex64 copies, held 4.0× the outputs'
    bytes; the ring's values written into complex64 pages made once, 1.5×."""
    d = synthetic.zigzag(size=96, teeth=3, width=3.0)
    grey = np.pad(np.tile(d.grey, (2, 2)), ((0, 600), (0, 600)), constant_values=1.0)
    mask = grey < 165 / 255
    rng = np.random.default_rng(0)
    c0, c2 = (np.where(mask, np.exp(1j * rng.uniform(0, 2 * np.pi, mask.shape)), 0).astype(np.complex64)
              for _ in range(2))
    field = Artifact(arrays={"c0": c0, "c2": c2,
                             "smart_weights": rng.uniform(0.5, 1.5, mask.shape).astype(np.float32)})
    out, peak = _peak(extension.run, CFG, prep=Artifact(arrays={"mask": mask}), field=field)
    outputs = out["c0_ext"].nbytes + out["c2_ext"].nbytes
    assert out["c0_ext"].dtype == np.complex64 and (np.abs(out["c0_ext"][~mask]) > 0).sum() > mask.sum()
    assert peak < 2.5 * outputs, peak / outputs


def test_the_extension_is_the_complex128_solve_rounded_once():
    """The stage's complex64 pages are the complex128 ones of :func:`extend_field` rounded: bit for bit."""
    d = synthetic.vee(size=48, width=3)
    mask = d.grey < 165 / 255
    rng = np.random.default_rng(1)
    c0, c2 = (np.where(mask, rng.standard_normal(mask.shape) + 1j * rng.standard_normal(mask.shape), 0)
              .astype(np.complex64) for _ in range(2))
    s = rng.uniform(0.5, 1.5, mask.shape).astype(np.float32)
    conf = extension.ExtensionConfig(**CFG)
    wide = extension.extend_field(c0, c2, mask, s, conf)
    narrow = extension.extend_field(c0, c2, mask, s, conf, dtype=np.complex64)
    art = extension.run(CFG, prep=Artifact(arrays={"mask": mask}),
                        field=Artifact(arrays={"c0": c0, "c2": c2, "smart_weights": s}))
    for w, n, name in zip(wide[:2], narrow[:2], ("c0_ext", "c2_ext")):
        assert w.dtype == np.complex128 and n.dtype == np.complex64
        assert w.astype(np.complex64).tobytes() == n.tobytes() == art[name].tobytes()
    assert wide[2] == narrow[2]


def test_saving_an_array_makes_no_copy_of_it(tmp_path):
    """zarr's test for an empty chunk (np.array_equal) copied a float or complex array twice: 2.4× its
    bytes to save it; the store's own test copies nothing (the encoder's output buffer remains, ≤ 1×)."""
    rng = np.random.default_rng(2)
    a = np.zeros((1000, 1000), np.complex64)
    some = rng.random(a.shape) < 0.25
    a[some] = rng.standard_normal(int(some.sum()))
    store = ArtifactStore(tmp_path / "store")
    store._write_arrays(str(tmp_path / "warm"), {"a": a[:2, :2]})   # zarr's imports and caches
    _, peak = _peak(store._write_arrays, str(tmp_path / "a"), {"a": a})
    assert peak < 1.5 * a.nbytes, peak / a.nbytes
    back = zarr.open_group(str(tmp_path / "a" / "arrays.zarr"), mode="r")["a"][...]
    assert back.tobytes() == a.tobytes()


@pytest.mark.filterwarnings("ignore::zarr.errors.UnstableSpecificationWarning")   # the text arrays
def test_saved_arrays_are_the_files_zarr_writes(tmp_path):
    """The same files as zarr's own write, whether or not the array equals its fill value (no chunk is
    written then): floats by bit pattern (−0.0 is written), complex by value (−0 is not), NaN written."""
    arrays = {
        "f_zero": np.zeros((5, 7), np.float32), "f_negzero": np.full((5, 7), -0.0, np.float32),
        "h_negzero": np.full(3, -0.0, np.float16), "f_nan": np.full(3, np.nan), "f": np.arange(6.0),
        "c_zero": np.zeros((4, 4), np.complex64), "c_negzero": np.full(4, complex(-0.0, -0.0)),
        "c_nan": np.array([complex(np.nan, 0)], np.complex64), "c": np.array([1j, 0], np.complex64),
        "b_false": np.zeros(9, bool), "b": np.ones(9, bool), "i_zero": np.zeros(3, np.int64),
        "i": np.array([0, 2], np.int32), "empty": np.zeros((0, 3)), "scalar_zero": np.array(0.0),
        "scalar": np.array(2.5), "text": np.array(["a", ""]), "text_empty": np.array(["", ""]),
        "strided": np.arange(20.0)[::2],
    }
    store = ArtifactStore(tmp_path / "store")
    for name, a in arrays.items():
        store._write_arrays(str(tmp_path / "ours" / name), {name: a})
        group = zarr.open_group(str(tmp_path / "zarr" / name / "arrays.zarr"), mode="w")
        a = np.ascontiguousarray(a)
        group.create_array(name, shape=a.shape, dtype=a.dtype, chunks=tuple(max(1, s) for s in a.shape))[...] = a

    def files(root: Path) -> dict[str, bytes]:
        return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}

    ours, theirs = files(tmp_path / "ours"), files(tmp_path / "zarr")
    assert ours == theirs
    written = {Path(k).parts[0] for k in ours if "c" in Path(k).parts[3:]}   # NAME/arrays.zarr/NAME/c/…
    assert {"f_negzero", "h_negzero", "f_nan", "c_nan"} <= written
    assert not {"f_zero", "c_zero", "c_negzero", "b_false", "i_zero"} & written
