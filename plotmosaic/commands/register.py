"""`plotmosaic register-plot` and `plotmosaic tie-to-als`."""

from __future__ import annotations

import typer

from plotmosaic.commands.common import not_implemented


def register_plot_command(ctx: typer.Context) -> None:
    """Not implemented yet."""
    not_implemented("register-plot")


def tie_to_als_command(ctx: typer.Context) -> None:
    """Not implemented yet."""
    not_implemented("tie-to-als")
