"""Pool workers die with their parent: a SIGKILLed run leaves no orphaned worker processes.

`bind_to_parent()` runs in each worker's initializer. On Linux the kernel kills the worker when the
parent dies (PR_SET_PDEATHSIG); everywhere, a daemon thread also ends the worker as soon as its parent
PID changes (the worker was re-parented). Ctrl-C reaches the whole process group: workers ignore
SIGINT and let the parent stop them, so one interrupt gives one message, not a traceback per worker.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys
import threading
import time

POLL_SECONDS = 0.2  # how fast a worker notices that its parent is gone (a cheap getppid() call)
_PR_SET_PDEATHSIG = 1
_bound = False


def _parent_death_signal() -> None:
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):  # no libc / prctl: the watchdog thread still does it
        pass


def _watch(parent: int) -> None:
    while True:
        if os.getppid() != parent:
            os._exit(1)  # the parent is gone: nothing will read our result
        time.sleep(POLL_SECONDS)


def bind_to_parent(ignore_sigint: bool = True) -> None:
    """Make this (worker) process end when its parent process ends; call once in the pool initializer."""
    global _bound
    if _bound:
        return
    _bound = True
    parent = os.getppid()
    _parent_death_signal()
    if os.getppid() != parent or parent == 1:  # the parent died before the signal was armed
        os._exit(1)
    if ignore_sigint:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(
        target=_watch, args=(parent,), name="plotmosaic-parent-watch", daemon=True
    ).start()
