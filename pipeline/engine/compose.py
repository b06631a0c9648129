"""The app's config composed once per set of config files and overrides, then read back from a cache.

Hydra's compose API (``initialize_config_module`` + ``compose``) costs about 0.2 s of every ``polyvec``
run, a twentieth of a one-image run from an empty store and half of a fully cached one. The composed
config is a pure function of the files of the ``conf`` package, the config name, the overrides and the
Hydra / OmegaConf versions, so it is pickled under a hash of them in the user's cache
(``$XDG_CACHE_HOME/polyvec/config``, default ``~/.cache/polyvec/config``) and unpickled (~1 ms) when
the same command line is run again on the same files. A command line that differs from a cached one only
in values of existing keys (``output=…``, ``store.path=…``, ``flow.lam=0.5``: a λ re-run, the next
drawing into another folder) starts from the cached composition of the other overrides and sets those
values with OmegaConf, through the same schema validation; anything else (a config group, a list, a new
key, a value the schema refuses) is composed by Hydra. Interpolations stay unresolved in the pickle, as
in a fresh composition (``${oc.env:…}`` reads the environment when it is accessed). Where the cache
cannot be written (a read-only home), or a cached file cannot be read, the config is composed as before.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import re
import uuid
from pathlib import Path

from omegaconf import DictConfig

from pipeline.engine.config import CONF_DIR

#: Cached configs kept; the oldest are removed beyond it (every distinct command line is one file of
#: about 20 kB).
MAX_ENTRIES = 64


def cache_dir() -> Path:
    """Where composed configs are cached."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "polyvec" / "config"


def _conf_root() -> Path:
    """The ``conf`` package Hydra composes from."""
    return CONF_DIR


def _files_digest() -> bytes:
    """Hash of the conf files (names and bytes) and the Hydra and OmegaConf versions.

    Hydra's version is read from its ``__init__.py`` (found, not imported: its import is ~50 ms that a
    cached line never needs), the file that declares ``__version__``.
    """
    import importlib.util

    import omegaconf

    spec = importlib.util.find_spec("hydra")
    hydra_init = Path(spec.origin).read_bytes() if spec is not None and spec.origin else b""
    h = hashlib.sha256(hydra_init + f"\0{omegaconf.__version__}\0".encode())
    root = _conf_root()
    for path in sorted(p for p in root.rglob("*") if p.is_file() and p.suffix in (".yaml", ".yml")):
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.digest()


def config_digest(config_name: str, overrides: list[str], files: bytes | None = None) -> str:
    """Hash of everything a composition depends on: the conf files (``files``, :func:`_files_digest`
    when not given), the config name and the overrides."""
    h = hashlib.sha256(files if files is not None else _files_digest())
    for part in (config_name, *overrides):
        h.update(part.encode() + b"\0")
    return h.hexdigest()[:32]


def compose_config(config_name: str, overrides: list[str]) -> DictConfig:
    """This app's config for ``overrides`` (Hydra's compose API), through the cache of compositions.

    Parameters
    ----------
    config_name : str
        The primary config of the ``conf`` package (``config``, ``bench_app``, …).
    overrides : list of str
        Plain ``key=value`` overrides, as on the command line.

    Returns
    -------
    omegaconf.DictConfig
        The composed config, equal to a fresh composition.
    """
    overrides = list(overrides)
    files = _files_digest()           # read once for both entries below
    where = _entry(config_name, overrides, files)
    cfg = _read(where)
    if cfg is not None:
        return cfg
    rest, values = _value_overrides(overrides)
    if values:
        base = _entry(config_name, rest, files)
        cfg = _read(base)
        if cfg is None:
            try:
                cfg = _compose(config_name, rest)
            except Exception:  # noqa: BLE001 - the whole line's composition below says what is wrong
                cfg = None
            else:
                _store(base, cfg)          # the base of later lines that change only these values
        if cfg is not None and _set_values(cfg, values):
            _store(where, cfg)
            return cfg
    cfg = _compose(config_name, overrides)
    _store(where, cfg)
    return cfg


def cached_config(config_name: str, overrides: list[str], files: bytes | None = None) -> DictConfig | None:
    """The cached composition of exactly this config name and these overrides, or None; imports no Hydra.

    Only plain command lines (overrides of one job: no flag, no sweep, no ``hydra.`` key) are ever
    cached, so a hit is also one: the CLI takes it without parsing the line with Hydra.
    """
    return _read(_entry(config_name, list(overrides), files))


def _entry(config_name: str, overrides: list[str], files: bytes | None) -> Path:
    return cache_dir() / f"{config_digest(config_name, overrides, files)}.pkl"


def _compose(config_name: str, overrides: list[str]) -> DictConfig:
    from hydra import compose, initialize_config_module

    with initialize_config_module(config_module="conf", version_base=None):
        return compose(config_name, overrides=overrides)


