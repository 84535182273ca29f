"""Interrupts and process lifetime: the one module that handles signals.

Ctrl-C or SIGTERM ends any run as `interrupted` and exit 130 (`interrupts`, installed by every
entry point). Pool workers die with their parent: a SIGKILLed run leaves no orphaned worker
(`bind_to_parent()` runs in each worker's initializer: on Linux the kernel kills the worker when
the parent dies, PR_SET_PDEATHSIG; everywhere, a daemon thread also ends the worker as soon as its
parent PID changes). Ctrl-C reaches the whole process group: workers ignore SIGINT and SIGTERM
from their first instant (`DeafSpawnContext`) and let the parent stop them, so one interrupt
gives one message, not a traceback per worker.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import multiprocessing.context
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from typing import NoReturn

INTERRUPTED = 130  # exit code of an interrupted run (Ctrl-C or SIGTERM), the shell's 128 + SIGINT
POLL_SECONDS = 0.2  # how fast a worker notices that its parent is gone (a cheap getppid() call)
_STOPS = (signal.SIGINT, signal.SIGTERM)
_PR_SET_PDEATHSIG = 1
_bound = False


class Interrupts:
    """SIGINT / SIGTERM raise KeyboardInterrupt and are remembered, the one handler of every entry
    point: an error a library wraps around the interrupt (LazrsError "Failed to call write", or
    the InputError merge makes of it) still ends as an interrupt (exit 130)."""

    def __init__(self) -> None:
        self.received = False
        self._depth = 0  # installed() nests (a command around merge_scans): the outermost owns it

    def handler(self, signum, frame):
        if self.received:  # a second Ctrl-C must not break the clean-up the first one started
            return
        self.received = True
        raise KeyboardInterrupt

    @contextlib.contextmanager
    def installed(self) -> Iterator[None]:
        if threading.current_thread() is not threading.main_thread():
            yield  # signals can only be handled in the main thread
            return
        previous = {}
        if self._depth == 0:
            self.received = False
            previous = {s: signal.signal(s, self.handler) for s in _STOPS}
        self._depth += 1
        try:
            yield
        except Exception:
            if self.received:
                raise KeyboardInterrupt from None
            raise
        finally:
            self._depth -= 1
            for s, h in previous.items():
                signal.signal(s, h)


interrupts = Interrupts()


def interrupt_on_term() -> None:
    """SIGTERM an interrupt from now on (the console script's first code: a batch scheduler's
    SIGTERM while the command layer imports ends the process with 130, not 143)."""
    signal.signal(signal.SIGTERM, interrupts.handler)


def ignore_stops() -> None:
    """SIGINT and SIGTERM ignored from now on (the work is done and reported: a signal while the
    process exits would only end it by the default action, status 143, and the exit code stands)."""
    for s in _STOPS:
        signal.signal(s, signal.SIG_IGN)


def exit_interrupted() -> NoReturn:
    """The end of an interrupted run outside a command (while importing, or as it exits)."""
    sys.stderr.write("interrupted\n")
    sys.exit(INTERRUPTED)


@contextlib.contextmanager
def signals_held() -> Iterator[None]:
    """Hold SIGINT/SIGTERM through a clean-up or a rename, so a second Ctrl-C cannot cut it in half."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, set(_STOPS))
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


@contextlib.contextmanager
def _stops_ignored() -> Iterator[None]:
    """Ctrl-C and SIGTERM ignored in the block (only the main thread may change handlers)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, signal.SIG_IGN) for s in _STOPS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


class _DeafProcess(multiprocessing.context.SpawnProcess):
    """A spawned worker that ignores Ctrl-C and SIGTERM from its first instant: the terminal signals
    the whole process group, and a worker still importing would print a traceback. An ignored
    signal stays ignored across exec (a caught or blocked one does not), so the parent ignores them
    while it forks (milliseconds); the parent alone stops its workers."""

    @staticmethod
    def _Popen(process_obj):
        with _stops_ignored():
            return multiprocessing.context.SpawnProcess._Popen(process_obj)


class DeafSpawnContext(multiprocessing.context.SpawnContext):
    """The spawn context of the run's worker pool: its workers are `_DeafProcess`es."""

    Process = _DeafProcess


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
