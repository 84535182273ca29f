"""The console script's first code: SIGTERM is an interrupt from the first instant.

Importing the command layer (typer, numpy, Open3D, GTSAM) takes a noticeable while; a batch
scheduler's SIGTERM in that window would otherwise kill the process with 143 instead of 130.
"""

from __future__ import annotations

import importlib
import signal
import sys

from plotmosaic.errors import exit_interrupted, interrupts


def main() -> None:
    signal.signal(signal.SIGTERM, interrupts.handler)
    for stream in (sys.stdout, sys.stderr):  # file names need not be UTF-8: print them escaped
        stream.reconfigure(errors="backslashreplace")
    try:
        # imported only now, under the handler above: the import itself is the window to cover
        cli = importlib.import_module("plotmosaic.cli")
    except KeyboardInterrupt:
        exit_interrupted()
    try:
        cli.main()
    finally:
        # the work is done and reported: a signal now would only end the process by the default
        # action (status 143) while it exits, so the exit code stands
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
