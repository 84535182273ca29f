"""Errors a user can act on. The CLI prints their message on one line and exits with their code."""


class PlotmosaicError(Exception):
    """Bad input or an unusable result; never a bug."""

    exit_code = 2


class InputError(PlotmosaicError):
    """A file, manifest or option the user gave cannot be used (exit 2)."""


class RegistrationFailed(PlotmosaicError):
    """A pair could not be registered; the message carries the figures that show why (exit 3)."""

    exit_code = 3


INTERRUPTED = 130  # exit code of an interrupted run (Ctrl-C or SIGTERM), the shell's 128 + SIGINT
