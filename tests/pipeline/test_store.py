"""Artifact store: content keys, round trips, atomic writes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from pipeline.engine.store import ArtifactStore, artifact_key
from stages.artifact import Artifact, pack_ragged, unpack_ragged


def _artifact():
    return Artifact(arrays={"c": np.arange(12, dtype=np.complex64).reshape(3, 4), "m": np.eye(3, dtype=bool),
                            "empty": np.zeros((0, 2))}, data={"n": 3, "names": ["a", "b"]})


def test_key_depends_on_stage_version_config_and_inputs():
    base = artifact_key("field", "1", {"beta": 10}, {"prep": "abc"})
    assert base == artifact_key("field", "1", {"beta": 10}, {"prep": "abc"})
    assert base != artifact_key("field", "2", {"beta": 10}, {"prep": "abc"})
    assert base != artifact_key("field", "1", {"beta": 11}, {"prep": "abc"})
    assert base != artifact_key("field", "1", {"beta": 10}, {"prep": "abd"})
    assert base != artifact_key("graph", "1", {"beta": 10}, {"prep": "abc"})
    # canonical form: key order in the config does not matter
    assert artifact_key("s", "1", {"a": 1, "b": 2}, {}) == artifact_key("s", "1", {"b": 2, "a": 1}, {})


@pytest.mark.parametrize("url", ["local", "memory://polyvec-test"])
def test_round_trip(tmp_path, url):
    store = ArtifactStore(tmp_path / "store" if url == "local" else url)
    art = _artifact()
    assert not store.exists("field", "k1")
    store.save("field", "k1", art, {"stage": "field"})
    assert store.exists("field", "k1")
    back = store.load("field", "k1")
    for name, value in art.arrays.items():
        assert back[name].dtype == value.dtype
        np.testing.assert_array_equal(back[name], value)
    assert back.data == art.data
    assert store.manifest("field", "k1")["arrays"]["c"]["dtype"] == "complex64"
    assert [(s, k) for s, k, _ in store.iter_manifests()] == [("field", "k1")]


def test_failed_write_leaves_nothing_readable(tmp_path, monkeypatch):
    store = ArtifactStore(tmp_path)

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr("json.dump", boom)
    with pytest.raises(RuntimeError):
        store.save("graph", "k2", _artifact(), {"stage": "graph"})
    monkeypatch.undo()
    assert not store.exists("graph", "k2")
    with pytest.raises(KeyError):
        store.load("graph", "k2")
    assert not os.listdir(tmp_path / ".tmp")


def test_killed_writer_leaves_nothing_readable(tmp_path):
    """kill -9 in the middle of a write: the artifact is absent, the next write succeeds."""
    code = textwrap.dedent(f"""
        import os, signal, numpy as np
        from pipeline.engine.store import ArtifactStore
        from stages.artifact import Artifact
        store = ArtifactStore({str(tmp_path)!r})
        real = ArtifactStore._write_arrays
        def half(self, path, arrays):
            real(self, path, dict(list(arrays.items())[:1]))   # half the arrays are on disk ...
            os.kill(os.getpid(), signal.SIGKILL)               # ... when the process dies
        ArtifactStore._write_arrays = half
        store.save("flow", "k3", Artifact({{"a": np.ones(10), "b": np.zeros(10)}}, {{"x": 1}}), {{}})
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True)
    assert proc.returncode == -signal.SIGKILL
    store = ArtifactStore(tmp_path)
    assert os.listdir(tmp_path / ".tmp"), "the half-written artifact should be an orphan under .tmp"
    assert not store.exists("flow", "k3")
    with pytest.raises(KeyError):
        store.load("flow", "k3")
    assert store.sweep_tmp(older_than_s=0) == 1
    store.save("flow", "k3", _artifact(), {})
    assert store.load("flow", "k3").data["n"] == 3


def test_one_file_results_of_stores_before_packs_are_swept(tmp_path):
    """A store written before packs holds the flow's results as one file each under two-character
    prefix folders that nothing reads any more: the next run's sweep removes them, never a pack."""
    store = ArtifactStore(tmp_path)
    store.save_items("flow", "img1", [("ka", {"curve": np.zeros((2, 2))})])
    old = tmp_path / ".items" / "flow" / "ab"
    old.mkdir(parents=True)
    (old / "ab12.item").write_bytes(b"polyvec-item 1\n...")
    assert store.sweep_tmp() == 1
    assert not old.exists()
    assert store.load_items("flow", "img1", ["ka"])[0]["curve"].shape == (2, 2)


