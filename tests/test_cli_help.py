"""`plotmosaic --help` lists the commands without importing them, in the words click would use."""

from __future__ import annotations

import subprocess
import sys

import pytest
import typer

from plotmosaic.cli import COMMANDS, app, short_help


@pytest.mark.parametrize("limit", [20, 45, 200])
def test_each_listed_line_is_the_loaded_commands_short_help(limit):
    group = typer.main.get_command(app)
    for name in COMMANDS:
        command = group.get_command(None, name)  # imports the command's module
        assert short_help(name, limit) == command.get_short_help_str(limit)


def test_the_top_level_help_imports_no_command():
    code = (
        "import sys; from plotmosaic.cli import app; app(['--help'], standalone_mode=False); "
        "print(sorted(m for m in sys.modules if m.startswith('plotmosaic.commands.')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "register-plot" in out.stdout
    assert out.stdout.strip().splitlines()[-1] == "[]"
