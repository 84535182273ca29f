"""`plotmosaic manifest-from`: a manifest for every scan of an E57 project file."""

from __future__ import annotations

import os
from pathlib import Path

import typer

from plotmosaic.commands.common import handle_errors
from plotmosaic.errors import InputError
from plotmosaic.io.atomic import atomic_output
from plotmosaic.io.e57 import E57Scan, is_e57, list_scans
from plotmosaic.io.outputs import OutputPlan, check_outputs, inputs_of
from plotmosaic.manifest import Manifest, Plot, Scan, ScanKind, check_id, dump_manifest, safe_id


def scan_ids(scans: list[E57Scan]) -> list[str]:
    """One valid, unique id per scan: its name made safe for file names, else S<index>."""
    ids: list[str] = []
    for s in scans:
        base = safe_id(s.name) if s.name else f"S{s.index}"
        sid, k = base, 1
        while sid in ids:
            k += 1
            sid = f"{base}-{k}"
        ids.append(sid)
    return ids


def manifest_for(
    e57_path: Path, manifest_dir: Path | None, plot_id: str, kind: ScanKind, use_pose: bool
) -> Manifest:
    """The manifest naming every scan of the file by index; the path relative to `manifest_dir` when the
    file lies under it, else absolute."""
    scans = list_scans(e57_path)
    if not scans:
        raise InputError(f"{e57_path}: holds no scans")
    empty = [s for s in scans if s.point_count == 0]
    if empty:
        raise InputError(f"{e57_path}: {empty[0].label}: contains no points")
    absolute = e57_path.resolve()
    inside = manifest_dir is not None and absolute.is_relative_to(manifest_dir.resolve())
    # no ../../ chains
    path = Path(os.path.relpath(absolute, manifest_dir.resolve())) if inside else absolute
    entries = [
        Scan(id=sid, path=path, kind=kind, scan=s.index, use_pose=use_pose, reference=s.index == 0)
        for sid, s in zip(scan_ids(scans), scans)
    ]
    return Manifest(name=f"scans of {e57_path.name}", plots=[Plot(id=plot_id, scans=entries)])


@handle_errors
def manifest_from_command(
    path: Path = typer.Argument(..., help="An E57 file holding one or more scans."),
    out: Path | None = typer.Option(
        None,
        "--out",
        help="Write the manifest here (paths relative to it) instead of to stdout (absolute paths).",
    ),
    plot_id: str = typer.Option(
        "plot", "--plot-id", help="The plot's id (letters, digits, '-', '_', '.')."
    ),
    kind: ScanKind = typer.Option(ScanKind.tls, "--kind", help="Kind of every scan."),
    use_pose: bool = typer.Option(
        False,
        "--use-pose",
        help="Offer each scan's stored pose as the initial guess (verified, never trusted).",
    ),
    force: bool = typer.Option(
        False, "--force", help="Overwrite an existing --out file (never the E57 file read)."
    ),
) -> None:
    """Write a manifest for every scan of an E57 file (`plotmosaic manifest-from plot.e57 > plot.toml`)."""
    if not is_e57(path):
        raise InputError(f"{path}: not an E57 file (expected .e57)")
    try:
        check_id(plot_id)
    except ValueError as exc:
        raise InputError(f"--plot-id: {exc}") from None
    if out is not None:
        inputs = inputs_of([(path, "E57 file")])
        check_outputs(OutputPlan("manifest-from", inputs, files=(out,), force=force))
    manifest = manifest_for(path, out.parent if out is not None else None, plot_id, kind, use_pose)
    text = dump_manifest(manifest)
    if out is None:
        typer.echo(text, nl=False)
        return
    with atomic_output(out, force=force) as tmp:
        tmp.write_text(text)
    typer.echo(f"{out}: {len(manifest.scans)} scan(s) of {path}", err=True)
