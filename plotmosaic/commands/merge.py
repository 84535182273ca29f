"""`plotmosaic merge`."""

from __future__ import annotations

from pathlib import Path

import typer
from pydantic import ValidationError
from rich.console import Console
from rich.table import Table

from plotmosaic.commands.common import (
    CONFIG_HELP,
    CONFIG_USED,
    handle_errors,
    no_empty_output,
    run_settings,
    write_config_used,
)
from plotmosaic.config.merge import MergeConfig
from plotmosaic.errors import InputError
from plotmosaic.io.atomic import check_output_dir
from plotmosaic.io.outputs import OutputPlan, check_outputs, inputs_of, manifest_inputs
from plotmosaic.manifest import load_manifest
from plotmosaic.poses import load_poses
from plotmosaic.stages.merge import TILE_INDEX, MergeSummary, merge_scans, parse_bbox, sidecar_path

_MERGE = MergeConfig.model_fields


@handle_errors
def merge_command(
    manifest: Path = typer.Argument(..., help="Manifest (.toml) naming the scans (and ALS tiles)."),
    poses: Path = typer.Option(
        ..., "--poses", help="poses.json (ground truth, register-plot or tie-to-als)."
    ),
    out: Path = typer.Option(
        ..., "--out", help="Merged cloud (.laz or .las); a sidecar <out>.json is written beside it."
    ),
    voxel: float | None = typer.Option(
        None, "--voxel", help="Keep one point per voxel of this size (m): evens out TLS density."
    ),
    include_als: bool | None = typer.Option(
        None, "--include-als", help="Add the manifest's ALS tiles, each with its own source id."
    ),
    bbox: str | None = typer.Option(
        None, "--bbox", help="Crop to xmin,ymin,xmax,ymax[,zmin,zmax] in output coordinates."
    ),
    force: bool | None = typer.Option(
        None,
        "--force",
        help="Overwrite an earlier merge output (never an input: scans, ALS, manifest, poses, config).",
    ),
    skip_missing: bool | None = typer.Option(
        None, "--skip-missing", help="Leave out scans without a pose instead of failing."
    ),
    tiles: bool | None = typer.Option(
        None,
        "--tiles",
        help="Write one LAZ per square tile into the folder --out, plus index.json.",
    ),
    tile_size: float | None = typer.Option(
        None,
        "--tile-size",
        help="Tile edge (m) with --tiles; a whole multiple of --voxel "
        f"(default merge.tile_size, {_MERGE['tile_size'].default:g}).",
    ),
    memory_mb: int | None = typer.Option(
        None,
        "--memory-mb",
        help="Memory (MB) for thinning: tiles are cut to fit, whatever the size "
        f"(default merge.tile_memory_mb, {_MERGE['tile_memory_mb'].default}).",
    ),
    config: Path | None = typer.Option(None, "--config", help=CONFIG_HELP),
) -> None:
    """Apply each scan's pose and write one LAS/LAZ 1.4 cloud (point_source_id = scan index)."""
    settings = run_settings(config)
    given = {
        "voxel": voxel,
        "include_als": include_als,
        "bbox": parse_bbox(bbox) if bbox else None,
        "force": force,
        "skip_missing": skip_missing,
        "tiles": tiles,
        "tile_size": tile_size,
        "tile_memory_mb": memory_mb,
    }
    merge = merge_options(settings.merge, given)
    settings = settings.model_copy(update={"merge": merge})
    used = out / CONFIG_USED if merge.tiles else out.with_name(f"{out.stem}.{CONFIG_USED}")
    loaded = load_manifest(manifest)
    check_outputs(output_plan(loaded, poses, config, out, used, merge))
    if merge.tiles:  # the output location is checked (with a real write probe) before any work
        check_output_dir(out.parent if str(out.parent) else Path("."))
    # SIGINT / SIGTERM are the command wrapper's (commands/common.py): they unwind as KeyboardInterrupt
    with no_empty_output(out if merge.tiles else out.parent):  # a failed run leaves no folder
        summary = merge_scans(
            loaded, load_poses(poses), out, merge, progress=True, poses_path=poses
        )
    write_config_used(used, settings, "merge")
    print_summary(summary)
    typer.echo(f"settings used: {used}")


def option_of(key: str) -> str:
    """The command-line option of a [merge] key."""
    return "--memory-mb" if key == "tile_memory_mb" else f"--{key.replace('_', '-')}"


def merge_options(merge: MergeConfig, given: dict) -> MergeConfig:
    """The file's [merge] with the given options over it (None: not given); a bad option is
    named as the option (merge and export)."""
    try:
        return MergeConfig.model_validate(
            merge.model_dump() | {k: v for k, v in given.items() if v is not None}
        )
    except ValidationError as exc:
        err = exc.errors()[0]
        msg = err["msg"].removeprefix("Value error, ")
        if not err["loc"]:  # a check across options names them itself
            raise InputError(msg) from None
        raise InputError(f"{option_of(str(err['loc'][0]))}: {msg}") from None


def output_plan(manifest, poses: Path, config: Path | None, out: Path, used: Path, merge):
    """What `merge` writes (the cloud, its sidecar and settings; or a tile folder) and reads.

    A tile folder is swapped whole for the new one, so it may hold nothing merge did not write."""
    inputs = manifest_inputs(manifest) + inputs_of(
        [(poses, "poses file"), (config, "--config file")]
    )
    if merge.tiles:
        names = ("tile_*.laz", TILE_INDEX, CONFIG_USED)
        return OutputPlan(
            "merge --tiles",
            inputs,
            folder=out,
            names=names,
            replaces_folder=True,
            kind="tile folder",
        )
    files = (out, sidecar_path(out), used)
    return OutputPlan("merge", inputs, files=files, force=merge.force)


def print_summary(summary: MergeSummary) -> None:
    console = Console(highlight=False)
    table = Table(title=f"{summary.out}", title_justify="left")
    for name in ("source id", "scan", "kind", "points in", "points out"):
        table.add_column(name, justify="right" if name.startswith(("points", "source")) else "left")
    for s in summary.sources:
        table.add_row(str(s.source_id), s.id, s.kind, f"{s.points_in:,}", f"{s.points_out:,}")
    table.add_row("", "total", "", f"{summary.points_in:,}", f"{summary.points_out:,}")
    console.print(table)
    lo, hi = summary.mins, summary.maxs
    lines = [
        f"bounds  x {lo[0]:.3f}..{hi[0]:.3f}  y {lo[1]:.3f}..{hi[1]:.3f}  z {lo[2]:.3f}..{hi[2]:.3f}"
    ]
    if summary.crs:
        lines.append(f"CRS     {summary.crs_name} (from {summary.crs_source})")
    else:
        lines.append(f"CRS     none ({summary.crs_source.removeprefix('none: ')})")
    if summary.voxel:
        lines.append(f"voxel   {summary.voxel:g} m (first point of each voxel in scan order)")
    if summary.tiles is not None:
        lines.append(
            f"tiles   {len(summary.tiles)} LAZ files in {summary.out} (index: {summary.sidecar.name})"
        )
    if summary.bbox:
        lines.append(f"bbox    {', '.join(f'{v:.3f}' for v in summary.bbox)}")
    if summary.skipped:
        lines.append(f"left out (no pose): {', '.join(summary.skipped)}")
    if summary.ignored:
        lines.append(
            f"note: poses for scans not in the manifest were ignored: {', '.join(summary.ignored)}"
        )
    lines.append(
        f"{summary.seconds:.1f} s, {summary.points_per_second / 1e6:.2f} M points/s; source id table in {summary.sidecar}"
    )
    for line in lines:
        typer.echo(line)
