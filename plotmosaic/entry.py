"""The console script's first code: SIGTERM is an interrupt from the first instant.

Importing the command layer (typer, numpy, Open3D, GTSAM) takes about a second; a batch
scheduler's SIGTERM in that window used to kill the process with 143 instead of 130.
"""

from __future__ import annotations

import signal
import sys

from plotmosaic.errors import INTERRUPTED


def _terminate(signum, frame):
    raise KeyboardInterrupt


def main() -> None:
    signal.signal(signal.SIGTERM, _terminate)
    try:
        from plotmosaic.cli import main as cli_main
    except KeyboardInterrupt:
        sys.stderr.write("interrupted\n")
        sys.exit(INTERRUPTED)
    cli_main()
