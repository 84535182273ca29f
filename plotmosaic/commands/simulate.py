"""`plotmosaic simulate`."""

from __future__ import annotations

import typer

from plotmosaic.commands.common import not_implemented


def simulate_command(ctx: typer.Context) -> None:
    """Not implemented yet."""
    not_implemented("simulate")
