"""Atomic output: write to a temporary file beside the target, rename at the end.

A failed or interrupted run leaves no half-written file and keeps whatever was there before.
Temporaries are named `.NAME.tmp-PID`; those whose process is gone (a SIGKILLed run) are removed by
the next run that writes into the same folder. `check_output_file` / `check_output_dir` find an
unusable output location before any work starts, and leave nothing behind.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
from collections.abc import Iterator
from pathlib import Path

from plotmosaic.errors import InputError
from plotmosaic.lifetime import signals_held

TEMP_NAME = re.compile(r"^\..+\.tmp-(\d+)$")  # our own temporaries: `.NAME.tmp-PID`
# bytes per path component on every common file system (ext4, xfs, btrfs, NTFS, APFS)
NAME_MAX = 255
_cleaned: set[str] = set()  # folders already swept for stale temporaries in this process


def temp_name(path: Path, tag: str = "") -> Path:
    """The temporary beside `path` (`.NAME{tag}.tmp-PID`): a later run finds what a killed one left."""
    return path.with_name(f".{path.name}{tag}.tmp-{os.getpid()}")


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def remove_stale_temporaries(folder: str | Path) -> list[Path]:
    """Delete `.NAME.tmp-PID` files (and folders) in `folder` whose process no longer runs (once per folder and process)."""
    folder = Path(folder)
    tag = str(folder.resolve()) if folder.exists() else str(folder)
    if tag in _cleaned or not folder.is_dir():
        return []
    _cleaned.add(tag)
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return []
    for entry in entries:
        m = TEMP_NAME.match(entry.name)
        if not m or entry.is_symlink() or _alive(int(m.group(1))):
            continue
        with contextlib.suppress(OSError):
            # a temporary folder (merge's tiles and spill files)
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path)
            else:
                os.unlink(entry.path)
            removed.append(Path(entry.path))
    return removed


def _check_names(path: Path) -> None:
    for part in path.parts:
        if len(os.fsencode(part)) > NAME_MAX:
            raise InputError(
                f"{path}: the name {part[:40]}... is {len(os.fsencode(part))} bytes long, "
                f"more than the {NAME_MAX} a file system allows"
            )
    # the temporary's name is the longest one we write
    name = len(os.fsencode(path.name))
    extra = len(os.fsencode(temp_name(path).name)) - name
    if name + extra > NAME_MAX:
        raise InputError(
            f"{path}: the file name is {name} bytes long, at most {NAME_MAX - extra} can be written"
        )


def _existing_ancestor(folder: Path) -> Path:
    """The nearest folder of `folder` (itself included) that exists; an error if it is a file."""
    current = folder
    while not current.exists():
        if current.parent == current:
            break
        current = current.parent
    if current.exists() and not current.is_dir():
        raise InputError(f"{folder}: cannot be created, {current} is a file, not a folder")
    return current


def _probe(folder: Path, what: Path) -> None:
    """Create the missing folders and a probe file in `folder`, then remove everything created."""
    made: list[Path] = []
    missing = []
    current = folder
    while not current.exists():
        missing.append(current)
        current = current.parent
    try:
        for d in reversed(missing):
            d.mkdir()
            made.append(d)
        probe = folder / f".plotmosaic-probe.tmp-{os.getpid()}"
        try:
            with open(probe, "wb") as fh:
                fh.write(b"probe")
                fh.flush()
                os.fsync(fh.fileno())  # a full disk refuses the data here, not at open()
        finally:
            with contextlib.suppress(OSError):
                probe.unlink()
    except OSError as exc:
        reason = exc.strerror or str(exc)
        if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
            reason = f"not writable: {reason}"
        raise InputError(f"{what}: cannot write in {folder} ({reason})") from None
    finally:
        for d in reversed(made):
            with contextlib.suppress(OSError):
                d.rmdir()


def check_writable(
    path: Path, force: bool = True, create: bool = True, probe: bool = False
) -> Path:
    """`path` can be written as a file: not a folder, (with force=False) not existing, its folder usable.

    create=True makes the missing parent folders (what a writer needs); probe=True writes and removes a
    probe file there (leaving nothing behind when create=False), which catches /proc, read-only mounts, quotas.
    """
    path = Path(path)
    _check_names(path)  # first: stat() of an over-long name raises
    if path.is_dir():
        raise InputError(f"{path}: is a directory, expected a file path")
    if path.exists() and not force:
        raise InputError(f"{path}: already exists (use --force to overwrite)")
    parent = path.parent if str(path.parent) else Path(".")
    _existing_ancestor(parent)
    if create and not parent.exists():
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(
                f"{path}: cannot create output folder ({exc.strerror or exc})"
            ) from None
    if parent.exists() and not os.access(parent, os.W_OK):
        raise InputError(f"{path}: output folder {parent} is not writable")
    if probe:
        _probe(parent, path)
    return path


def check_output_file(path: str | Path, force: bool = True) -> Path:
    """The pre-work check of an output file: everything `check_writable` checks, with a real probe, nothing left."""
    return check_writable(Path(path), force=force, create=False, probe=True)


def check_output_dir(folder: str | Path) -> Path:
    """The pre-work check of an output folder: a folder (or creatable), names valid, writable; nothing left."""
    folder = Path(folder)
    _check_names(folder / "x")
    if folder.exists() and not folder.is_dir():
        raise InputError(f"{folder}: exists and is not a folder")
    _existing_ancestor(folder)
    _probe(folder, folder)
    return folder


@contextlib.contextmanager
def atomic_output(path: str | Path, force: bool = True) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on success rename it onto `path`."""
    path = check_writable(Path(path), force=force)
    remove_stale_temporaries(path.parent if str(path.parent) else Path("."))
    tmp = temp_name(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text_atomic(path: str | Path, text: str) -> Path:
    """UTF-8 text; a file name that is not UTF-8 (a surrogate escape) is written as `\\udcff`."""
    with atomic_output(path) as tmp:
        tmp.write_text(text, encoding="utf-8", errors="backslashreplace")
    return Path(path)


@contextlib.contextmanager
def atomic_folder(path: Path, force: bool) -> Iterator[Path]:
    """Yield a temporary folder beside `path`; on success it replaces `path` (an earlier folder)."""
    tmp = temp_name(path)
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        yield tmp
        with signals_held():
            if path.exists():
                if not force:
                    raise InputError(f"{path}: already exists (use --force to overwrite)")
                old = temp_name(path, ".old")
                os.replace(path, old)
                try:
                    os.replace(tmp, path)
                except BaseException:
                    os.replace(old, path)
                    raise
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(tmp, path)
    except BaseException:
        with signals_held():
            shutil.rmtree(tmp, ignore_errors=True)
        raise


@contextlib.contextmanager
def temp_folder(path: Path, tag: str) -> Iterator[Path]:
    """A scratch folder beside `path` (`.NAME{tag}.tmp-PID`), removed at the end whatever happens."""
    folder = temp_name(path, tag)
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir()
    try:
        yield folder
    finally:
        with signals_held():
            shutil.rmtree(folder, ignore_errors=True)
