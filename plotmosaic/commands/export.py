"""`plotmosaic export`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import typer

from plotmosaic.commands.common import CONFIG_HELP, handle_errors, no_empty_output, run_settings
from plotmosaic.commands.merge import merge_options, option_of
from plotmosaic.config.merge import MergeConfig
from plotmosaic.errors import InputError
from plotmosaic.io.outputs import (
    OutputPlan,
    check_not_inputs,
    check_outputs,
    claimed,
    inputs_of,
    manifest_inputs,
)
from plotmosaic.manifest import Manifest, load_manifest
from plotmosaic.poses import load_poses
from plotmosaic.stages.export import (
    FORMATS,
    ExportPlan,
    output_names,
    plan_export,
    points_progress,
    write_copc,
    write_e57,
    write_matrices,
    write_pipeline,
)
from plotmosaic.stages.merge import parse_bbox, sidecar_path

# the merge options each format takes (the others are refused, not ignored)
_TAKES = {
    "matrices": {"skip_missing"},
    "pdal": {"skip_missing", "include_als"},
    "e57": {"skip_missing"},
    "copc": {"skip_missing", "include_als", "voxel", "bbox", "tile_memory_mb"},
}


@handle_errors
def export_command(
    manifest: Path = typer.Argument(..., help="Manifest (.toml) naming the scans (and ALS tiles)."),
    poses: Path = typer.Option(
        ..., "--poses", help="poses.json (ground truth, register-plot or tie-to-als)."
    ),
    to: str = typer.Option(
        ...,
        "--to",
        help="matrices (a folder: one CloudCompare 4x4 text matrix per scan), pdal (a pipeline "
        ".json), e57 (one .e57 with every scan and its pose) or copc (the merged cloud, .copc.laz).",
    ),
    out: Path = typer.Option(..., "--out", help="Output: a folder (matrices) or a file."),
    cloud: Path | None = typer.Option(
        None,
        "--cloud",
        help="pdal: the cloud the pipeline writes (.las/.laz; .copc.laz: writers.copc); "
        "default: --out with .laz.",
    ),
    skip_missing: bool | None = typer.Option(
        None, "--skip-missing", help="Leave out scans without a pose instead of failing."
    ),
    include_als: bool | None = typer.Option(
        None, "--include-als", help="pdal, copc: add the manifest's ALS tiles, as merge does."
    ),
    voxel: float | None = typer.Option(
        None, "--voxel", help="copc: keep one point per voxel of this size (m), as merge does."
    ),
    bbox: str | None = typer.Option(
        None, "--bbox", help="copc: crop to xmin,ymin,xmax,ymax[,zmin,zmax] (output coordinates)."
    ),
    memory_mb: int | None = typer.Option(
        None, "--memory-mb", help="copc: memory (MB) for thinning and for the octree's regions."
    ),
    force: bool = typer.Option(
        False, "--force", help="Overwrite an earlier export (never an input, never another file)."
    ),
    config: Path | None = typer.Option(None, "--config", help=CONFIG_HELP),
) -> None:
    """Export posed scans for other tools: 4x4 matrices, a PDAL pipeline, an E57 with poses, or COPC."""
    if to not in FORMATS:
        raise InputError(f"--to {to!r}: expected one of {', '.join(FORMATS)}")
    given = {
        "skip_missing": skip_missing,
        "include_als": include_als,
        "voxel": voxel,
        "bbox": parse_bbox(bbox) if bbox else None,
        "tile_memory_mb": memory_mb,
    }
    for name, value in given.items():
        if value is not None and name not in _TAKES[to]:
            raise InputError(f"{option_of(name)}: not an option of --to {to}")
    merge = merge_options(run_settings(config).merge, given)
    if cloud is not None and to != "pdal":
        raise InputError(f"--cloud: only with --to pdal, not --to {to}")
    loaded = load_manifest(manifest)
    inputs = manifest_inputs(loaded) + inputs_of([(poses, "poses file"), (config, "--config file")])
    job = Job(to=to, manifest=loaded, poses=poses, out=out, merge=merge)
    if to == "matrices":
        _matrices(job, inputs, force)
        return
    suffix = {"pdal": ".json", "e57": ".e57", "copc": ".copc.laz"}[to]
    if not out.name.lower().endswith(suffix):
        raise InputError(f"{out}: --to {to} writes a {suffix} file")
    files = (out, sidecar_path(out)) if to == "copc" else (out,)
    if to == "pdal":
        cloud = cloud if cloud is not None else out.with_suffix(".laz")
        if not cloud.name.lower().endswith((".las", ".laz")):
            raise InputError(f"--cloud {cloud}: the pipeline writes a .las, .laz or .copc.laz file")
    check_outputs(OutputPlan(f"export {to}", inputs, files=files, force=force))
    if cloud is not None:  # written by PDAL later, never over an input
        check_not_inputs(OutputPlan(f"export {to}", inputs, files=(cloud,)))
    if to == "pdal":
        _pdal(job, cloud)
    elif to == "e57":
        _e57(job)
    else:
        _copc(job)


@dataclass(frozen=True, kw_only=True)
class Job:
    """One export: its format, inputs (manifest loaded, poses file) and output."""

    to: str
    manifest: Manifest
    poses: Path
    out: Path
    merge: MergeConfig

    def plan(self) -> ExportPlan:
        return plan_export(self.manifest, load_poses(self.poses), self.merge, self.poses)


def _matrices(job: Job, inputs, force: bool) -> None:
    plan = job.plan()
    outputs = OutputPlan(
        "export matrices", inputs, folder=job.out, names=output_names(plan), force=force
    )
    check_outputs(outputs)
    with no_empty_output(job.out), claimed(outputs):
        written = write_matrices(plan, job.out)
    typer.echo(f"{len(written) - 1} matrices (frame: {_frame(plan)}) in {job.out}")


def _pdal(job: Job, cloud: Path) -> None:
    plan = job.plan()
    write_pipeline(plan, job.out, cloud)
    typer.echo(f"PDAL pipeline for {len(plan.sources)} sources in {job.out} (writes {cloud})")
    typer.echo(f"run it: pdal pipeline {job.out}")


def _e57(job: Job) -> None:
    plan = job.plan()
    with points_progress(True, "e57", sum(s.info.point_count for s in plan.scans)) as advance:
        written = write_e57(plan, job.out, advance)
    typer.echo(
        f"{len(written)} scans, {sum(n for _, n in written):,} points with their poses "
        f"(frame: {_frame(plan)}) in {job.out}"
    )


def _copc(job: Job) -> None:
    poses = load_poses(job.poses)
    summary = write_copc(job.manifest, poses, job.out, job.merge, job.poses, progress=True)
    typer.echo(
        f"{summary.points:,} points in {summary.nodes} octree nodes (depth {summary.depth}, "
        f"spacing {summary.spacing:g} m) in {job.out}; source table in {sidecar_path(job.out)}"
    )
    if summary.dropped:
        typer.echo(f"note: extra dimensions not in the COPC: {', '.join(summary.dropped)}")


def _frame(plan) -> str:
    return plan.crs.name if plan.frame == "crs" and plan.crs else plan.frame
