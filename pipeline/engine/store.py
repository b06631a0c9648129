"""Content-addressed artifact store: zarr arrays + JSON data + a manifest per artifact.

Layout under the store root::

    <stage>/<key[:2]>/<key>/arrays.zarr     one zarr v3 group, one array per artifact array
    <stage>/<key[:2]>/<key>/data.json       the artifact's small structured data
    <stage>/<key[:2]>/<key>/manifest.json   stage, version, config, inputs, timings, library versions
    .items/<stage>/<image key>/<uuid>.pack  per-item results of a per-item stage (the flow's paths),
                                            one pack per computation, reused across artifacts
                                            (:mod:`pipeline.engine.execute.node`)
    .failures/<stage>/<key[:2]>/<key>.json  a task that failed on its input (not an image, no ink):
                                            the error, under the key its artifact would have had
    .tmp/<uuid>/                            artifacts being written

An artifact is written completely into ``.tmp/<uuid>`` and then renamed into place. A rename of a
directory is atomic on a local file system, so a reader either sees the whole artifact or nothing: a
run killed half-way (Ctrl-C, ``kill -9``) leaves only an orphan under ``.tmp`` that is never read and
is swept at the next run. On an fsspec URL (``memory://``, ``s3://`` …) the manifest is written last
and an artifact only counts as present when its manifest is, which gives the same guarantee for
readers that go through this class. A per-item result is a few bytes (its arrays' names, dtypes and
shapes as JSON, their bytes, and a BLAKE2b digest of all that); the results one task computed are
written together, as one *pack* (an index of item keys and sizes, then the results), to ``.tmp`` and
renamed the same way — one file, not one per item: 333 small files took 0.1–0.3 s of the elephant's
default run on this project's machine. A lookup reads the index of each pack of one image and only the
results it wants (a sweep of ten λ values leaves ten packs, ~0.7 MB each for the elephant's 333 paths). A result that is missing or unreadable
(truncated, corrupted: the digest) is simply absent, and the engine computes the item again. (Stores
written before packs kept one file per result under ``.items/<stage>/<key[:2]>/``; nothing reads them,
and the next run's :meth:`ArtifactStore.sweep_tmp` removes them.)

A task that fails on its input (:class:`stages.errors.InputError`: a junk file, a blank page) leaves a
*failure record* instead of an artifact, filed under the task's key: the key already hashes the image's
bytes, the stage's version and its config section (:func:`artifact_key`), so the next run of the same
command finds the record and reports the failure without running anything for the image, and a changed
file, config or stage version is a new key, tried again (:meth:`ArtifactStore.save_failure`).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
import uuid
from pathlib import Path
from typing import Any, BinaryIO, Iterator

import numpy as np

from stages.artifact import Artifact

MANIFEST = "manifest.json"
ITEMS = ".items"
FAILURES = ".failures"
ITEM_MAGIC = b"polyvec-item 1\n"
PACK_MAGIC = b"polyvec-items 1\n"
DATA = "data.json"
ARRAYS = "arrays.zarr"


def canonical_json(obj: Any) -> str:
    """Deterministic JSON text (sorted keys, no whitespace) used for hashing."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=_json_default)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def hash_bytes(data: bytes) -> str:
    """Key of an input image: SHA-256 of its bytes (first 32 hex digits)."""
    return hashlib.sha256(data).hexdigest()[:32]


def artifact_key(stage: str, version: str, config: Any, inputs: dict[str, str]) -> str:
    """Key of a stage artifact: hash of stage name, version, its config section and input keys."""
    payload = canonical_json({"stage": stage, "version": version, "config": config, "inputs": inputs})
    return hashlib.sha256(payload.encode()).hexdigest()[:32]


def item_keys(stage: str, version: str, context: Any, inputs: dict[str, str],
              items: list[tuple[np.ndarray, ...]]) -> list[str]:
    """Keys of the items of a per-item stage (:class:`stages.artifact.ItemPlan`).

    Each hashes the stage, its version, the plan's context, the keys of the inputs every item depends
    on, and the item's own arrays (dtype, shape and bytes).
    """
    head = hashlib.sha256(canonical_json({"stage": stage, "version": version, "context": context,
                                          "inputs": inputs}).encode())
    keys = []
    for item in items:
        h = head.copy()
        for a in item:
            a = np.ascontiguousarray(a)
            h.update(f"|{a.dtype.str}{a.shape}|".encode())
            h.update(a.tobytes())
        keys.append(h.hexdigest()[:32])
    return keys


