"""The `plotmosaic` command: a thin typer layer over the library.

Each subcommand lives in plotmosaic/commands/<name>.py; this file only names them. A command's
module (and the stage it drives, with numpy, Open3D, GTSAM, ...) is imported when that command
runs, so `plotmosaic info` or `--version` does not pay for every stage.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import os
import sys
from pathlib import Path

import typer

# typer vendors click: its parser raises these, not the `click` package's
from typer._click import exceptions as click_errors
from typer._click.utils import make_default_short_help
from typer.core import TyperGroup

from plotmosaic import __version__
from plotmosaic.errors import InputError
from plotmosaic.lifetime import INTERRUPTED, exit_interrupted, interrupts

HELP = """Targetless, GNSS-free registration of forest LiDAR scans into one georeferenced cloud.

Typical run on a plot scanned from five positions, with an ALS tile over the region:

\b
  plotmosaic simulate sim --preset small            # a simulated plot with ground truth
  plotmosaic align sim/P1/P1-S1.laz sim/P1/P1-S0.laz --out pair.json
  plotmosaic register-plot sim/manifest.toml --out reg
  plotmosaic tie-to-als sim/manifest.toml --poses reg/poses.json --out geo
  plotmosaic merge sim/manifest.toml --poses geo/poses.json --out merged.laz
  plotmosaic demo demo-output                        # all of the above on a built-in demo
  plotmosaic info sim/manifest.toml --full           # check a manifest and its files
  plotmosaic config --defaults > my.toml             # the settings you turn; --all: every one
"""


# command name -> (module, function) under plotmosaic.commands, in the order `--help` lists them
COMMANDS = {
    "align": ("align", "align_command"),
    "register-plot": ("register", "register_plot_command"),
    "tie-to-als": ("register", "tie_to_als_command"),
    "merge": ("merge", "merge_command"),
    "export": ("export", "export_command"),
    "simulate": ("simulate", "simulate_command"),
    "bench": ("bench", "bench_command"),
    "report": ("report", "report_command"),
    "demo": ("demo", "demo_command"),
    "info": ("info", "info_command"),
    "manifest-from": ("manifest_from", "manifest_from_command"),
    "config": ("config_command", "config_command"),
}


def short_help(name: str, limit: int) -> str:
    """A command's line in `plotmosaic --help`: the first paragraph of its function's docstring, as
    click shortens it, read from the module's source without importing it (each command module
    pulls in its whole stage, and the listing imported them all)."""
    module, function = COMMANDS[name]
    source = Path(importlib.util.find_spec(f"plotmosaic.commands.{module}").origin)
    tree = ast.parse(source.read_text(encoding="utf-8"))
    doc = next(
        ast.get_docstring(node) or ""
        for node in tree.body
        if isinstance(node, ast.FunctionDef) and node.name == function
    )
    return make_default_short_help(doc, limit).strip()


class OneLineErrors(TyperGroup):
    """Bad options, arguments and unreadable files end as one `error:` line and exit 2, as every
    other bad input does, instead of click's usage block."""

    def list_commands(self, ctx) -> list[str]:
        return list(COMMANDS)

    def format_commands(self, ctx, formatter) -> None:
        limit = formatter.width - 6 - max(len(name) for name in COMMANDS)
        with formatter.section("Commands"):
            formatter.write_dl([(name, short_help(name, limit)) for name in COMMANDS])

    def get_command(self, ctx, name: str):
        """The command, its module imported now (only the command that runs pays for its stage)."""
        if name not in COMMANDS:
            return None
        module, function = COMMANDS[name]
        one = typer.Typer(add_completion=False, rich_markup_mode=None)
        try:
            loaded = importlib.import_module(f"plotmosaic.commands.{module}")
        except KeyboardInterrupt:  # click would end it as a silent exit 130
            exit_interrupted()
        one.command(name)(getattr(loaded, function))
        return typer.main.get_command(one)

    def main(self, *args, standalone_mode: bool = True, **kwargs):
        try:  # not standalone, click returns a typer.Exit's code instead of exiting
            returned = super().main(*args, standalone_mode=False, **kwargs)
            code = returned if isinstance(returned, int) else 0
        except click_errors.NoArgsIsHelpError as exc:
            typer.echo(exc.ctx.get_help() if exc.ctx else str(exc))
            code = 0
        except click_errors.ClickException as exc:
            where = f" (see {exc.ctx.command_path} --help)" if getattr(exc, "ctx", None) else ""
            message = " ".join(exc.format_message().split())
            typer.echo(f"error: {message}{where}", err=True)
            code = InputError.exit_code
        # click's form of Ctrl-C at a prompt or EOF (defined by typer, not in typer._click)
        except typer.Abort:
            typer.echo("interrupted", err=True)
            code = INTERRUPTED
        if standalone_mode:
            sys.exit(code)
        return code


app = typer.Typer(
    cls=OneLineErrors,
    help=HELP,
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode=None,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"plotmosaic {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Show the version and exit."
    ),
) -> None:
    pass


def main() -> None:
    try:
        app()
    except KeyboardInterrupt:  # outside a command (e.g. while parsing options): same exit code
        exit_interrupted()
    except Exception as exc:  # a bug, not bad input: one line unless debugging
        if interrupts.received:  # an interrupt wrapped in another error by a library
            exit_interrupted()
        if os.environ.get("PLOTMOSAIC_DEBUG"):
            raise
        typer.echo(
            f"internal error: {type(exc).__name__}: {exc} (set PLOTMOSAIC_DEBUG=1 for a traceback)",
            err=True,
        )
        sys.exit(1)
