"""Atomic output: write to a temporary file beside the target, rename at the end.

A failed or interrupted run leaves no half-written file and keeps whatever was there before.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from plotmosaic.errors import InputError


def check_writable(path: Path, force: bool = True) -> Path:
    path = Path(path)
    if path.exists() and path.is_dir():
        raise InputError(f"{path}: is a directory, expected a file path")
    if path.exists() and not force:
        raise InputError(f"{path}: already exists (use --force to overwrite)")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.exists():
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"{path}: cannot create output folder ({exc.strerror})") from None
    if not os.access(parent, os.W_OK):
        raise InputError(f"{path}: output folder is not writable")
    return path


@contextlib.contextmanager
def atomic_output(path: str | Path, force: bool = True) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on success rename it onto `path`."""
    path = check_writable(Path(path), force=force)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def write_text_atomic(path: str | Path, text: str) -> Path:
    with atomic_output(path) as tmp:
        tmp.write_text(text)
    return Path(path)
