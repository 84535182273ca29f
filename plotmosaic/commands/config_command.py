"""`plotmosaic config`: print the default settings, or check a settings file."""

from __future__ import annotations

from pathlib import Path

import typer

from plotmosaic.commands.common import handle_errors, run_settings
from plotmosaic.config.settings import Settings, default_toml
from plotmosaic.errors import InputError


@handle_errors
def config_command(
    defaults: bool = typer.Option(
        False,
        "--defaults",
        help="Print the settings a user turns, each with its default and a comment (TOML).",
    ),
    every: bool = typer.Option(
        False,
        "--all",
        help="Print every setting: the method's calibration too (docs/method.md#calibration-settings).",
    ),
    check: Path | None = typer.Option(
        None, "--check", help="Check a settings file: exit 0 if usable, else 2 naming the key."
    ),
) -> None:
    """The settings of every stage: `--defaults > my.toml`, edit, then give it with --config."""
    printing = defaults or every
    if printing == (check is not None):
        raise InputError("give one of --defaults (or --all) or --check FILE.toml")
    if printing:
        typer.echo(default_toml("all" if every else "user"), nl=False)
        return
    settings = run_settings(check)
    changed = _changed(settings)
    typer.echo(f"{check}: ok ({len(changed)} settings differ from the defaults)")
    for key in changed:
        typer.echo(f"  {key}")


def _changed(settings) -> list[str]:
    out: list[str] = []

    def walk(a, b, loc):
        if isinstance(a, dict):
            for k in a:
                walk(a[k], b.get(k), f"{loc}.{k}" if loc else k)
        elif a != b:
            out.append(loc)

    walk(settings.model_dump(), Settings().model_dump(), "")
    return out
