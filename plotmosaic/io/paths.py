"""One check for every file the user names as an input: a single line that says what is wrong.

`Path.exists()` folds a symlink loop, a broken link and a folder it cannot search into "not found";
`os.stat` keeps them apart, so the message points at the real cause.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from plotmosaic.errors import InputError


def input_problem(path: str | Path, what: str = "file") -> str | None:
    """Why `path` cannot be read as a `what` (a regular file), or None when it can."""
    path = Path(path)
    try:
        info = os.stat(path)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "symbolic link loop (the link points back at itself)"
        if exc.errno == errno.ENOENT and os.path.islink(path):
            return f"broken symbolic link (to {os.readlink(path)}, which does not exist)"
        if exc.errno == errno.ENOENT:
            return f"{what} not found"
        if exc.errno in (errno.EACCES, errno.EPERM):
            return f"not readable ({exc.strerror})"
        return exc.strerror or str(exc)
    if stat.S_ISDIR(info.st_mode):
        return f"is a directory, expected a {what}"
    if not stat.S_ISREG(info.st_mode):
        return f"not a regular file, expected a {what}"
    if not os.access(path, os.R_OK):
        return "not readable (permission denied)"
    return None


def check_input_file(path: str | Path, what: str = "file") -> Path:
    """`path` when it is a readable regular file, else InputError naming it and the cause."""
    problem = input_problem(path, what)
    if problem is not None:
        raise InputError(f"{path}: {problem}")
    return Path(path)
