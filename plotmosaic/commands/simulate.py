"""`plotmosaic simulate`: a simulated forest plot (or region) with TLS + ALS scans and ground truth."""

from __future__ import annotations

import time
from pathlib import Path

import typer
from pydantic import ValidationError
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from plotmosaic.commands.common import handle_errors
from plotmosaic.config.cuts import DrawnConfig
from plotmosaic.config.simulate import SimulationConfig, grid_layout
from plotmosaic.errors import InputError
from plotmosaic.io.outputs import OutputPlan, check_outputs, claimed, inputs_of
from plotmosaic.simulate.drawn import drawn_plot
from plotmosaic.simulate.from_cloud import cut_cloud_to_folder, parse_positions
from plotmosaic.simulate.run import SimulationResult, make_config, simulate
from plotmosaic.simulate.scene import plot_ids

_WRITES = ("manifest.toml", "ground_truth.json")  # besides one folder per plot (simulate/run.py)

# simulator options that are settings of the config (make_config's names)
_SETTINGS = {
    "--points-per-scan": "points_per_scan",
    "--angular-step": "angular_step",
    "--als-density": "als_density",
    "--tree-density": "tree_density",
    "--crowns": "crowns",
    "--conifer-fraction": "conifer_fraction",
    "--shrub-density": "shrub_density",
    "--grass-density": "grass_density",
    "--flat-terrain": "flat_terrain",
    "--approx-positions": "approx_positions",
    "--approx-sigma": "approx_sigma_m",
}


def simulate_plan(
    outdir: Path, plots: list[str], force: bool, cloud: Path | None = None, drawn: bool = False
):
    """What `simulate` writes in OUTDIR: manifest, ground truth, a folder per plot, als/, figures/."""
    extra = ("als", "figures") if cloud is None and not drawn else ()
    return OutputPlan(
        "simulate",
        inputs_of([(cloud, "--from-cloud cloud")]),
        folder=outdir,
        names=(*_WRITES, *plots, *extra),
        force=force,
    )


