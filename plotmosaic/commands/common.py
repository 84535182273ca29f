"""Shared CLI plumbing: user errors become one line on stderr and an exit code."""

from __future__ import annotations

import functools
from collections.abc import Callable

import typer

from plotmosaic.errors import PlotmosaicError


def handle_errors(func: Callable) -> Callable:
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except PlotmosaicError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(exc.exit_code) from None

    return wrapper

