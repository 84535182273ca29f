"""`plotmosaic info`: what is in a LAS/LAZ file or a manifest, validating it on the way."""

from __future__ import annotations

from pathlib import Path

import typer

from plotmosaic.commands.common import handle_errors
from plotmosaic.io.las import read_cloud, read_header_info
from plotmosaic.manifest import load_manifest


def _describe_file(path: Path, full: bool) -> str:
    info = read_header_info(path)
    if full:
        read_cloud(path, attributes=False)  # reads every point: catches truncation and NaNs
    elif info.point_count == 0:
        read_cloud(path)  # raises the "contains no points" error
    crs = info.crs.name if info.crs is not None else "none"
    lo, hi = info.mins, info.maxs
    return (
        f"{path}: {info.point_count:,} points, LAS {info.version} PF{info.point_format}, CRS {crs}\n"
        f"  bounds x {lo[0]:.3f}..{hi[0]:.3f}  y {lo[1]:.3f}..{hi[1]:.3f}  z {lo[2]:.3f}..{hi[2]:.3f}\n"
        f"  dimensions: {', '.join(info.dimensions)}"
    )


@handle_errors
def info_command(
    paths: list[Path] = typer.Argument(..., help="LAS/LAZ files or a manifest (.toml)."),
    full: bool = typer.Option(False, "--full", help="Read every point (finds truncated files and NaNs)."),
) -> None:
    """Describe LAS/LAZ files or validate a manifest and every scan it names."""
    for path in paths:
        if path.suffix.lower() == ".toml":
            manifest = load_manifest(path)
            typer.echo(f"{path}: {len(manifest.plots)} plot(s), {len(manifest.scans)} scan(s), {len(manifest.als)} ALS tile(s)")
            for plot in manifest.plots:
                typer.echo(f"plot {plot.id} (crs {plot.crs or 'none'}, reference {plot.reference.id})")
                for scan in plot.scans:
                    typer.echo(f"  [{scan.kind.value} K={scan.k}] {scan.id}: " + _describe_file(manifest.resolve(scan.path), full))
            for tile in manifest.als:
                typer.echo("  [als] " + _describe_file(manifest.resolve(tile.path), full))
        else:
            typer.echo(_describe_file(path, full))
