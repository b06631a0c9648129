"""The Python API: :func:`vectorize` one drawing — a path, bytes, a PIL image or a numpy array — in this process.

It is the ``polyvec`` command line without the console: the config is composed from the same files and
overrides (:func:`pipeline.engine.compose.compose_config`), the drawing runs through the same stage DAG
and the same artifact store (``store.path``, ``artifacts/`` of the working directory by default), so a
drawing the command line vectorised is read back here, and the other way round.

Examples
--------
>>> from pipeline import vectorize
>>> result = vectorize("drawing.png", "flow.lam=0.5")      # doctest: +SKIP
>>> result.svg, result.curves, result.keypoints             # doctest: +SKIP
"""

from __future__ import annotations

import hashlib
import io
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stages.errors import InputError

#: Overrides the API adds unless the caller sets the same key (why: :func:`vectorize`'s notes).
API_DEFAULTS = ("runtime.cluster=sync", "runtime.keypoints_process=false", "runtime.progress=false")
#: The folder of the store (a local one) that holds non-path inputs as files, named by their content.
INPUTS_FOLDER = ".inputs"
#: How the engine's failures that are not the input's fault begin (the executors' and node's words).
NOT_THE_INPUT = ("internal error", "worker lost", "out of memory")


class VectorizationError(RuntimeError):
    """A stage failed on the drawing for a reason other than the input (an internal error, a lost worker
    process, out of memory).

    Attributes
    ----------
    detail : str or None
        The stage's traceback, for a bug report.
    """

    def __init__(self, message: str, detail: str | None = None):
        super().__init__(message)
        self.detail = detail


@dataclass(repr=False, eq=False)   # eq: the curves hold numpy arrays, which == cannot compare as a whole
class Vectorization:
    """What :func:`vectorize` returns: the drawing's curves, keypoints and SVG, in the drawing's pixels.

    Attributes
    ----------
    source : str
        The image file that was vectorised (for bytes, a PIL image or an array: its PNG in the store's
        ``.inputs`` folder, named by its content).
    svg : str or None
        The SVG document (``polyvec``'s ``.svg`` file); None when ``runtime.until`` stops before export.
    curves : list of dict
        One per curve, as in ``polyvec``'s ``.json`` file, except that ``points`` is a float64 (N, 2)
        numpy array of (x, y) in the drawing's pixels (``plt.plot(*c["points"].T)``); ``end_types``
        (1 endpoint, 3 junction, 5 corner, 0 an end at no keypoint), ``end_keypoints`` (indices into
        :attr:`keypoints`, −1 for none), ``width``, ``corners``, ``parts``.
    keypoints : list of tuple
        ``(x, y, type)`` of every keypoint the curves were fitted to (the detections after any
        ``<stem>.keypoints.json`` edits), in the drawing's pixels; type 1 endpoint, 3 junction, 5 corner.
    bezier_svg : str or None
        The cubic Bézier SVG with ``export.bezier=true``, else None.
    keys : dict
        Stage → key of its artifact in the store (``polyvec-inspect show STAGE KEY`` prints one).
    notes : list of str
        What the stages want a user to know (``"prep: inverted light strokes …"``), as the command line
        prints them.
    """

    source: str
    svg: str | None
    curves: list[dict]
    keypoints: list[tuple[float, float, int]]
    bezier_svg: str | None = None
    keys: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    _export: dict | None = None   # the export artifact's data, for :meth:`save` (JSON as the CLI writes it)

    def __repr__(self) -> str:
        # the dataclass's own repr would print the whole SVG text and every point
        export = self.keys.get("export", "")[:12] or "none"
        return (f"Vectorization({self.source!r}: {len(self.curves)} curves, {len(self.keypoints)} keypoints, "
                f"export {export})")

    def _repr_svg_(self) -> str | None:
        """The SVG, which Jupyter and IPython show as the cell's output."""
        return self.svg

    def save(self, path: str | os.PathLike) -> list[Path]:
        """Write ``<path>.svg`` and ``<path>.json`` (and ``<path>.bezier.svg``), as ``polyvec`` writes them.

        Parameters
        ----------
        path : str or path-like
            ``out/cat.svg`` or ``out/cat``; missing folders are made.

        Returns
        -------
        list of pathlib.Path
            The files written.

        Raises
        ------
        ValueError
            When the run stopped before export (``runtime.until``): there is nothing to write.
        """
        from pipeline.engine.execute.outputs import atomic_write, output_texts

        if self._export is None:
            raise ValueError("nothing to save: the run stopped before export (runtime.until)")
        path = Path(path)
        stem = path.with_suffix("") if path.suffix.lower() == ".svg" else path
        texts = output_texts(stem, self._export, self.source, self.keys.get("export"))
        stem.parent.mkdir(parents=True, exist_ok=True)
        for where, text in texts.items():
            atomic_write(where, text)
        return list(texts)


