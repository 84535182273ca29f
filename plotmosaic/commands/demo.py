"""`plotmosaic demo`: the whole chain on a simulated plot, with errors against ground truth."""

from __future__ import annotations

from pathlib import Path

import typer

from plotmosaic.commands.common import handle_errors
from plotmosaic.demo import run_demo


@handle_errors
def demo_command(
    outdir: Path = typer.Argument(
        Path("demo-output"), help="Folder for the simulated data and every result."
    ),
    seed: int = typer.Option(0, help="Seed of the simulation and of every random choice."),
    points_per_scan: int = typer.Option(400_000, help="TLS points per scan of the simulated plot."),
    jobs: int = typer.Option(None, help="Parallel pair jobs (default: number of cores)."),
    force: bool = typer.Option(
        False,
        "--force",
        help="Reuse a non-empty output folder (files no demo run wrote are left untouched).",
    ),
) -> None:
    """Simulate a forest plot (5 TLS scans + ALS), run register-plot, tie-to-als and merge, report errors."""
    result = run_demo(
        outdir, seed=seed, points_per_scan=points_per_scan, jobs=jobs, force=force, echo=typer.echo
    )
    typer.echo("")
    typer.echo("pose errors against the simulator's ground truth")
    typer.echo(f"  {'scan':<10} {'plot frame':>22} {'ALS CRS (georeferenced)':>28}")
    for sid in sorted(result.geo_errors):
        gr, gt = result.geo_errors[sid]
        if sid in result.plot_errors:
            pr, pt = result.plot_errors[sid]
            plot = f"{pt * 100:8.2f} cm {pr:7.3f} deg"
        else:
            plot = f"{'(the plot frame)':>22}"  # the reference: zero by construction
        typer.echo(f"  {sid:<10} {plot} {gt * 100:12.2f} cm {gr:7.3f} deg")
    plot_errors, geo_errors = result.plot_errors.values(), result.geo_errors.values()
    worst = (
        [
            f"plot frame {max(e[1] for e in plot_errors) * 100:.2f} cm / "
            f"{max(e[0] for e in plot_errors):.3f} deg"
        ]
        if plot_errors
        else []
    )
    worst.append(
        f"georeferenced {max(e[1] for e in geo_errors) * 100:.2f} cm / "
        f"{max(e[0] for e in geo_errors):.3f} deg"
    )
    typer.echo(f"  worst: {', '.join(worst)}")
    typer.echo("")
    typer.echo(f"merged LAZ:  {result.merged}")
    for report in result.reports:
        typer.echo(f"report:      {report} (pictures beside it)")
    typer.echo(f"total time:  {sum(result.seconds.values()):.0f} s")
    typer.echo(f"open in a browser (one self-contained page): {result.html}")
