"""The console script's first code: SIGTERM is an interrupt from the first instant.

Importing the command layer (typer, numpy, Open3D, GTSAM) takes a noticeable while; a batch
scheduler's SIGTERM in that window would otherwise kill the process with 143 instead of 130.
"""

from __future__ import annotations

import importlib
import sys

from plotmosaic.lifetime import exit_interrupted, ignore_stops, interrupt_on_term


def main() -> None:
    interrupt_on_term()
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
        ignore_stops()