def vectorize(image: Any, *overrides: str, store: str | os.PathLike | None = None) -> Vectorization:
    """Vectorise one drawing in this process, through the same configs and artifact store as ``polyvec``.

    Parameters
    ----------
    image : str, path-like, bytes, PIL.Image.Image or numpy.ndarray
        An image file's path; the bytes of an image file (PNG, JPEG, …); a PIL image; or an array,
        (H, W) grey or (H, W, 3) RGB or (H, W, 4) RGBA, of uint8, uint16, or floats in [0, 1] (1 = white).
        Bytes, PIL images and arrays are stored as a file named by their content (see Notes).
    *overrides : str
        ``key=value`` settings exactly as on the command line (``"flow.lam=0.5"``,
        ``"export.bezier=true"``, ``"runtime.until=graph"``; the README's configuration table lists
        the groups). Strings rather than keyword arguments because that is the form the README, the
        config files' comments and ``polyvec --cfg job`` show, a line can be copied between shell and
        Python, and Hydra reads the values the same way (lists, ``null``, quoting). An unknown key or a
        value of the wrong type is a :class:`ValueError`, never a silent default.
    store : str or path-like, optional
        The artifact store: a folder or an fsspec URL; the same as ``"store.path=…"``. Default: the
        config's, ``artifacts/`` in the working directory, as ``polyvec``.

    Returns
    -------
    Vectorization
        ``.svg``, ``.curves``, ``.keypoints`` (and ``.bezier_svg``, ``.keys``, ``.notes``);
        ``.save("out/cat.svg")`` writes the command line's files. Shown as its SVG in a notebook.

    Raises
    ------
    stages.errors.InputError
        A ``ValueError``: the image cannot be read (not an image, an empty or ill-typed array, a missing
        file), or a setting is out of its range. One line; the stage's message.
    ValueError
        An override that does not compose (an unknown key, a value of the wrong type).
    TypeError
        ``image`` is of none of the accepted types.
    VectorizationError
        A stage failed for another reason (an internal error, whose traceback ``.detail`` holds; a lost
        worker; out of memory).

    Notes
    -----
    The run is in-process (``runtime.cluster=sync``) with the keypoint network on a thread of this
    process (``runtime.keypoints_process=false``), unless an override says otherwise: worker or child
    processes are *spawned*, which re-runs a script's top level in them (a script without an
    ``if __name__ == "__main__":`` guard would fail), and on a thread the network and torch are loaded
    once per session, not once per call. No progress bars (``runtime.progress=false``).

    Bytes, a PIL image or an array are written once, as a file named by the SHA-256 of its content (an
    array or a PIL image as PNG, bytes as they are), to the store's ``.inputs`` folder (a temporary
    folder for a store at a URL). The store's keys hash the image file's bytes, so the same array
    vectorised again is read back from the store, computing nothing, and so is its file given by path.
    A PIL image keeps its EXIF data (orientation, focal length), so it gives what its file gives.
    """
    from pipeline.engine.compose import compose_config
    from pipeline.engine.execute.batch import run_batch
    from pipeline.engine.store import ArtifactStore

    overrides = [str(o) for o in overrides]
    if store is not None:
        overrides.append(f"store.path={os.fspath(store)}")
    given = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    line = [d for d in API_DEFAULTS if d.split("=", 1)[0] not in given] + overrides
    cfg = _compose(compose_config, line)
    artifacts = ArtifactStore(str(cfg.store.path))
    source, cached_input = _image_file(image, artifacts)
    batch = run_batch([source], cfg, store=artifacts, on_compile=_say_compiling)
    failed = batch.failed_images.get(source)
    if failed is not None:
        stage, _, _ = failed.partition(":")
        result = batch.results[source].get(stage.strip())
        if cached_input and stage == "prep":
            Path(source).unlink(missing_ok=True)    # not a readable image: keep no file of it
        message = f"{_shown(image, source)}: {failed}"
        if result is None or result.detail or (result.error or "").startswith(NOT_THE_INPUT):
            raise VectorizationError(message, result.detail if result is not None else None)
        raise InputError(message)    # the stage's own InputError: what was wrong with the image or a setting
    keys = batch.keys(source)
    return _result(source, {s: keys[s] for s in batch.stages if s in keys}, artifacts)   # DAG order


