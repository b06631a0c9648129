"""The machinery the Hydra commands share (``polyvec``, ``polyvec-bench``, ``polyvec-train``): paths told
from overrides, overrides checked before any work, plain sweeps run without Hydra's multirun, one-line
usage errors, exit statuses across a sweep's jobs, Ctrl-C in one line, and an exit without teardown.
"""

from __future__ import annotations

import os
import re
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from pipeline.console import PROGRESS
from pipeline.engine.config import CONF_DIR
from pipeline.engine.execute.dask_cluster import ClusterError
from pipeline.engine.registry import StageUnavailable

if TYPE_CHECKING:   # the keypoints child imports this module again (spawn): it needs no omegaconf
    from omegaconf import DictConfig


class UsageError(Exception):
    """A problem with the command line, reported as one line."""


#: The running job's folder name in a sweep this module runs itself (:func:`sweep_jobs`); None otherwise.
_SWEEP_JOB: list[str | None] = [None]


def multirun_folder(out: Path) -> Path:
    """``out``, or in a multirun (``-m``) its sub-folder named after the job's overrides."""
    if _SWEEP_JOB[0] is not None:
        return out / (_SWEEP_JOB[0] or "default")
    if "hydra" not in sys.modules:   # no Hydra app ran (a cached plain line): not a multirun
        return out
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        hc = HydraConfig.get()
        if hc.mode == RunMode.MULTIRUN:
            out = out / (hc.job.override_dirname or "default")
    except ValueError:  # not running under Hydra (called from Python)
        pass
    return out


# Hydra's options that take a value (the value is not a path to vectorise).
_HYDRA_VALUE_FLAGS = {"--cfg", "-c", "--package", "-p", "--config-path", "-cp", "--config-name", "-cn",
                      "--config-dir", "-cd", "--experimental-rerun"}
_OVERRIDE = re.compile(r"^[+~]{0,2}[A-Za-z_][\w\-./@\[\]]*(=|$)")


_EDITS_ALIAS = "keypoints.edits="


def is_override(arg: str) -> bool:
    """Whether a command-line argument is a ``key=value`` override (and not a path that happens to
    hold ``=``: an existing file of that name is a path)."""
    return "=" in arg and bool(_OVERRIDE.match(arg)) and not os.path.lexists(arg)


def split_arguments(argv: list[str], positional: bool = True) -> tuple[list[str], list[str]]:
    """Split a command line into Hydra's arguments and the paths to vectorise.

    A path is any argument that is not an option and not ``key=value``, or that names an existing
    file; ``input=VALUE`` is a path too, so that a file name with characters the override grammar
    rejects (``ü``, ``(``, ``,``, ``✓``) works either way. ``keypoints.edits=FILE`` is read as
    ``keypoint_edits.file=FILE``.

    Parameters
    ----------
    argv : list of str
        ``sys.argv[1:]``.
    positional : bool
        False for commands without paths (``polyvec-bench``): everything goes to Hydra.

    Returns
    -------
    hydra_args, paths : list of str
    """
    if not positional:
        return list(argv), []
    hydra_args, paths = [], []
    it = iter(argv)
    for a in it:
        if a.startswith("-") and not os.path.lexists(a):
            hydra_args.append(a)
            if a in _HYDRA_VALUE_FLAGS:
                nxt = next(it, None)
                if nxt is not None:
                    hydra_args.append(nxt)
        elif a.startswith("input="):
            paths.append(a[len("input="):])
        elif a.startswith(_EDITS_ALIAS):
            # The and the page's spelling; the edits live in a stage of their own so that the
            # detector's key (its config section) does not change when a correction is made.
            hydra_args.append("keypoint_edits.file=" + a[len(_EDITS_ALIAS):])
        elif is_override(a):
            hydra_args.append(a)
        else:
            paths.append(a)
    return hydra_args, [p for p in paths if p]


