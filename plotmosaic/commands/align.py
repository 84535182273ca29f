"""`plotmosaic align`: ForestAlign pairwise registration of SOURCE onto TARGET."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from scipy.spatial.transform import Rotation

from plotmosaic.align.pipeline import align_files
from plotmosaic.align.prepare import MIN_POINTS
from plotmosaic.commands.common import (
    CONFIG_HELP,
    CONFIG_USED,
    handle_errors,
    run_settings,
    write_config_used,
)
from plotmosaic.config.align import DEFAULT_LEVELS, KINDS, MAX_LEVELS
from plotmosaic.errors import InputError
from plotmosaic.io.atomic import check_output_dir, check_output_file
from plotmosaic.io.las import read_header_info
from plotmosaic.io.outputs import OutputPlan, check_outputs, claimed, inputs_of
from plotmosaic.poses import read_json, rigid_matrix

LEVEL_NAMES = ("source_levels.laz", "target_levels.laz", "levels.png")  # what --save-levels writes


def load_init(path: Path) -> np.ndarray:
    """A 4x4 from a JSON file: {"transform": [[...]]} (e.g. a previous RESULT.json) or a bare 4x4 list."""
    data = read_json(path, "init file")
    return rigid_matrix(data.get("transform") if isinstance(data, dict) else data, str(path))


def check_point_counts(files) -> None:
    """Each (path, role) can be read and has enough points to register: a header read, before any work."""
    for path, role in files:
        n = read_header_info(path).point_count
        if n < MIN_POINTS:
            raise InputError(
                f"{path}: only {n} points ({role}), at least {MIN_POINTS} needed to register"
            )


_KIND_HELP = " | ".join(KINDS)
_LEVELS_HELP = ", ".join(f"{k} {v}" for k, v in DEFAULT_LEVELS.items())


def config_used_path(out: Path | None, save_levels: Path | None) -> Path | None:
    """Where `align` writes the settings it used: beside RESULT.json, else in the levels folder."""
    if out is not None:
        return out.with_name(f"{out.stem}.{CONFIG_USED}")
    return save_levels / CONFIG_USED if save_levels is not None else None


def output_plan(source, target, init, config, out, save_levels, force) -> OutputPlan:
    """What `align` writes (RESULT.json, its settings, the levels folder) and what it reads."""
    used = config_used_path(out, save_levels)
    names = LEVEL_NAMES + ((CONFIG_USED,) if out is None else ())
    return OutputPlan(
        "align",
        inputs_of(
            [
                (source, "SOURCE"),
                (target, "TARGET"),
                (init, "--init file"),
                (config, "--config file"),
            ]
        ),
        files=tuple(p for p in (out, used if out is not None else None) if p is not None),
        folder=save_levels,
        names=names if save_levels is not None else (),
        force=force,
    )


def summary_lines(result) -> list[str]:

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
    source_kind: str = typer.Option(KINDS[0], "--source-kind", help=_KIND_HELP),
    target_kind: str = typer.Option(KINDS[0], "--target-kind", help=_KIND_HELP),
    levels_source: int | None = typer.Option(
        None,
        "--levels-source",
        help=f"Complexity levels K of the source, 1 to {MAX_LEVELS} (default by kind: {_LEVELS_HELP}).",
    ),
    levels_target: int | None = typer.Option(
        None, "--levels-target", help="Complexity levels K of the target."
    ),
    init: Path | None = typer.Option(
        None,
        "--init",
        help="Initial guess, JSON: {'transform': 4x4} (e.g. a RESULT.json) or a 4x4 list; source file -> target file coordinates. A prior: the coarse stage searches around it (with --no-coarse, ICP starts from it).",
    ),
    out: Path | None = typer.Option(
        None,
        "--out",
        help=f"Write RESULT.json here (and the settings used as RESULT.{CONFIG_USED} beside it).",
    ),
    save_levels: Path | None = typer.Option(
        None,
        "--save-levels",
        help="Folder for the levels: LAZ per cloud (level attribute) + levels.png.",
    ),
    complexity: str | None = typer.Option(
        None,
        "--complexity",
        help="Grouping signal: vmf (the paper's) | vmf+eigen (vMF + local eigen-features); "
        "default align.complexity of the settings.",
    ),
    coarse: bool | None = typer.Option(
        None,
        "--coarse/--no-coarse",
        help="Run or skip the global coarse stage (skipped: start from --init or identity); "
        "default align.coarse.enabled of the settings.",
    ),
    config: Path | None = typer.Option(None, "--config", help=CONFIG_HELP),
    seed: int = typer.Option(0, "--seed", help="Random seed (same seed, same result)."),
    force: bool = typer.Option(
        False,
        "--force",
        help="Write into a --save-levels folder that holds other files (they are left untouched).",
    ),
) -> None:
    """Register SOURCE onto TARGET with ForestAlign; print the transform and its quality figures.

    Exit 0 on success, 2 on bad input, 3 when the pair cannot be registered (the message shows why).
    """
    for kind, which in ((source_kind, "--source-kind"), (target_kind, "--target-kind")):
        if kind.lower() not in KINDS:
            raise InputError(f"{which} {kind!r}: expected one of {', '.join(KINDS)}")
    for k, which in ((levels_source, "--levels-source"), (levels_target, "--levels-target")):
        if k is not None and not 1 <= k <= MAX_LEVELS:
            raise InputError(f"{which} {k}: expected 1 to {MAX_LEVELS} levels")
    if complexity is not None and complexity not in ("vmf", "vmf+eigen"):
        raise InputError(f"--complexity {complexity!r}: expected vmf or vmf+eigen")
    settings = run_settings(
        config, {"align": {"complexity": complexity, "coarse": {"enabled": coarse}}}
    )
    used = config_used_path(out, save_levels)
    T0 = load_init(init) if init is not None else None
    check_point_counts([(source, "SOURCE"), (target, "TARGET")])
    plan = check_outputs(output_plan(source, target, init, config, out, save_levels, force))
    if out is not None:
        check_output_file(out)
    if save_levels is not None:
        check_output_dir(save_levels)
    if used is not None:
        check_output_file(used)

    console = Console(stderr=True)
    with claimed(plan), console.status("aligning") as status:
        result = align_files(
            source,
            target,
            source_kind,
            target_kind,
            settings.align_config(),
            T0,
            levels_source,
            levels_target,
            seed,
            progress=lambda msg: status.update(msg),
            save_levels=save_levels,
        )
    if out is not None:
        result.save(out)
    if used is not None:
        write_config_used(used, settings, "align")
    typer.echo(f"aligned {source.name} -> {target.name}")
    for line in summary_lines(result):
        typer.echo("  " + line)
    if out is not None:
        typer.echo(f"  result: {out}")
    if save_levels is not None:
        typer.echo(f"  levels: {save_levels}/source_levels.laz, target_levels.laz, levels.png")
    if used is not None:
        typer.echo(f"  settings used: {used}")