# -- the config --------------------------------------------------------------------------------
def _compose(compose_config, line: list[str]):
    """The composed config of ``line``; an error of Hydra's (an unknown key, a value of the wrong type, a
    line it cannot parse) as a ``ValueError`` of one line: its first line and its cause's."""
    from pipeline.hydra_command import config_error

    try:
        return compose_config("config", line)
    except Exception as exc:  # Hydra raises several kinds (others are re-raised)
        if not type(exc).__module__.startswith(("hydra", "omegaconf")):
            raise
        raise ValueError(f"the settings do not compose: {config_error(exc)}") from None


def _say_compiling(why: str) -> None:
    # the command line's line: a first run on a machine without fitting shipped kernels takes longer
    from pipeline.console import compile_message

    print(compile_message(why), file=sys.stderr)


def _shown(image: Any, source: str) -> str:
    """How an error names the input: its path, or what kind of object it was."""
    if isinstance(image, (str, os.PathLike)):
        return str(source)
    if isinstance(image, np.ndarray):
        return f"the array {image.shape} {image.dtype}"
    return f"the {type(image).__name__} input"


# -- the input as a file -----------------------------------------------------------------------
def _image_file(image: Any, store) -> tuple[str, bool]:
    """The file to vectorise and whether it was written here (bytes, a PIL image, an array).

    Raises
    ------
    InputError
        Empty bytes, an empty or ill-shaped array, an array of an unsupported dtype.
    TypeError
        An object of none of the accepted types.
    """
    if isinstance(image, (str, os.PathLike)):
        return os.fspath(image), False
    if isinstance(image, (bytes, bytearray, memoryview)):
        content, suffix = bytes(image), _suffix(bytes(image))
    elif _is_pil(image):
        content, suffix = _pil_png(image), ".png"
    elif isinstance(image, np.ndarray):
        content, suffix = _array_png(image), ".png"
    else:
        raise TypeError(f"cannot vectorise an object of type {type(image).__name__!r}: give a path, the bytes "
                        "of an image file, a PIL image or a numpy array")
    if not content:
        raise InputError("empty bytes: not an image")
    folder = (Path(store.root) / INPUTS_FOLDER if store.local
              else Path(tempfile.gettempdir()) / "polyvec-inputs")
    folder.mkdir(parents=True, exist_ok=True)
    where = folder / (hashlib.sha256(content).hexdigest() + suffix)
    if not where.is_file() or where.stat().st_size != len(content):
        from pipeline.engine.execute.outputs import atomic_write

        atomic_write(where, content)   # whole or absent: another process may vectorise the same array
    return str(where), True


def _suffix(content: bytes) -> str:
    """A suffix for an image file's bytes (for the reader of the folder: prep reads the content)."""
    from PIL import Image

    try:
        with Image.open(io.BytesIO(content)) as im:
            return "." + (im.format or "img").lower()
    except Exception:  # noqa: BLE001 - not an image Pillow knows: prep says what it is
        return ".img"


def _is_pil(image: Any) -> bool:
    pil = sys.modules.get("PIL.Image")    # an object of PIL's only when the caller imported PIL
    return pil is not None and isinstance(image, pil.Image)