def library_versions() -> dict[str, str]:
    """Versions of the libraries whose behaviour can change results (a copy of this process's record).

    Looked up once per process: its libraries do not change while it runs, and every task's manifest
    asks (``importlib.metadata`` parses the packages' metadata: 0.09–0.15 s the first time, 20–30 ms
    each time after, in every task; stages/DECISIONS.md, engine).
    """
    global _VERSIONS
    if _VERSIONS is None:
        _VERSIONS = _installed_versions()
    return dict(_VERSIONS)


def adopt_library_versions(versions: dict[str, str]) -> None:
    """Take as this process's :func:`library_versions` those its parent found: a process spawned from
    the same interpreter and installation (the keypoints child), which is spared the lookup."""
    global _VERSIONS
    if _VERSIONS is None:
        _VERSIONS = dict(versions)


_VERSIONS: dict[str, str] | None = None


def _installed_versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {}
    for name in ("numpy", "scipy", "torch", "scikit-image", "pulp", "zarr", "numba"):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            pass
    return out


def encode_item(arrays: dict[str, np.ndarray]) -> bytes:
    """One per-item result as bytes: magic, header length, JSON header, array bytes, 16-byte digest.

    A few hundred small results are read per run: a zip (``.npz``) cost ten times more to read.
    """
    parts = [np.asarray(a) for a in arrays.values()]  # tobytes() writes C order; 0-d arrays stay 0-d
    header = json.dumps([[name, a.dtype.str, list(a.shape)] for name, a in zip(arrays, parts)]).encode()
    body = b"".join([ITEM_MAGIC, len(header).to_bytes(4, "little"), header, *(a.tobytes() for a in parts)])
    return body + hashlib.blake2b(body, digest_size=16).digest()


def decode_item(raw: bytes) -> dict[str, np.ndarray]:
    """Inverse of :func:`encode_item` (read-only arrays); ``ValueError`` when the bytes are not one intact."""
    body, digest = raw[:-16], raw[-16:]
    if not body.startswith(ITEM_MAGIC) or hashlib.blake2b(body, digest_size=16).digest() != digest:
        raise ValueError("not an intact per-item result")
    at = len(ITEM_MAGIC) + 4
    end = at + int.from_bytes(body[len(ITEM_MAGIC):at], "little")
    out = {}
    for name, dtype, shape in json.loads(body[at:end]):
        a = np.frombuffer(body, dtype=dtype, count=int(np.prod(shape)), offset=end).reshape(shape)
        end += a.nbytes
        out[name] = a
    return out


def encode_pack(items: list[tuple[str, dict[str, np.ndarray]]]) -> bytes:
    """Per-item results as one pack: magic, index length, JSON index ``[[key, size], ...]``, the
    results (:func:`encode_item`, each with its own digest) one after the other."""
    blobs = [encode_item(arrays) for _, arrays in items]
    index = json.dumps([[key, len(b)] for (key, _), b in zip(items, blobs)]).encode()
    return b"".join([PACK_MAGIC, len(index).to_bytes(4, "little"), index, *blobs])


def read_pack(f: BinaryIO, wanted: set[str]) -> dict[str, dict[str, np.ndarray]]:
    """The intact results of ``wanted`` keys in a pack open for reading (binary, seekable).

    Only the index and the wanted results are read, so a lookup costs what it finds, not the size of
    every pack of the image. A torn or corrupted result is left out; an unreadable index gives nothing.
    """
    head = f.read(len(PACK_MAGIC) + 4)
    if len(head) < len(PACK_MAGIC) + 4 or not head.startswith(PACK_MAGIC):
        return {}
    n = int.from_bytes(head[len(PACK_MAGIC):], "little")
    try:
        index = json.loads(f.read(n))
        entries = [(str(e[0]), int(e[1])) for e in index]
    except (ValueError, TypeError, IndexError, KeyError):
        return {}
    out: dict[str, dict[str, np.ndarray]] = {}
    offset = len(head) + n
    for key, size in entries:
        if key in wanted and key not in out:
            f.seek(offset)
            try:
                out[key] = decode_item(f.read(size))
            except (ValueError, TypeError):
                pass
        offset += size
    return out