def check_overrides(args: list[str]) -> bool:
    """Parse the command line's overrides, so that one that does not parse is a usage error.

    Whether they fit the config (a key it has, a value of the right type) is found when Hydra composes
    it for the run, and :meth:`ExitCode.main` reports that as a usage error too: composing it here as
    well would cost a third composition, about 0.12 s of every run.

    Returns
    -------
    bool
        True when the command line is plain overrides of one job: no flag, no sweep, no ``hydra`` key.

    Raises
    ------
    UsageError
        An override that does not parse, in one line.
    """
    from pipeline.engine.compose import plain_values

    if plain_values(args) is not None:   # the simplest key=value overrides: no need to import Hydra
        return True
    from hydra.core.override_parser.overrides_parser import OverridesParser

    overrides = [a for a in args if not a.startswith("-") and a not in _flag_values(args)]
    parser = OverridesParser.create()
    try:
        parsed = parser.parse_overrides(overrides)
    except Exception as exc:  # noqa: BLE001 - hydra raises several kinds; all are usage errors
        raise UsageError(f"cannot read the arguments: {first_line(exc)} (quote odd characters: key='value', "
                         "or give input paths as plain arguments)") from None
    return (len(overrides) == len(args)
            and not any(o.is_sweep_override() or o.is_hydra_override() for o in parsed))


def config_error(exc: BaseException) -> str:
    """One line for an error Hydra raised composing the config: its first line and its cause's."""
    cause = f" ({first_line(exc.__cause__)})" if exc.__cause__ is not None else ""
    return first_line(exc) + cause


@contextmanager
def hydra_raises():
    """Have Hydra raise the errors it meets (``HYDRA_FULL_ERROR=1``) instead of printing them and exiting 1.

    :meth:`ExitCode.main` then reports a config that does not compose as a one-line usage error.
    """
    before = os.environ.get("HYDRA_FULL_ERROR")
    os.environ["HYDRA_FULL_ERROR"] = "1"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = before


def sweep_jobs(config_name: str, args: list[str]) -> list[tuple[list[str], str]] | None:
    """The jobs of a plain sweep: each job's overrides and its folder name, as Hydra's basic sweeper and
    its ``override_dirname`` make them; None for any other command line.

    A plain sweep is ``-m`` (or ``--multirun``) and overrides of the task's keys: no other flag, no
    ``hydra.`` key, no glob. Hydra's own multirun composes every job's config twice from the YAML
    files (once to check the batch, once to run it), about 0.4 s each time, nearly what a λ job on a
    stored drawing costs; the CLI runs such a sweep itself and composes each job once, through
    :mod:`pipeline.engine.compose` (a job that changes only values of existing keys sets them on the
    cached composition of the rest: milliseconds). The folder name follows
    ``hydra.job.config.override_dirname`` of the app's YAML (``exclude_keys``; ``=`` and ``,``).

    Raises
    ------
    UsageError
        An override that does not parse, in one line.
    """
    flags = [a for a in args if a.startswith("-")]
    if len(flags) != 1 or flags[0] not in ("-m", "--multirun"):
        return None
    overrides = [a for a in args if a not in flags]
    try:
        from hydra._internal.config_loader_impl import get_overrides_dirname
        from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
        from hydra.core.override_parser.overrides_parser import OverridesParser
        from hydra.core.override_parser.types import ValueType
    except ImportError:  # another Hydra: its own multirun
        return None
    parser = OverridesParser.create()
    try:
        parsed = parser.parse_overrides(overrides)
    except Exception as exc:  # noqa: BLE001 - hydra raises several kinds; all are usage errors
        raise UsageError(f"cannot read the arguments: {first_line(exc)}") from None
    if any(o.is_hydra_override() or o.value_type == ValueType.GLOB_CHOICE_SWEEP for o in parsed):
        return None
    import yaml

    app = yaml.safe_load((CONF_DIR / f"{config_name}.yaml").read_text())
    naming = (((app.get("hydra") or {}).get("job") or {}).get("config") or {}).get("override_dirname") or {}
    if set(naming) - {"exclude_keys"}:
        return None   # a separator of its own: Hydra names the folders
    exclude = list(naming.get("exclude_keys") or [])
    try:
        [batch] = BasicSweeper.split_arguments(parsed, None)
    except Exception:  # noqa: BLE001 - a sweep the basic sweeper refuses: Hydra says why
        return None
    return [(job, get_overrides_dirname(parser.parse_overrides(job), exclude, ",", "=")) for job in batch]


