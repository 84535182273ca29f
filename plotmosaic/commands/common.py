"""Shared CLI plumbing: user errors become one line on stderr and an exit code.

Exit codes: 0 done; 2 bad input (a file, manifest, option or output location that cannot be used,
named on one line); 3 cannot register (the figures that show why); 130 interrupted (Ctrl-C or
SIGTERM: outputs are atomic, nothing half-written is left). Anything else is a bug (exit 1).
"""

from __future__ import annotations

import contextlib
import errno
import functools
import os
import shlex
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import typer

from plotmosaic.align.prepare import MIN_POINTS
from plotmosaic.config.settings import (
    Settings,
    SettingsError,
    dump_settings,
    load_settings,
    with_overrides,
)
from plotmosaic.errors import InputError, PlotmosaicError
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.las import read_header_info
from plotmosaic.lifetime import INTERRUPTED, interrupts
from plotmosaic.manifest import load_manifest
from plotmosaic.poses import load_poses

# OS errors that describe the user's files or disk, not a bug: reported as bad input (exit 2)
_USER_ERRNOS = {
    errno.ENOENT,
    errno.EACCES,
    errno.EPERM,
    errno.ENOTDIR,
    errno.EISDIR,
    errno.ENAMETOOLONG,
    errno.EROFS,
    errno.ENOSPC,
    errno.EDQUOT,
    errno.EEXIST,
    errno.ELOOP,
}


def _interrupted() -> typer.Exit:
    typer.echo("interrupted", err=True)
    return typer.Exit(INTERRUPTED)


def handle_errors(func: Callable) -> Callable:
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            with interrupts.installed():
                return func(*args, **kwargs)
        except PlotmosaicError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(exc.exit_code) from None
        except KeyboardInterrupt:
            raise _interrupted() from None
        except (typer.Exit, SystemExit):
            raise
        except OSError as exc:
            if exc.errno in _USER_ERRNOS and exc.filename is not None:
                typer.echo(f"error: {exc.filename}: {exc.strerror}", err=True)
                raise typer.Exit(2) from None
            raise

    return wrapper


# ---- pre-work checks shared by the commands: bad input is found before any work starts ----


def check_scan_files(manifest_path):
    """The manifest, after a header read of every scan: each readable, with enough points to register."""
    manifest = load_manifest(manifest_path)
    for scan in manifest.scans:
        path = manifest.resolve(scan.path)
        n = read_header_info(path).point_count
        if n < MIN_POINTS:
            raise InputError(
                f"{path}: scan {scan.id!r} has only {n} points, at least {MIN_POINTS} needed to register"
            )
    return manifest


def check_poses_match(manifest, poses_path):
    """The poses file, if it was made for this manifest: shared scan ids, in the same plots."""
    poses = load_poses(poses_path)
    plots = {s.id: p.id for p in manifest.plots for s in p.scans}
    shared = [sid for sid in poses.scans if sid in plots]
    if not shared:
        names = ", ".join(sorted(poses.scans)[:5]) or "none"
        raise InputError(
            f"{poses_path}: none of its scans ({names}) is in {manifest.source}; poses of another manifest?"
        )
    wrong = [sid for sid in shared if poses.scans[sid].plot not in (None, plots[sid])]
    if wrong:
        sid = wrong[0]
        raise InputError(
            f"{poses_path}: scan {sid!r} is in plot {poses.scans[sid].plot!r} there but in plot "
            f"{plots[sid]!r} in {manifest.source}; poses of another manifest?"
        )
    return poses


@contextlib.contextmanager
def no_empty_output(folder) -> Iterator[None]:
    """A run that fails leaves no empty output folder it created (folders holding files are kept)."""
    top = None  # the outermost folder this run will create
    current = Path(folder).absolute()
    while not current.exists() and current.parent != current:
        top, current = current, current.parent
    try:
        yield
    except BaseException:
        if top is not None and top.is_dir():
            # deepest first
            for root, _dirs, _files in sorted(os.walk(top), key=lambda w: -len(w[0])):
                with contextlib.suppress(OSError):
                    os.rmdir(root)  # only succeeds on an empty folder
        raise


# ---- settings: --config FILE.toml, options over it, config-used.toml beside the outputs ----

CONFIG_HELP = (
    "Settings file (TOML; `plotmosaic config --defaults` prints the keys a user turns, `config "
    "--all` every key). Options given on the command line override it."
)
CONFIG_USED = "config-used.toml"


def run_settings(config_path, overrides: dict | None = None):
    """The settings of this run: defaults, then the --config file, then the command's options
    (nested {"section": {"key": value}}; None = not given). Bad keys or values: exit 2, one line."""
    try:
        settings = load_settings(config_path) if config_path is not None else Settings()
        return with_overrides(settings, overrides or {}, "command-line option")
    except SettingsError as exc:
        raise InputError(str(exc)) from None


def write_config_used(path, settings, command: str):
    """The settings a run used, as TOML beside its outputs (atomic): `--config` repeats the run."""
    header = (
        f"Settings used by `plotmosaic {command}` (give back with --config to repeat the run; "
        "copy it first when the run writes into this folder: a run never writes over its inputs)."
    )
    # the console script or `python -m plotmosaic`; not when called in-process (tests)
    if sys.argv and sys.argv[0].endswith(("plotmosaic", os.path.join("plotmosaic", "__main__.py"))):
        argv = " ".join(shlex.quote(a) for a in sys.argv[1:])
        header += f"\ncommand line: plotmosaic {argv}"
    return write_text_atomic(path, dump_settings(settings, header))
