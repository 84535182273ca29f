"""`plotmosaic simulate`: a simulated forest plot (or region) with TLS + ALS scans and ground truth."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from plotmosaic.commands.common import handle_errors
from plotmosaic.errors import InputError


@handle_errors
def simulate_command(
    outdir: Path = typer.Argument(..., help="Output folder (must be empty unless --force)."),
    preset: str = typer.Option("small", "--preset", help="small | paper | region | grassland | prepost"),
    seed: int = typer.Option(0, "--seed", help="Random seed: the same seed gives the same files."),
    points_per_scan: int | None = typer.Option(None, "--points-per-scan", help="Target points per TLS scan."),
    angular_step: float | None = typer.Option(None, "--angular-step", help="TLS angular step in degrees (overrides --points-per-scan)."),
    max_range: float | None = typer.Option(None, "--max-range", help="TLS maximum range (m)."),
    als_density: float | None = typer.Option(None, "--als-density", help="ALS returns per m2."),
    tree_density: float | None = typer.Option(None, "--tree-density", help="Trees per hectare."),
    conifer_fraction: float | None = typer.Option(None, "--conifer-fraction", help="Share of conifers (0-1)."),
    shrub_density: float | None = typer.Option(None, "--shrub-density", help="Shrubs per hectare."),
    grass_density: float | None = typer.Option(None, "--grass-density", help="Grass tufts per m2."),
    flat_terrain: bool | None = typer.Option(None, "--flat-terrain/--sloped-terrain", help="Near-flat terrain (the hard case)."),
    approx_positions: bool = typer.Option(False, "--approx-positions", help="Write noisy approximate scanner positions (CRS frame)."),
    approx_sigma: float | None = typer.Option(None, "--approx-sigma", help="Noise of the approximate positions (m)."),
    figures: bool = typer.Option(False, "--figures", help="Also write PNG pictures to OUTDIR/figures."),
    force: bool = typer.Option(False, "--force", help="Write into a non-empty OUTDIR."),
) -> None:
    """Simulate a forest plot: terrain, trees, understory; TLS scans, an ALS tile, ground truth and a manifest."""
    from plotmosaic.simulate import simulate

    if outdir.exists() and not outdir.is_dir():
        raise InputError(f"{outdir}: exists and is not a folder")
    if outdir.is_dir() and any(outdir.iterdir()) and not force:
        raise InputError(f"{outdir}: folder is not empty (use --force to write into it)")
    overrides = dict(
        points_per_scan=points_per_scan, angular_step=angular_step, max_range=max_range, als_density=als_density,
        tree_density=tree_density, conifer_fraction=conifer_fraction, shrub_density=shrub_density,
        grass_density=grass_density, flat_terrain=flat_terrain, approx_positions=approx_positions or None,
        approx_sigma_m=approx_sigma,
    )
    columns = [TextColumn("{task.description:<14}"), BarColumn(), TextColumn("{task.completed}/{task.total}"), TimeElapsedColumn()]
    with Progress(*columns, transient=True) as bar:
        task = bar.add_task("building scene", total=None)

        def progress(what: str, done: int, total: int) -> None:
            bar.update(task, description=what, completed=done, total=total)

        result = simulate(outdir, preset=preset, seed=seed, figures=figures, progress=progress, **overrides)
    n_tls = sum(v for k, v in result.points.items() if k != "als")
    scans = [k for k in result.points if k != "als"]
    typer.echo(f"simulated {result.config.name} (seed {seed}) in {result.seconds['total']:.1f} s: "
               f"{len(scans)} TLS scans, {n_tls:,} points ({n_tls // max(len(scans), 1):,} a scan); "
               f"ALS {result.points['als']:,} points, {result.als_density:.1f} pts/m2")
    typer.echo(f"  manifest:     {result.manifest_path}")
    typer.echo(f"  ground truth: {result.ground_truth_path}")
    typer.echo(f"  scans:        {outdir}/<plot>/<scan>.laz ({', '.join(scans[:3])}{', ...' if len(scans) > 3 else ''})")
    typer.echo(f"  ALS:          {', '.join(str(p) for p in result.als_paths)}")
    for fig in result.figures:
        typer.echo(f"  figure:       {fig}")