def _flag_values(args: list[str]) -> set[str]:
    return {args[i + 1] for i, a in enumerate(args[:-1]) if a in _HYDRA_VALUE_FLAGS}


def first_line(exc: BaseException) -> str:
    """An exception's first non-blank line (its type's name when it has none)."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return lines[0] if lines else type(exc).__name__


@contextmanager
def no_stray_multirun():
    """Remove the ``multirun.yaml`` a sweep (``-m``) leaves in the working directory.

    Hydra's sweeper always saves it into the sweep folder, which is the working directory (jobs do
    not chdir): the user's folder keeps nothing it did not have (one that was there stays).
    """
    stray = Path("multirun.yaml")
    had_stray = stray.exists()
    try:
        yield
    finally:
        if not had_stray and stray.exists():
            stray.unlink()


class ExitCode:
    """Exit status a Hydra app records across (multirun) jobs: 1 = some image failed, 2 = usage error."""

    def __init__(self, prog: str, positional: bool = False):
        self.prog = prog
        self.positional = positional
        self.inputs: list[str] = []
        self.code = 0
        self.started = False  # a job has started: an exception is no longer a usage error

    def job(self, fn, cfg: DictConfig) -> None:
        """Run one job; ``fn(cfg)`` returns True when something failed."""
        self.started = True
        try:
            failed = fn(cfg)
        except (UsageError, ClusterError) as exc:
            print(f"{self.prog}: error: {exc}", file=sys.stderr)
            self.code = 2
            return
        except StageUnavailable as exc:
            print(f"{self.prog}: error: {exc}", file=sys.stderr)
            self.code = 1
            return
        if failed and self.code == 0:
            self.code = 1

    def main(self, app, single: tuple[Callable[[DictConfig], bool], str] | None = None) -> None:
        """Check the command line, run the Hydra app, shut dask down and exit with the recorded status.

        An override that does not parse or does not fit the config is one line and exit 2, before any
        work. Ctrl-C prints one line and exits 130; the store keeps every finished artifact, so running
        the same command again resumes.

        ``single`` = (job, config name): a command line of plain overrides (no sweep, no Hydra flag,
        no ``hydra.`` key) is one job whose config is composed once with Hydra's compose API (and
        read back from :mod:`pipeline.engine.compose` when the same command ran on the same files) and
        passed to ``job``; ``@hydra.main`` composes it twice (once to find the run mode), about 0.3 s
        of every run. The config is the same: this app's Hydra run does nothing else (run dir ``.``,
        no output subdir, no log files).
        """
        args, self.inputs = split_arguments(sys.argv[1:], self.positional)
        cached = None
        if single is not None:
            from pipeline.engine.compose import cached_config

            cached = cached_config(single[1], args)   # a plain line run before: no Hydra at all
        plain = cached is not None
        if not plain:
            try:
                plain = check_overrides(args)
            except UsageError as exc:
                print(f"{self.prog}: error: {exc}", file=sys.stderr)
                sys.exit(2)
        sys.argv[1:] = args
        try:
            sweep = None if single is None or plain else sweep_jobs(single[1], args)
            if cached is not None:
                self.job(single[0], cached)
            elif single is not None and plain:
                job, config_name = single
                from pipeline.engine.compose import compose_config

                self.job(job, compose_config(config_name, args))
            elif sweep is not None:
                self.sweep(single, sweep)
            else:
                with no_stray_multirun(), hydra_raises():
                    app()
        except KeyboardInterrupt:
            self.interrupted()
        except Exception as exc:
            if self.started:
                raise  # from a job (a bug): its traceback, exit 1
            # Raised by Hydra before any job started (a multirun composes every job's config first):
            # the config does not compose with these overrides.
            print(f"{self.prog}: error: {config_error(exc)}", file=sys.stderr)
            self.code = 2
        finally:
            from pipeline.engine.execute.dask_cluster import close_client

            close_client()
        sys.exit(self.code)

    def sweep(self, single: tuple[Callable[[DictConfig], bool], str], jobs: list[tuple[list[str], str]]) -> None:
        """Run a plain sweep's jobs (:func:`sweep_jobs`) one after another, each into its folder.

        Every job's config is composed before the first runs, as Hydra's multirun does: one that does not
        compose is a usage error before any work."""
        from pipeline.engine.compose import compose_config

        job, config_name = single
        configs = [(compose_config(config_name, overrides), folder) for overrides, folder in jobs]
        for cfg, folder in configs:
            _SWEEP_JOB[0] = folder
            try:
                self.job(job, cfg)
            finally:
                _SWEEP_JOB[0] = None

    def console(self, app, single: tuple[Callable[[DictConfig], bool], str] | None = None) -> None:
        """:meth:`main` for a console entry point: the process ends with its status through
        :func:`exit_now` (no interpreter teardown)."""
        try:
            self.main(app, single)
        except SystemExit as done:
            exit_now(done.code)

    def interrupted(self) -> None:
        """Report Ctrl-C in one line, then shut dask down with stderr silenced and exit 130."""
        done = (f"{PROGRESS.done} of {PROGRESS.total} images done, {PROGRESS.stored} stage results stored; "
                if PROGRESS.total else "")
        print(f"{self.prog}: interrupted — {done}run the same command again to resume", file=sys.stderr,
              flush=True)
        # Worker processes and dask's shutdown report the interrupt too (tracebacks, "closing"
        # warnings): none of it is news to the user.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 2)
        sys.stderr = open(os.devnull, "w")
        try:
            from pipeline.engine.execute.dask_cluster import close_client

            close_client()
        except BaseException:  # noqa: BLE001 - a second Ctrl-C during shutdown: just leave
            pass
        sys.stdout.flush()
        os._exit(130)


def hydra_app(body: Callable[[DictConfig], None], config_name: str) -> Callable[[], None]:
    """``@hydra.main`` on ``body`` with this package's config ``config_name``, built when it is called.

    Why: importing Hydra costs ~50 ms of every start-up, and only a command line that needs its app (a
    sweep, a Hydra flag, a ``hydra.`` key) or a first composition needs Hydra at all; a plain line run
    before reads its config from :mod:`pipeline.engine.compose`.
    """
    def app() -> None:
        import hydra

        hydra.main(version_base=None, config_path="pkg://conf", config_name=config_name)(body)()

    return app


def exit_now(code: object) -> None:
    """End the process with ``code`` (a :class:`SystemExit` code) without the interpreter's teardown.

    After a run with torch and numba loaded, Python's finalisation (garbage collection and module
    teardown, after the last output) took about 1 s of the elephant's 9-s default run. Everything a
    run leaves is written by then (artifacts, outputs, dask shut down); the ``atexit`` handlers still
    run and the standard streams are flushed. Console entry points only: a caller in Python gets
    :class:`SystemExit` from :meth:`ExitCode.main`.
    """
    import atexit

    if code is None:
        code = 0
    elif not isinstance(code, int):
        print(code, file=sys.stderr)
        code = 1
    try:
        atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):  # a closed pipe: nothing more can reach it
                pass
        os._exit(code)