def _pil_png(image) -> bytes:
    """A PIL image as PNG bytes, its EXIF kept (prep applies the orientation, reads the focal length)."""
    buf = io.BytesIO()
    exif = image.getexif()
    extra = {"exif": exif.tobytes()} if len(exif) else {}
    try:
        image.save(buf, "PNG", **extra)
    except (OSError, ValueError, KeyError):   # a mode PNG cannot hold (CMYK, F, …)
        buf = io.BytesIO()
        image.convert("RGBA" if "A" in image.getbands() else "RGB").save(buf, "PNG", **extra)
    return buf.getvalue()


def _array_png(a: np.ndarray) -> bytes:
    """An image array as PNG bytes: grey (H, W), RGB (H, W, 3) or RGBA (H, W, 4); 1 or 255 = white.

    uint8 as it is; uint16 grey as a 16-bit PNG (colour: its high bytes); floats in [0, 1] as a 16-bit
    grey PNG (colour: 8 bits); other integers when their values fit uint8.

    Raises
    ------
    InputError
        An empty array, another shape, a dtype of none of those kinds, floats outside [0, 1] or NaN.
    """
    from PIL import Image

    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)):
        raise InputError(f"an image array is (H, W), (H, W, 3) or (H, W, 4), not {a.shape}")
    if a.size == 0:
        raise InputError(f"empty image array {a.shape}")
    kind = a.dtype.kind
    if kind == "f":
        if not np.isfinite(a).all() or a.min() < 0 or a.max() > 1:
            raise InputError("a float image array holds values in [0, 1] (1 = white); this one has "
                             f"{'NaN or inf' if not np.isfinite(a).all() else f'{a.min():g} … {a.max():g}'}")
        a = (np.round(a * 65535).astype(np.uint16) if a.ndim == 2
             else np.round(a * 255).astype(np.uint8))
    elif kind in "iu" and a.dtype != np.uint16:
        if a.min() < 0 or a.max() > 255:
            raise InputError(f"an integer image array other than uint16 holds 0 … 255; this {a.dtype} one has "
                             f"{a.min()} … {a.max()}")
        a = a.astype(np.uint8)
    elif a.dtype == np.uint16 and a.ndim == 3:
        a = (a >> 8).astype(np.uint8)   # Pillow writes no 16-bit colour PNG
    elif a.dtype != np.uint16:
        raise InputError(f"an image array is uint8, uint16 or float in [0, 1], not {a.dtype}")
    a = np.ascontiguousarray(a)
    im = Image.fromarray(a)   # uint16 (H, W): a 16-bit grey ("I;16")
    buf = io.BytesIO()
    im.save(buf, "PNG")
    return buf.getvalue()


# -- the result --------------------------------------------------------------------------------
def _result(source: str, keys: dict[str, str], store) -> Vectorization:
    """The :class:`Vectorization` of a drawing's stored artifacts (``keys``: stage → key)."""
    export = store.load_data("export", keys["export"]) if "export" in keys else None
    curves = []
    for c in (export or {}).get("curves", []):
        c = dict(c)
        c["points"] = np.asarray(c["points"], np.float64).reshape(-1, 2)
        curves.append(c)
    notes = [f"{stage}: {note}" for stage, key in keys.items()
             for note in store.manifest(stage, key).get("warnings", [])]
    return Vectorization(source=source, svg=export["svg"] if export else None, curves=curves,
                         keypoints=_keypoints(store, keys), bezier_svg=(export or {}).get("bezier_svg") or None,
                         keys=dict(keys), notes=notes, _export=export)


def _keypoints(store, keys: dict[str, str]) -> list[tuple[float, float, int]]:
    """The keypoints the curves were fitted to, in the drawing's pixels.

    Those of keypoint_edits (the detections after the user's edits: the list the curves'
    ``end_keypoints`` index), else the detections; the stages hold them in internal pixels, which
    :func:`stages.prep.to_source` maps back with the keypoints artifact's scale, crop and pieces.
    """
    from stages.prep import to_source

    if "keypoints" not in keys:
        return []
    detected = store.load_data("keypoints", keys["keypoints"])   # not its heatmaps
    points = (store.load_data("keypoint_edits", keys["keypoint_edits"]) if "keypoint_edits" in keys
              else detected)["points"]
    if not points:
        return []
    xy = to_source([(p["x"], p["y"]) for p in points], detected)
    return [(float(x), float(y), int(p["type"])) for (x, y), p in zip(xy, points)]
