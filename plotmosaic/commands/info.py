"""`plotmosaic info`: what is in a LAS/LAZ/E57/PLY file or a manifest, validating it on the way."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from plotmosaic.commands.common import handle_errors
from plotmosaic.errors import InputError
from plotmosaic.io.e57 import E57Scan, iter_e57_chunks, list_scans, scan_ref, split_scan_ref
from plotmosaic.io.frame import rotation_deg
from plotmosaic.io.las import file_format, read_cloud, read_header_info
from plotmosaic.manifest import load_manifest


def _describe_file(path: Path, full: bool) -> str:
    info = read_header_info(path)
    valid = ""
    if full:  # reads every point: catches truncation and NaNs
        n = len(read_cloud(path, attributes=False))
        valid = f" ({info.point_count - n:,} flagged invalid)" if n != info.point_count else ""
    elif info.point_count == 0:
        read_cloud(path)  # raises the "contains no points" error
    crs = info.crs.name if info.crs is not None else "none"
    lo, hi = info.mins, info.maxs
    kind = (
        f"LAS {info.version} PF{info.point_format}" if file_format(path) == "las" else info.version
    )
    return (
        f"{path}: {info.point_count:,} points{valid}, {kind}, CRS {crs}\n"
        f"  bounds x {lo[0]:.3f}..{hi[0]:.3f}  y {lo[1]:.3f}..{hi[1]:.3f}  z {lo[2]:.3f}..{hi[2]:.3f}\n"
        f"  dimensions: {', '.join(info.dimensions)}"
    )


def pose_text(T: np.ndarray | None) -> str:
    if T is None:
        return "no stored pose"
    t = T[:3, 3]
    ident = " (identity)" if np.allclose(T, np.eye(4)) else ""
    return f"pose t = ({t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}) m, rotation {rotation_deg(T):.3f} deg{ident}"


def _describe_e57(path: Path, full: bool) -> str:
    """Every scan of an E57 file: index, name, GUID, point count, stored pose."""
    scans: list[E57Scan] = list_scans(path)
    if not scans:
        raise InputError(f"{path}: holds no scans")
    lines = [f"{path}: E57, {len(scans)} scan(s)"]
    for s in scans:
        if s.point_count == 0:
            raise InputError(f"{path}: {s.label}: contains no points")
        valid = ""
        if full:
            n = sum(
                len(xyz) for xyz, _ in iter_e57_chunks(scan_ref(path, s.index), attributes=False)
            )
            valid = f" ({s.point_count - n:,} flagged invalid)" if n != s.point_count else ""
        name = repr(s.name) if s.name else "(no name)"
        pose = f"unusable stored pose ({s.pose_problem})" if s.pose_problem else pose_text(s.pose)
        lines.append(
            f"  scan {s.index} {name} {s.guid or ''}: {s.point_count:,} points{valid}, {pose}"
        )
    return "\n".join(lines)


@handle_errors
def info_command(
    paths: list[Path] = typer.Argument(..., help="LAS/LAZ/E57/PLY files or a manifest (.toml)."),
    full: bool = typer.Option(
        False, "--full", help="Read every point (finds truncated files and NaNs)."
    ),
) -> None:
    """Describe point-cloud files (an E57: every scan, with its stored pose) or validate a manifest and every scan it names."""
    for path in paths:
        if path.suffix.lower() == ".toml":
            manifest = load_manifest(path)
            typer.echo(
                f"{path}: {len(manifest.plots)} plot(s), {len(manifest.scans)} scan(s), {len(manifest.als)} ALS tile(s)"
            )
            for plot in manifest.plots:
                typer.echo(
                    f"plot {plot.id} (crs {plot.crs or 'none'}, reference {plot.reference.id})"
                )
                for scan in plot.scans:
                    typer.echo(
                        f"  [{scan.kind.value} K={scan.k}] {scan.id}: "
                        + _describe_file(manifest.resolve(scan.path), full)
                    )
            for tile in manifest.als:
                typer.echo("  [als] " + _describe_file(manifest.resolve(tile.path), full))
        elif file_format(path) == "e57" and split_scan_ref(path)[1] is None:
            typer.echo(_describe_e57(path, full))
        else:
            typer.echo(_describe_file(path, full))