@handle_errors
def simulate_command(
    outdir: Path = typer.Argument(..., help="Output folder (must be empty unless --force)."),
    preset: str | None = typer.Option(
        None,
        "--preset",
        help="small (default) | paper | region | grassland | prepost | large | region10 | understorey"
        " | scattered (crowns of scattered foliage, no branches) | bare-stems (open stand, no crowns)",
    ),
    seed: int = typer.Option(0, "--seed", help="Random seed: the same seed gives the same files."),
    points_per_scan: int | None = typer.Option(
        None, "--points-per-scan", help="Target points per TLS scan."
    ),
    angular_step: float | None = typer.Option(
        None, "--angular-step", help="TLS angular step in degrees (overrides --points-per-scan)."
    ),
    max_range: float | None = typer.Option(None, "--max-range", help="TLS maximum range (m)."),
    als_density: float | None = typer.Option(None, "--als-density", help="ALS returns per m2."),
    tree_density: float | None = typer.Option(
        None, "--tree-density", help="Trees per hectare (with bare-stems: stems per hectare)."
    ),
    crowns: str | None = typer.Option(
        None,
        "--crowns",
        help="branches (foliage along branches) | scattered (foliage through the crown volume, no"
        " branches) | none (bare stems).",
    ),
    conifer_fraction: float | None = typer.Option(
        None, "--conifer-fraction", help="Share of conifers (0-1)."
    ),
    shrub_density: float | None = typer.Option(None, "--shrub-density", help="Shrubs per hectare."),
    grass_density: float | None = typer.Option(None, "--grass-density", help="Grass tufts per m2."),
    flat_terrain: bool | None = typer.Option(
        None, "--flat-terrain/--sloped-terrain", help="Near-flat terrain (the hard case)."
    ),
    scan_grid: int | None = typer.Option(
        None,
        "--scan-grid",
        min=1,
        help="Scan positions on an N x N grid per plot (replaces the preset's layout).",
    ),
    scan_spacing: float = typer.Option(
        18.0, "--scan-spacing", help="With --scan-grid: metres between grid positions."
    ),
    approx_positions: bool = typer.Option(
        False, "--approx-positions", help="Write noisy approximate scanner positions (CRS frame)."
    ),
    approx_sigma: float | None = typer.Option(
        None, "--approx-sigma", help="Noise of the approximate positions (m)."
    ),
    figures: bool = typer.Option(
        False, "--figures", help="Also write PNG pictures to OUTDIR/figures."
    ),
    force: bool = typer.Option(
        False,
        "--force",
        help="Write into a non-empty OUTDIR (files no simulate run wrote are left untouched).",
    ),
    drawn: bool = typer.Option(
        False,
        "--drawn",
        help="Draw the forest as points instead of ray casting it (no occlusion but the stems' far"
        " sides, foliage drawn anew for every scan): 45 leaning trees on a 40 m plot, six levelled scans"
        " 30 m range; with --seed, --points-per-scan (default 1,500,000) and --max-range only.",
    ),
    from_cloud: Path | None = typer.Option(
        None,
        "--from-cloud",
        help="Cut virtual scans out of this real cloud (LAS/LAZ) instead of simulating.",
    ),
    positions: str | None = typer.Option(
        None,
        "--positions",
        help="--from-cloud: scanner positions 'x,y;x,y' (or x,y,z), cloud coordinates.",
    ),
    views: int | None = typer.Option(
        None,
        "--views",
        min=1,
        help="--from-cloud: this many positions on a grid around the centre...",
    ),
    spacing: float | None = typer.Option(
        None, "--spacing", help="--from-cloud: ...this far apart (m)."
    ),
    full_density_range: float | None = typer.Option(
        None,
        "--full-density-range",
        help="--from-cloud: points beyond it kept with probability (r0/r)^2 (m).",
    ),
    range_noise: float | None = typer.Option(
        None, "--range-noise", help="--from-cloud: range noise std (m), default 0."
    ),
    occupancy_voxel: float | None = typer.Option(
        None, "--occupancy-voxel", help="--from-cloud: occupancy voxel for the line of sight (m)."
    ),
) -> None:
    """Simulate a forest plot: terrain, trees, understory; TLS scans, an ALS tile, ground truth and a manifest."""
    if outdir.exists() and not outdir.is_dir():
        raise InputError(f"{outdir}: exists and is not a folder")
    if outdir.is_dir() and any(outdir.iterdir()) and not force:
        raise InputError(f"{outdir}: folder is not empty (use --force to write into it)")
    simulator_only = {  # None: not given
        "--preset": preset,
        "--points-per-scan": points_per_scan,
        "--angular-step": angular_step,
        "--als-density": als_density,
        "--tree-density": tree_density,
        "--crowns": crowns,
        "--conifer-fraction": conifer_fraction,
        "--shrub-density": shrub_density,
        "--grass-density": grass_density,
        "--flat-terrain": flat_terrain,
        "--approx-positions": approx_positions or None,
        "--scan-grid": scan_grid,
        "--approx-sigma": approx_sigma,
        "--figures": figures or None,
    }
    if drawn:
        _draw(outdir, simulator_only, from_cloud, seed, points_per_scan, max_range, force)
        return
    if from_cloud is not None:
        clash = [name for name, value in simulator_only.items() if value is not None]
        if clash:
            raise InputError(f"--from-cloud: {clash[0]} applies to the simulator only")
        plan = check_outputs(simulate_plan(outdir, ["P1"], force, from_cloud))
        with claimed(plan):
            _cut(
                outdir,
                from_cloud,
                positions,
                views,
                spacing,
                seed,
                max_range=max_range,
                full_density_range=full_density_range,
                range_noise=range_noise,
                voxel=occupancy_voxel,
            )
        return
    if positions is not None or views is not None or spacing is not None:
        raise InputError("--positions/--views/--spacing need --from-cloud")
    settings = {_SETTINGS[name]: v for name, v in simulator_only.items() if name in _SETTINGS}
    layout = None if scan_grid is None else grid_layout(scan_grid, scan_spacing)
    # before the progress bar: a bad preset is one clean line
    config = make_config(preset or "small", max_range=max_range, scan_layout=layout, **settings)
    _simulate(outdir, config, seed, figures, force)


