"""`plotmosaic report`: a run's report.md and report.html, written again in its folder, or the
report of one `align` result."""

from __future__ import annotations

from pathlib import Path

import typer

from plotmosaic.commands.common import handle_errors
from plotmosaic.errors import InputError
from plotmosaic.io.outputs import OutputPlan, check_outputs, claimed, inputs_of, read_record
from plotmosaic.poses import load_poses
from plotmosaic.report.align_page import pair_files, report_pair
from plotmosaic.report.build import VIEW3D
from plotmosaic.report.plot_figures import PLOT_FIGURES
from plotmosaic.report.runs import rerender

PAGES = ("report.md", "report.html", VIEW3D)
PAIR_FIGURES = ("before.png", "after.png", "after_slice.png", "levels.png")


def report_plan(
    out: Path, inputs: list[tuple[Path | None, str]], names: tuple[str, ...], force: bool
) -> OutputPlan:
    return OutputPlan("report", inputs_of(inputs), folder=out, names=names, force=force)


def _pair(result: Path, source: Path, target: Path, out: Path | None, points, seed, levels, force):
    folder = out or result.with_name(f"report-{result.stem}")
    inputs = [(result, "RESULT.json"), (source, "SOURCE"), (target, "TARGET")]
    names = (*PAGES, *PAIR_FIGURES, *(f"pair_{f}.png" for f in PLOT_FIGURES))
    with claimed(check_outputs(report_plan(folder, inputs, names, force))):
        return report_pair(result, source, target, folder, points=points, seed=seed, levels=levels)


def _run_plan(directory: Path, manifest: Path | None) -> OutputPlan:
    """The run's report written again as that run (register-plot or tie-to-als) wrote it: its
    files may be replaced, a report.md the user made in the folder is not."""
    poses = directory / "poses.json"
    if not poses.is_file():
        raise InputError(f"{directory}: no poses.json: not a register-plot / tie-to-als folder")
    runs = dict(read_record(directory).runs)
    command = next((c for c in ("tie-to-als", "register-plot") if c in runs), None)
    if command is None:  # a folder written before folders had a record
        command = "tie-to-als" if load_poses(poses).frame == "crs" else "register-plot"
    inputs = [
        (poses, "poses.json"),
        (directory / "graph.json", "graph.json"),
        (manifest, "manifest"),
    ]
    return OutputPlan(
        command,
        inputs_of(inputs),
        folder=directory,
        names=(*PAGES, *(f"*_{f}.png" for f in (*PLOT_FIGURES, "graph"))),
        force=True,  # the run's other outputs stay as they are
        legacy="plots" if command == "tie-to-als" else "pairs",
    )


def _run(directory: Path, manifest: Path | None, seed: int) -> Path:
    if not directory.is_dir():
        raise InputError(f"{directory}: not a folder")
    with claimed(check_outputs(_run_plan(directory, manifest))):
        return rerender(directory, manifest, seed)


@handle_errors
def report_command(
    directory: Path | None = typer.Argument(
        None,
        help="A register-plot / tie-to-als output folder (its report is written again in place), "
        "or an align RESULT.json that names its clouds.",
    ),
    pair: tuple[Path, Path, Path] | None = typer.Option(
        None, "--pair", help="RESULT.json SOURCE TARGET of one `align` run."
    ),
    manifest: Path | None = typer.Option(
        None,
        "--manifest",
        help="Manifest of the run's scans (default: the paths recorded in graph.json).",
    ),
    out: Path | None = typer.Option(
        None, "--out", help="Output folder of an align result's report (default report-<result>)."
    ),
    points: int = typer.Option(
        40_000,
        "--points",
        min=1000,
        help="Points drawn per cloud in an align result's before/after pictures (a seeded subset).",
    ),
    no_levels: bool = typer.Option(
        False,
        "--no-levels",
        help="Skip an align result's structural-complexity figure (it re-runs the levelling).",
    ),
    seed: int = typer.Option(0, "--seed"),
    force: bool = typer.Option(
        False,
        "--force",
        help="Write an align result's report into a folder holding other files (left untouched).",
    ),
) -> None:
    """A registration's report: report.md and report.html (one page: summary, pictures, tables,
    times) and view3d.html. For a run's folder they are written again in place."""
    levels = not no_levels
    if pair and pair[0] is not None:
        if directory is not None:
            raise InputError("give either a folder or --pair RESULT.json SOURCE TARGET, not both")
        md = _pair(*pair, out, points, seed, levels, force)
    elif directory is not None and directory.is_file():  # an align RESULT.json naming its clouds
        md = _pair(directory, *pair_files(directory), out, points, seed, levels, force)
    else:
        if directory is None:
            raise InputError(
                "give a register-plot output folder, or --pair RESULT.json SOURCE TARGET"
            )
        if out is not None and out.resolve() != directory.resolve():
            raise InputError(
                f"{directory}: a run's report is written again in its own folder; --out is for an "
                "align result"
            )
        md = _run(directory, manifest, seed)
    typer.echo(f"wrote {md}")
    typer.echo(f"report: {md.with_name('report.html')}")
