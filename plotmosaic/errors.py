"""Errors a user can act on. The CLI prints an error's message on one line and exits with its code
(interrupts: lifetime.py)."""

from __future__ import annotations


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
