"""Errors a user can act on, and interrupts. The CLI prints an error's message on one line and exits
with its code; Ctrl-C or SIGTERM ends any run as `interrupted` and exit 130."""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator
from typing import NoReturn


class PlotmosaicError(Exception):
    """Bad input or an unusable result; never a bug."""

    exit_code = 2


class InputError(PlotmosaicError):
    """A file, manifest or option the user gave cannot be used (exit 2)."""


class RegistrationFailed(PlotmosaicError):
    """A pair could not be registered; the message carries the figures that show why (exit 3)."""

    exit_code = 3


def short_error(exc: Exception) -> str:
    """A library's error message cut to its first line, to go inside our one-line message."""
    text = str(exc).strip().splitlines()
    return text[0][:160] if text else type(exc).__name__


INTERRUPTED = 130  # exit code of an interrupted run (Ctrl-C or SIGTERM), the shell's 128 + SIGINT


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
            previous = {s: signal.signal(s, self.handler) for s in (signal.SIGINT, signal.SIGTERM)}
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


def exit_interrupted() -> NoReturn:
    """The end of an interrupted run outside a command (while importing, or as it exits)."""
    sys.stderr.write("interrupted\n")
    sys.exit(INTERRUPTED)


@contextlib.contextmanager
def signals_held() -> Iterator[None]:
    """Hold SIGINT/SIGTERM through a clean-up or a rename, so a second Ctrl-C cannot cut it in half."""
    held = {signal.SIGINT, signal.SIGTERM}
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)
