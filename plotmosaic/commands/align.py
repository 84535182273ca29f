"""`plotmosaic align`: ForestAlign pairwise registration of SOURCE onto TARGET."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer
from rich.console import Console

from plotmosaic.commands.common import handle_errors
from plotmosaic.errors import InputError
from plotmosaic.poses import read_json, rigid_matrix


def load_init(path: Path) -> np.ndarray:
    """A 4x4 from a JSON file: {"transform": [[...]]} (e.g. a previous RESULT.json) or a bare 4x4 list."""
    data = read_json(path, "init file")
    return rigid_matrix(data.get("transform") if isinstance(data, dict) else data, str(path))


def check_point_counts(files) -> None:
    """Each (path, role) can be read and has enough points to register: a header read, before any work."""
    from plotmosaic.align.prepare import MIN_POINTS
    from plotmosaic.io.las import read_header_info

    for path, role in files:
        n = read_header_info(path).point_count
        if n < MIN_POINTS:
            raise InputError(
                f"{path}: only {n} points ({role}), at least {MIN_POINTS} needed to register"
            )


def summary_lines(result) -> list[str]:
    from scipy.spatial.transform import Rotation

    T = result.transform
    rx, ry, rz = Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True)
    steps = ", ".join(
        f"{s['source_levels']}->{s['target_levels']}" for s in result.levels.get("steps", [])
    )
    return [
        f"rotation (x, y, z) deg: {rx:+.4f} {ry:+.4f} {rz:+.4f}",
        f"translation (m):        {T[0, 3]:+.4f} {T[1, 3]:+.4f} {T[2, 3]:+.4f}",
        f"fitness {result.fitness:.3f}, inlier RMSE {result.inlier_rmse * 100:.1f} cm, overlap {result.overlap:.3f} "
        f"(at 25 cm); levels {steps}; {result.seconds:.1f} s",
    ]


@handle_errors
def align_command(
    source: Path = typer.Argument(..., help="Source LAS/LAZ (moved onto the target)."),
    target: Path = typer.Argument(..., help="Target LAS/LAZ (kept fixed)."),
    source_kind: str = typer.Option("tls", "--source-kind", help="tls | mls | uls | als"),
    target_kind: str = typer.Option("tls", "--target-kind", help="tls | mls | uls | als"),
    levels_source: int | None = typer.Option(
        None,
        "--levels-source",
        help="Complexity levels K of the source (default by kind: tls/mls 3, uls/als 2).",
    ),
    levels_target: int | None = typer.Option(
        None, "--levels-target", help="Complexity levels K of the target."
    ),
    init: Path | None = typer.Option(
        None,
        "--init",
        help="Initial guess, JSON: {'transform': 4x4} (e.g. a RESULT.json) or a 4x4 list; source file -> target file coordinates. A prior: the coarse stage searches around it (with --no-coarse, ICP starts from it).",
    ),
    out: Path | None = typer.Option(None, "--out", help="Write RESULT.json here."),
    save_levels: Path | None = typer.Option(
        None,
        "--save-levels",
        help="Folder for the levels: LAZ per cloud (level attribute) + levels.png.",
    ),
    complexity: str = typer.Option(
        "vmf+eigen",
        "--complexity",
        help="Grouping signal: vmf (the paper's) | vmf+eigen (vMF + local eigen-features).",
    ),
    no_coarse: bool = typer.Option(
        False, "--no-coarse", help="Skip the global coarse stage (start from --init or identity)."
    ),
    seed: int = typer.Option(0, "--seed", help="Random seed (same seed, same result)."),
) -> None:
    """Register SOURCE onto TARGET with ForestAlign; print the transform and its quality figures.

    Exit 0 on success, 2 on bad input, 3 when the pair cannot be registered (the message shows why).
    """
    from plotmosaic.align.config import KINDS, AlignConfig
    from plotmosaic.align.pipeline import align_files
    from plotmosaic.io.atomic import check_output_dir, check_output_file

    for kind, which in ((source_kind, "--source-kind"), (target_kind, "--target-kind")):
        if kind.lower() not in KINDS:
            raise InputError(f"{which} {kind!r}: expected one of {', '.join(KINDS)}")
    for k, which in ((levels_source, "--levels-source"), (levels_target, "--levels-target")):
        if k is not None and not 1 <= k <= 5:
            raise InputError(f"{which} {k}: expected 1 to 5 levels")
    if complexity not in ("vmf", "vmf+eigen"):
        raise InputError(f"--complexity {complexity!r}: expected vmf or vmf+eigen")
    T0 = load_init(init) if init is not None else None
    check_point_counts([(source, "SOURCE"), (target, "TARGET")])
    if out is not None:
        check_output_file(out)
    if save_levels is not None:
        check_output_dir(save_levels)
    config = AlignConfig(complexity=complexity)
    config.coarse.enabled = not no_coarse

    console = Console(stderr=True)
    with console.status("aligning") as status:
        result = align_files(
            source,
            target,
            source_kind,
            target_kind,
            config,
            T0,
            levels_source,
            levels_target,
            seed,
            progress=lambda msg: status.update(msg),
            save_levels=save_levels,
        )
    if out is not None:
        result.save(out)
    typer.echo(f"aligned {source.name} -> {target.name}")
    for line in summary_lines(result):
        typer.echo("  " + line)
    if out is not None:
        typer.echo(f"  result: {out}")
    if save_levels is not None:
        typer.echo(f"  levels: {save_levels}/source_levels.laz, target_levels.laz, levels.png")