def _only_fill(a: np.ndarray, fill: Any) -> bool | None:
    """Whether every element of ``a`` equals a zero ``fill`` as zarr's test of an empty chunk finds it
    (floats by bit pattern, −0.0 not 0.0; complex by value, −0 equal; NaN never), without a copy of
    ``a``; None for another fill value or a dtype other than bool, integer, float and complex."""
    kind, size = a.dtype.kind, a.dtype.itemsize
    if kind not in "biufc" or (kind == "f" and size not in (2, 4, 8)) or \
            np.asarray(fill, a.dtype).tobytes() != bytes(size):
        return None
    return not np.count_nonzero(a.view(f"u{size}") if kind == "f" else a)


class ArtifactStore:
    """A content-addressed store on a local path or an fsspec URL.

    Parameters
    ----------
    root : str or Path
        Local directory, or a URL such as ``memory://polyvec`` or ``s3://bucket/prefix``.
    create : bool
        Create the store when it does not exist; False (readers such as ``polyvec-inspect``) raises
        FileNotFoundError instead.
    """

    def __init__(self, root: str | os.PathLike, create: bool = True):
        import fsspec

        root = str(root)
        self.fs, path = fsspec.core.url_to_fs(root)
        self.local = self.fs.protocol in ("file", ("file", "local")) or "file" in np.atleast_1d(self.fs.protocol)
        self.root = os.path.abspath(path) if self.local else path.rstrip("/")
        # The URL handed to worker processes: a local path made absolute, since a worker resolves a
        # relative one in its own working directory (a remote scheduler's workers run elsewhere).
        self.url = self.root if self.local else root
        self.created = not self.fs.exists(self.root)
        if self.created and not create:
            raise FileNotFoundError(f"no artifact store at {self.url}")
        self.fs.makedirs(self.root, exist_ok=True)

    def remove_if_unused(self) -> None:
        """Remove the store's folder again when this object created it and nothing was written."""
        if self.created and self.local and os.path.isdir(self.root) and not os.listdir(self.root):
            os.rmdir(self.root)

    # -- paths ---------------------------------------------------------------------------------
    def _join(self, *parts: str) -> str:
        return os.path.join(self.root, *parts) if self.local else "/".join([self.root, *parts])

    def path_for(self, stage: str, key: str) -> str:
        """Directory (or URL path) of an artifact."""
        return self._join(stage, key[:2], key)

    def exists(self, stage: str, key: str) -> bool:
        """Whether a complete artifact is stored under this key."""
        return self.fs.exists(self._join(stage, key[:2], key, MANIFEST))

    # -- writing -------------------------------------------------------------------------------
    def save(self, stage: str, key: str, artifact: Artifact, manifest: dict) -> None:
        """Write an artifact atomically (temporary directory, then rename into place)."""
        final = self.path_for(stage, key)
        if self.exists(stage, key):
            return
        tmp = self._join(".tmp", uuid.uuid4().hex)
        self.fs.makedirs(tmp, exist_ok=True)
        try:
            self._write_arrays(tmp, artifact.arrays)
            with self.fs.open(f"{tmp}/{DATA}", "w") as f:
                # one json.dumps call: the C encoder (json.dump streams through the pure-Python one,
                # ~1 s for the megabytes of topology paths of a 700-px drawing)
                f.write(json.dumps(artifact.data, default=_json_default))
            manifest = dict(manifest, arrays={k: {"shape": list(v.shape), "dtype": str(v.dtype)}
                                              for k, v in artifact.arrays.items()},
                            nbytes=artifact.nbytes(), written_at=time.time())
            with self.fs.open(f"{tmp}/{MANIFEST}", "w") as f:
                json.dump(manifest, f, indent=1, default=_json_default)
            self.fs.makedirs(self._join(stage, key[:2]), exist_ok=True)
            if self.local:
                try:
                    os.rename(tmp, final)
                except OSError:
                    # Another worker finished the same key first: identical content, keep theirs.
                    if not self.exists(stage, key):
                        raise
            else:
                self.fs.mv(tmp, final, recursive=True)
        finally:
            if self.fs.exists(tmp):
                self.fs.rm(tmp, recursive=True)

    def save_failure(self, stage: str, key: str, record: dict) -> None:
        """Record that the task ``key`` of ``stage`` failed on its input, so that the next run with the
        same key reports it without running the stage (:meth:`failure`); written whole or not at all.

        Parameters
        ----------
        stage, key : str
            The task's stage and key (:func:`artifact_key`).
        record : dict
            JSON-able; ``record["error"]`` is the one line the run printed.
        """
        self.fs.makedirs(self._join(FAILURES, stage, key[:2]), exist_ok=True)
        self._put_file(self._join(FAILURES, stage, key[:2], f"{key}.json"),
                       json.dumps(record, default=_json_default).encode())

    def _put_file(self, final: str, raw: bytes) -> None:
        """Write one file whole or not at all: locally through ``.tmp`` and a rename; on an fsspec
        back-end in one piece (they write an object at once; a torn pack fails its digests anyway)."""
        if not self.local:
            with self.fs.open(final, "wb") as f:
                f.write(raw)
            return
        self.fs.makedirs(self._join(".tmp"), exist_ok=True)
        tmp = self._join(".tmp", f"{uuid.uuid4().hex}.part")
        try:
            with open(tmp, "wb") as f:
                f.write(raw)
            os.replace(tmp, final)
        finally:
            if os.path.exists(tmp):
                os.remove(tmp)

    def failure(self, stage: str, key: str) -> dict | None:
        """The failure record of a task (:meth:`save_failure`), None when it has none or it is unreadable."""
        try:
            with self.fs.open(self._join(FAILURES, stage, key[:2], f"{key}.json"), "r") as f:
                record = json.load(f)
        except (OSError, ValueError):
            return None
        return record if isinstance(record, dict) and isinstance(record.get("error"), str) else None

    def _write_arrays(self, path: str, arrays: dict[str, np.ndarray]) -> None:
        import zarr

        group = zarr.open_group(self._zarr_store(f"{path}/{ARRAYS}", read_only=False), mode="w")
        for name, value in arrays.items():
            a = np.ascontiguousarray(value)
            chunks = tuple(max(1, s) for s in a.shape)
            array = group.create_array(name, shape=a.shape, dtype=a.dtype, chunks=chunks)
            # zarr writes no chunk that equals the fill value, found by np.array_equal, which copies a float
            # or complex array twice (+110 MB to save a 4x4 page's extension): the same test without copies
            # (_only_fill), and zarr told to write the array it is given, so the files are the same
            only_fill = _only_fill(a, array.fill_value)
            if only_fill is None:  # a dtype or fill value _only_fill does not know: zarr's own test
                array[...] = a
            elif not only_fill:
                array.with_config({"write_empty_chunks": True})[...] = a

    def _zarr_store(self, path: str, read_only: bool):
        if self.local:
            return path
        from zarr.storage import FsspecStore

        protocol = self.fs.protocol if isinstance(self.fs.protocol, str) else self.fs.protocol[0]
        return FsspecStore.from_url(f"{protocol}://{path}", read_only=read_only)

    def save_items(self, stage: str, scope: str, items: list[tuple[str, dict[str, np.ndarray]]]) -> None:
        """Write per-item results as one pack, atomically (a temporary file renamed into place).

        Parameters
        ----------
        stage : str
        scope : str
            Where the pack is filed (the image's key): :meth:`load_items` reads the packs of one scope.
        items : list of (str, dict of str to numpy.ndarray)
            Each result's key (:func:`item_keys`) and arrays.
        """
        if not items:
            return
        self.fs.makedirs(self._join(ITEMS, stage, scope), exist_ok=True)
        self._put_file(self._join(ITEMS, stage, scope, f"{uuid.uuid4().hex}.pack"), encode_pack(items))

    def load_items(self, stage: str, scope: str, keys: list[str]) -> list[dict[str, np.ndarray] | None]:
        """The stored results of ``keys`` (None where missing or unreadable: computed again)."""
        wanted = set(keys)
        found: dict[str, dict[str, np.ndarray]] = {}
        try:
            packs = sorted(self.fs.ls(self._join(ITEMS, stage, scope), detail=False))
        except (FileNotFoundError, NotADirectoryError):
            packs = []
        for pack in packs:
            left = wanted - found.keys()
            if not left:
                break
            if not str(pack).endswith(".pack"):
                continue
            try:
                with self.fs.open(pack, "rb") as f:
                    found.update(read_pack(f, left))
            except OSError:
                continue
        return [found.get(k) for k in keys]

    # -- reading -------------------------------------------------------------------------------
    def load(self, stage: str, key: str) -> Artifact:
        """Read an artifact; raises ``KeyError`` when it is not (completely) stored."""
        if not self.exists(stage, key):
            raise KeyError(f"{stage}/{key} is not in the store {self.url}")
        path = self.path_for(stage, key)
        data = self.load_data(stage, key)
        arrays = {}
        manifest = self.manifest(stage, key)
        if manifest.get("arrays"):
            import zarr  # not for an artifact of JSON alone (export: a cached run imports no zarr)

            group = zarr.open_group(self._zarr_store(f"{path}/{ARRAYS}", read_only=True), mode="r")
            for name in manifest["arrays"]:
                arrays[name] = group[name][...]
        return Artifact(arrays=arrays, data=data)

    def load_data(self, stage: str, key: str) -> dict:
        """An artifact's JSON data alone, its arrays not read (the keypoints' heatmaps are 4 × H × W floats)."""
        with self.fs.open(f"{self.path_for(stage, key)}/{DATA}", "r") as f:
            return json.load(f)

    def manifest(self, stage: str, key: str) -> dict:
        """The manifest of a stored artifact."""
        with self.fs.open(self._join(stage, key[:2], key, MANIFEST), "r") as f:
            return json.load(f)

    def iter_manifests(self) -> Iterator[tuple[str, str, dict]]:
        """Yield ``(stage, key, manifest)`` for every stored artifact."""
        for path in self.fs.glob(self._join("*", "*", "*", MANIFEST)):
            parts = str(path).rstrip("/").split("/")
            stage, key = parts[-4], parts[-2]
            if stage.startswith("."):
                continue
            try:
                with self.fs.open(path, "r") as f:
                    yield stage, key, json.load(f)
            except (OSError, json.JSONDecodeError):
                continue

    def size_bytes(self, stage: str, key: str) -> int:
        """Bytes on disk of one artifact."""
        return int(sum(self.fs.du(self.path_for(stage, key), total=False).values()))

    def sweep_tmp(self, older_than_s: float = 3600.0) -> int:
        """Remove abandoned temporary directories (from killed runs) older than ``older_than_s``, and the
        one-file per-item results of stores written before packs (never read: their prefix folders,
        ``.items/<stage>/<key[:2]>/``, are the only two-character names there; the 256 possible names
        are probed, so every run pays the same ~0.3 ms however many images the store holds)."""
        if not self.local:
            return 0
        n = 0
        items = self._join(ITEMS)
        for stage in (os.scandir(items) if os.path.isdir(items) else ()):
            for prefix in (f"{i:02x}" for i in range(256)):
                old = os.path.join(stage.path, prefix)
                if os.path.isdir(old):
                    shutil.rmtree(old, ignore_errors=True)
                    n += 1
        tmp = self._join(".tmp")
        if not os.path.isdir(tmp):
            return n
        now = time.time()
        for entry in os.scandir(tmp):
            try:
                if now - entry.stat().st_mtime > older_than_s:
                    if entry.is_dir(follow_symlinks=False):
                        shutil.rmtree(entry.path, ignore_errors=True)
                    else:  # a pack of per-item results being written
                        os.remove(entry.path)
                    n += 1
            except OSError:
                pass
        return n