def _draw(
    outdir: Path,
    given: dict,
    from_cloud: Path | None,
    seed: int,
    points_per_scan: int | None,
    max_range: float | None,
    force: bool,
) -> None:
    """`simulate --drawn`: a forest drawn as points (simulate/drawn.py)."""
    allowed = {"--points-per-scan"}
    clash = [name for name, value in given.items() if value is not None and name not in allowed]
    if from_cloud is not None or clash:
        raise InputError(f"--drawn: {clash[0] if clash else '--from-cloud'} does not apply")
    settings = {"points_per_scan": points_per_scan, "max_range_m": max_range}
    try:
        config = DrawnConfig(**{k: v for k, v in settings.items() if v is not None})
    except ValidationError as exc:
        err = exc.errors()[0]
        raise InputError(f"--drawn: {'.'.join(map(str, err['loc']))}: {err['msg']}") from None
    plan = check_outputs(simulate_plan(outdir, ["P1"], force, drawn=True))
    t0 = time.perf_counter()
    with claimed(plan):
        manifest = drawn_plot(outdir, seed, config)
    typer.echo(
        f"drew {len(config.scan_layout)} scans of a forest drawn as points (seed {seed}) in"
        f" {time.perf_counter() - t0:.1f} s"
    )
    typer.echo(f"  manifest:     {manifest}")
    typer.echo(f"  ground truth: {outdir / 'ground_truth.json'}")


def _simulate(
    outdir: Path, config: SimulationConfig, seed: int, figures: bool, force: bool
) -> None:
    """Run the simulator under a progress bar, then say what it wrote."""
    plan = check_outputs(simulate_plan(outdir, plot_ids(config), force))
    columns = [
        TextColumn("{task.description:<14}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
    ]
    with claimed(plan), Progress(*columns, transient=True) as bar:
        task = bar.add_task("building scene", total=None)

        def progress(what: str, done: int, total: int) -> None:
            bar.update(task, description=what, completed=done, total=total)

        result = simulate(outdir, seed=seed, figures=figures, progress=progress, config=config)
    _echo_simulation(result, outdir, seed)


def _echo_simulation(result: SimulationResult, outdir: Path, seed: int) -> None:
    n_tls = sum(v for k, v in result.points.items() if k != "als")
    scans = [k for k in result.points if k != "als"]
    typer.echo(
        f"simulated {result.config.name} (seed {seed}) in {result.seconds['total']:.1f} s: "
        f"{len(scans)} TLS scans, {n_tls:,} points ({n_tls // max(len(scans), 1):,} a scan); "
        f"ALS {result.points['als']:,} points, {result.als_density:.1f} pts/m2"
    )
    typer.echo(f"  manifest:     {result.manifest_path}")
    typer.echo(f"  ground truth: {result.ground_truth_path}")
    typer.echo(
        f"  scans:        {outdir}/<plot>/<scan>.laz ({', '.join(scans[:3])}{', ...' if len(scans) > 3 else ''})"
    )
    typer.echo(f"  ALS:          {', '.join(str(p) for p in result.als_paths)}")
    for fig in result.figures:
        typer.echo(f"  figure:       {fig}")


def _cut(
    outdir: Path,
    cloud: Path,
    positions: str | None,
    views: int | None,
    spacing: float | None,
    seed: int,
    **settings,
) -> None:
    """`simulate --from-cloud`: virtual scans of a real cloud, ground truth and a manifest."""
    if positions is not None and (views is not None or spacing is not None):
        raise InputError("--from-cloud: give --positions or --views/--spacing, not both")
    parsed = parse_positions(positions) if positions is not None else None
    result = cut_cloud_to_folder(outdir, cloud, parsed, views, spacing, seed, **settings)
    total = sum(result.points.values())
    typer.echo(
        f"cut {len(result.points)} virtual scans from {cloud} (seed {seed}) in {result.seconds['total']:.1f} s: "
        f"{total:,} points ({total // max(len(result.points), 1):,} a scan)"
    )
    for sid, n in result.points.items():
        pos = ", ".join(f"{v:.2f}" for v in result.positions[sid])
        typer.echo(f"  {sid}: {n:,} points, scanner at ({pos})")
    typer.echo(f"  manifest:     {result.manifest_path}")
    typer.echo(f"  ground truth: {result.ground_truth_path}")
