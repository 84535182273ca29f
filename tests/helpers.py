"""Assertions shared by the CLI tests."""

from typer.testing import CliRunner

from plotmosaic.cli import app

runner = CliRunner()


def invoke(*args):
    """Run `plotmosaic ARGS...` in-process; a traceback (anything but SystemExit) fails the test."""
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    return result


def assert_one_line_error(result, *needles, code=2):
    """Exit `code` with exactly one line `error: ...` that names every needle, and no traceback."""
    assert result.exit_code == code, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    assert "Traceback" not in result.output
    for needle in needles:
        assert needle in lines[0], lines[0]
