"""`plotmosaic report`: before/after pictures, complexity levels and the pose graph on one page."""

from __future__ import annotations

from pathlib import Path

import typer

from plotmosaic.commands.common import handle_errors
from plotmosaic.errors import InputError
from plotmosaic.io.outputs import OutputPlan, check_outputs, claimed, inputs_of
from plotmosaic.report.page import pair_files, report_dir, report_pair

# what report/page.py and report/build.py write: two pages, a 3D view and figures named by plot
_NAMES = ("index.md", "report.html", "view3d.html")
_FIGURES = ("before", "after", "slice", "graph", "levels", "_map", "distances", "_scans")


def report_plan(out: Path, inputs: list[tuple[Path | None, str]], force: bool) -> OutputPlan:
    names = _NAMES + tuple(f"*{f}.png" for f in _FIGURES)
    return OutputPlan("report", inputs_of(inputs), folder=out, names=names, force=force)


@handle_errors
def report_command(
    directory: Path | None = typer.Argument(
        None,
        help="A register-plot / tie-to-als output folder (poses.json, graph.json), or an align RESULT.json that names its clouds.",
    ),
    pair: tuple[Path, Path, Path] | None = typer.Option(
        None, "--pair", help="RESULT.json SOURCE TARGET of one `align` run."
    ),
    manifest: Path | None = typer.Option(
        None,
        "--manifest",
        help="Manifest of the scans (default: the paths recorded in graph.json).",
    ),
    out: Path | None = typer.Option(
        None, "--out", help="Output folder (default DIR/report, or report-<result> for --pair)."
    ),
    points: int = typer.Option(
        40_000, "--points", min=1000, help="Points drawn per scan (a seeded random subset)."
    ),
    no_levels: bool = typer.Option(
        False,
        "--no-levels",
        help="Skip the structural-complexity figure (it re-runs the levelling).",
    ),
    seed: int = typer.Option(0, "--seed"),
    force: bool = typer.Option(
        False,
        "--force",
        help="Write into an output folder holding other files (they are left untouched).",
    ),
) -> None:
    """Pictures of a registration (before/after, breast-height slice, distances, levels, pose graph): index.md and report.html."""
    if pair and pair[0] is not None:
        if directory is not None:
            raise InputError("give either a folder or --pair RESULT.json SOURCE TARGET, not both")
        result, source, target = pair
        folder = out or result.with_name(f"report-{result.stem}")
        inputs = [(result, "RESULT.json"), (source, "SOURCE"), (target, "TARGET")]
        with claimed(check_outputs(report_plan(folder, inputs, force))):
            rep = report_pair(
                result, source, target, folder, points=points, seed=seed, levels=not no_levels
            )
    elif (
        directory is not None and directory.is_file()
    ):  # an align RESULT.json that names its two clouds
        source, target = pair_files(directory)
        folder = out or directory.with_name(f"report-{directory.stem}")
        inputs = [(directory, "RESULT.json"), (source, "SOURCE"), (target, "TARGET")]
        with claimed(check_outputs(report_plan(folder, inputs, force))):
            rep = report_pair(
                directory, source, target, folder, points=points, seed=seed, levels=not no_levels
            )
    else:
        if directory is None:
            raise InputError(
                "give a register-plot output folder, or --pair RESULT.json SOURCE TARGET"
            )
        if not directory.is_dir():
            raise InputError(f"{directory}: not a folder")
        folder = out or directory / "report"
        inputs = [(directory / n, n) for n in ("poses.json", "graph.json", "report.md")]
        inputs.append((manifest, "manifest"))
        with claimed(check_outputs(report_plan(folder, inputs, force))):
            rep = report_dir(
                directory, folder, manifest, points=points, seed=seed, levels=not no_levels
            )
    typer.echo(f"wrote {rep.index} and {len(rep.figures)} figures")
    if rep.html is not None:
        typer.echo(f"report: {rep.html}")