def _read(where: Path) -> DictConfig | None:
    try:
        with open(where, "rb") as f:
            cfg = pickle.load(f)
    except Exception:  # noqa: BLE001 - no entry, or one from another Python: compose it again
        return None
    if not isinstance(cfg, DictConfig):
        return None
    try:
        os.utime(where)                     # recently used: kept by the eviction of _store
    except OSError:
        pass
    return cfg


_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")
_INT = re.compile(r"[+-]?(0|[1-9][0-9]*)")
_FLOAT = re.compile(r"[+-]?(0|[1-9][0-9]*)\.[0-9]+")
_WORD = re.compile(r"[A-Za-z_/][A-Za-z0-9_./-]*")
_WORDS = {"true": True, "false": False, "null": None}
_TYPED_WORDS = (*_WORDS, "inf", "nan")   # Hydra types these in any case (``True``, ``NaN``): not plain words


def plain_values(overrides: list[str]) -> list[tuple[str, object]] | None:
    """``(key, value)`` of every override when all are ``key=value`` of the simplest kinds, as Hydra's
    override grammar reads them, without importing Hydra (its parser costs ~0.13 s of a λ re-run);
    None when any is not (Hydra parses the line then).

    The kinds: a dotted key of identifiers, not Hydra's own (``hydra.…``); a value that is a decimal int
    (``-3``, ``12``), a decimal with a point (``0.25``), ``true``, ``false``, ``null``, or a word or path of letters, digits and
    ``_ . / -`` that starts with a letter, ``_`` or ``/`` and is not one of Hydra's ``inf`` / ``nan``.
    """
    out = []
    for text in overrides:
        key, eq, value = text.partition("=")
        if not eq or not _KEY.fullmatch(key) or key.split(".")[0] == "hydra":
            return None
        if _INT.fullmatch(value):
            out.append((key, int(value)))
        elif _FLOAT.fullmatch(value):
            out.append((key, float(value)))
        elif value in _WORDS:
            out.append((key, _WORDS[value]))
        elif _WORD.fullmatch(value) and value.lower() not in _TYPED_WORDS:
            out.append((key, value))
        else:
            return None
    return out


def _value_overrides(overrides: list[str]) -> tuple[list[str], list[tuple[str, object]]]:
    """Split the overrides into the rest and ``(key, value)`` changes of one key (not a config group) to
    a plain value (number, string, bool, null): the overrides :func:`_set_values` may apply to a cached
    base."""
    groups = {p.name for p in _conf_root().iterdir() if p.is_dir()}     # `runtime=local` picks a file
    simple = plain_values(overrides)
    if simple is not None:
        rest = [text for text, (key, _) in zip(overrides, simple) if key in groups]
        return rest, [(key, value) for key, value in simple if key not in groups]
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import OverrideType, ValueType

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except Exception:  # noqa: BLE001 - Hydra's compose reports it
        return overrides, []
    rest, values = [], []
    for text, o in zip(overrides, parsed):
        plain = (o.type == OverrideType.CHANGE and o.package is None and o.value_type == ValueType.ELEMENT
                 and ("." in o.key_or_group or o.key_or_group not in groups))
        if plain and (o.value() is None or isinstance(o.value(), (str, int, float))):
            values.append((o.key_or_group, o.value()))
        else:
            rest.append(text)
    return rest, values


def _set_values(cfg: DictConfig, values: list[tuple[str, object]]) -> bool:
    """Set existing plain keys in place (OmegaConf validates them against the schema); False when a key
    is missing or not a plain value, or a value is refused (Hydra's compose then says why)."""
    from omegaconf import OmegaConf

    for key, value in values:
        parent, _, leaf = key.rpartition(".")
        node = OmegaConf.select(cfg, parent) if parent else cfg
        if not isinstance(node, DictConfig) or leaf not in node or OmegaConf.is_config(node[leaf]):
            return False
        try:
            node[leaf] = value
        except Exception:  # noqa: BLE001 - a value the schema refuses
            return False
    return True


def _store(where: Path, cfg: DictConfig) -> None:
    """Write one entry atomically and keep the newest :data:`MAX_ENTRIES`; a failure only skips it."""
    try:
        where.parent.mkdir(parents=True, exist_ok=True)
        tmp = where.with_name(f".{uuid.uuid4().hex}.tmp")
        with open(tmp, "wb") as f:
            pickle.dump(cfg, f, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(tmp, where)
        entries = sorted(where.parent.glob("*.pkl"), key=lambda p: p.stat().st_mtime)
        for old in entries[:-MAX_ENTRIES]:
            old.unlink(missing_ok=True)
    except OSError:
        pass