def test_ragged_round_trip():
    parts = [np.zeros((3, 2)), np.ones((0, 2)), np.full((2, 2), 5.0)]
    flat, off = pack_ragged(parts)
    assert off.tolist() == [0, 3, 3, 5]
    for a, b in zip(parts, unpack_ragged(flat, off)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("url", ["local", "memory://polyvec-test-items"])
def test_per_item_results_round_trip_as_packs(tmp_path, url):
    """Results are written one pack per call and read back by key from every pack of their scope;
    a result whose bytes are corrupted or torn, or a pack that is not one, reads as missing."""
    import io

    from pipeline.engine.store import encode_pack, read_pack

    def decode_pack(raw, wanted):
        return read_pack(io.BytesIO(raw), wanted)

    store = ArtifactStore(tmp_path / "s" if url == "local" else url)
    a = {"curve": np.arange(6.0).reshape(3, 2), "energy": np.float64(2.5), "failed": np.int8(0)}
    b = {"curve": np.zeros((0, 2)), "energy": np.float64(1.0), "failed": np.int8(1)}
    store.save_items("flow", "img1", [("ka", a)])
    store.save_items("flow", "img1", [("kb", b)])
    store.save_items("flow", "img2", [("kc", a)])
    got = store.load_items("flow", "img1", ["kb", "kc", "ka"])
    assert got[1] is None                                    # another image's pack is not read
    assert np.array_equal(got[2]["curve"], a["curve"]) and got[2]["energy"] == 2.5 and got[2]["energy"].shape == ()
    assert got[0]["curve"].shape == (0, 2) and int(got[0]["failed"]) == 1
    assert store.load_items("flow", "nothing-here", ["ka"]) == [None]
    raw = encode_pack([("ka", a), ("kb", b)])
    assert set(decode_pack(raw, {"ka", "kb"})) == {"ka", "kb"}
    assert set(decode_pack(raw[:-3], {"ka", "kb"})) == {"ka"}            # the last result torn
    flipped = bytearray(raw)
    flipped[-40] ^= 1
    assert set(decode_pack(bytes(flipped), {"ka", "kb"})) == {"ka"}      # its digest
    assert decode_pack(b"not a pack at all", {"ka"}) == {}
    assert decode_pack(raw[:len(raw) // 50], {"ka"}) == {}               # the index itself torn


def test_a_pack_lookup_reads_the_index_and_the_wanted_results_only():
    """Packs pile up (one per λ of a sweep): a lookup must cost what it finds, not every pack's size."""
    import io

    from pipeline.engine.store import encode_pack, read_pack

    big = {"curve": np.zeros((5000, 2))}
    raw = encode_pack([("ka", big), ("kb", {"curve": np.ones((3, 2))}), ("kc", big)])

    class Counting(io.BytesIO):
        n = 0

        def read(self, size=-1):
            out = super().read(size)
            Counting.n += len(out)
            return out

    got = read_pack(Counting(raw), {"kb"})
    assert list(got) == ["kb"] and np.array_equal(got["kb"]["curve"], np.ones((3, 2)))
    assert Counting.n < len(raw) // 10


def test_library_versions_are_looked_up_once_per_process_or_taken_from_the_parent(monkeypatch):
    """Every task's manifest records the libraries' versions: importlib.metadata is asked once per
    process (20–30 ms a task otherwise), and a spawned child of the same installation (the keypoints
    process) takes its parent's record instead of asking; a record already made is not replaced."""
    import importlib.metadata as md

    from pipeline.engine import store as store_mod

    calls = []
    real = md.version
    monkeypatch.setattr(md, "version", lambda name: calls.append(name) or real(name))
    monkeypatch.setattr(store_mod, "_VERSIONS", None)
    first = store_mod.library_versions()
    assert first["numpy"] == np.__version__ and len(calls) == 7
    first["numpy"] = "changed by a caller"
    assert store_mod.library_versions()["numpy"] == np.__version__ and len(calls) == 7

    monkeypatch.setattr(store_mod, "_VERSIONS", None)
    store_mod.adopt_library_versions({"numpy": "1.0"})
    assert store_mod.library_versions() == {"numpy": "1.0"} and len(calls) == 7
    store_mod.adopt_library_versions({"numpy": "2.0"})
    assert store_mod.library_versions() == {"numpy": "1.0"}


@pytest.mark.parametrize("url", ["local", "memory://polyvec-failures"])
def test_failure_records_round_trip(tmp_path, url):
    """A task's failure on its input is filed under its key; an unreadable record is no record (the task
    runs again) and a record is not an artifact."""
    store = ArtifactStore(tmp_path / "store" if url == "local" else url)
    key = artifact_key("prep", "1", {"threshold": 0.6}, {"image": "abc"})
    assert store.failure("prep", key) is None
    store.save_failure("prep", key, {"stage": "prep", "key": key, "error": "not an image (unrecognised file format)"})
    assert store.failure("prep", key)["error"] == "not an image (unrecognised file format)"
    assert not store.exists("prep", key) and store.failure("field", key) is None
    assert not list(store.iter_manifests())
    if url == "local":
        (tmp_path / "store" / ".failures" / "prep" / key[:2] / f"{key}.json").write_text('{"error": ')
        assert store.failure("prep", key) is None
        assert not list((tmp_path / "store" / ".tmp").iterdir())
