"""`plotmosaic align`: ForestAlign pairwise registration of SOURCE onto TARGET."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer
from rich.console import Console

from plotmosaic.align.pipeline import AlignRequest, align_files
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
from plotmosaic.io.atomic import check_output_dir, write_text_atomic
from plotmosaic.io.las import read_header_info
from plotmosaic.io.matrix import matrix_text
from plotmosaic.io.outputs import OutputPlan, check_outputs, claimed, inputs_of
from plotmosaic.poses import read_json, rigid_matrix

LEVEL_NAMES = ("source_levels.laz", "target_levels.laz", "levels.png")  # what --save-levels writes
MATRIX_DIRECTION = (
    "source file -> target file coordinates: p_target = M @ [x, y, z, 1] of the source"
)


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


_KIND_HELP = f"{' | '.join(KINDS)}; default: detected from the cloud (printed with why)"
_LEVELS_HELP = ", ".join(f"{k} {v}" for k, v in DEFAULT_LEVELS.items())


def config_used_path(out: Path | None, save_levels: Path | None) -> Path | None:
    """Where `align` writes the settings it used: beside RESULT.json, else in the levels folder."""
    if out is not None:
        return out.with_name(f"{out.stem}.{CONFIG_USED}")
    return save_levels / CONFIG_USED if save_levels is not None else None


def matrix_path(out: Path | None) -> Path | None:
    """The 4x4 as text beside RESULT.json (RESULT.matrix.txt), when there is one."""
    return None if out is None else out.with_name(f"{out.stem}.matrix.txt")


def output_plan(source, target, init, config, out, save_levels, force) -> OutputPlan:
    """What `align` writes (RESULT.json with its matrix and settings beside it, the levels folder)
    and reads: the three files beside --out are refused if they exist, unless --force."""
    used = config_used_path(out, save_levels)
    names = LEVEL_NAMES + ((CONFIG_USED,) if out is None else ())
    beside = (out, matrix_path(out), used) if out is not None else ()
    inputs = inputs_of(
        [(source, "SOURCE"), (target, "TARGET"), (init, "--init file"), (config, "--config file")]
    )
    return OutputPlan(
        "align",
        inputs,
        files=tuple(beside),
        folder=save_levels,
        names=names if save_levels is not None else (),
        force=force,
    )


def kind_lines(result) -> list[str]:
    """One line a cloud: its kind, and why (the detection's figures, or the option that gave it)."""
    lines = []
    for role, kind in (("source", result.source_kind), ("target", result.target_kind)):
        found = result.detected_kinds.get(role)
        why = f"detected: {found['reason']}" if found else f"given by --{role}-kind"
        lines.append(f"{role} kind: {kind} ({why})")
    return lines


def summary_lines(result) -> list[str]:
    """What the pose does to the source, in figures a user can check, then its quality."""
    steps = ", ".join(
        f"{s['source_levels']}->{s['target_levels']}" for s in result.levels.get("steps", [])
    )
    confidence = "" if result.confidence is None else f", confidence {result.confidence:.2f}"
    at = result.config.get("quality_distance")
    within = "" if at is None else f" (at {at * 100:g} cm)"
    lines = [f"rotation: {result.rotation_deg:.4f} deg"]
    if result.motion_at_centre_m is not None:
        dx, dy, dz = result.motion_at_centre_m
        lines.append(
            f"the source's bounding-box centre moves (source -> target): dx {dx:+.4f}, "
            f"dy {dy:+.4f}, dz {dz:+.4f} m ({np.linalg.norm([dx, dy, dz]):.4f} m)"
        )
    return lines + [
        f"fitness {result.fitness:.3f}, inlier RMSE {result.inlier_rmse * 100:.1f} cm, "
        f"overlap {result.overlap:.3f}{within}{confidence}; levels {steps}; "
        f"{result.seconds:.1f} s",
    ]


def check_options(source_kind, target_kind, levels_source, levels_target, complexity) -> None:
    """Each option's value in its range: one `error:` line otherwise."""
    for kind, which in ((source_kind, "--source-kind"), (target_kind, "--target-kind")):
        if kind is not None and kind.lower() not in KINDS:
            raise InputError(f"{which} {kind!r}: expected one of {', '.join(KINDS)}")
    for k, which in ((levels_source, "--levels-source"), (levels_target, "--levels-target")):
        if k is not None and not 1 <= k <= MAX_LEVELS:
            raise InputError(f"{which} {k}: expected 1 to {MAX_LEVELS} levels")
    if complexity is not None and complexity not in ("vmf", "vmf+eigen"):
        raise InputError(f"--complexity {complexity!r}: expected vmf or vmf+eigen")


def check_files(source: Path, target: Path, plan: OutputPlan) -> OutputPlan:
    """The inputs readable and large enough, the outputs writable: before any work."""
    check_point_counts([(source, "SOURCE"), (target, "TARGET")])
    plan = check_outputs(plan)
    if plan.folder is not None:
        check_output_dir(plan.folder)
    return plan


def write_outputs(result, settings, out: Path | None, save_levels: Path | None) -> list[str]:
    """RESULT.json, its 4x4 and the settings used; the lines that name them."""
    lines = []
    if out is not None:
        result.save(out)
        write_text_atomic(matrix_path(out), matrix_text(result.transform))
        lines += [f"result: {out}", f"matrix: {matrix_path(out)} (4x4, {MATRIX_DIRECTION})"]
    else:
        lines.append("pass --out RESULT.json to keep the transform (and its 4x4 as text)")
    used = config_used_path(out, save_levels)
    if used is not None:
        write_config_used(used, settings, "align")
    if save_levels is not None:
        lines.append(f"levels: {save_levels}/source_levels.laz, target_levels.laz, levels.png")
    if used is not None:
        lines.append(f"settings used: {used}")
    return lines


@handle_errors
def align_command(
    source: Path = typer.Argument(..., help="Source cloud (moved onto the target)."),
    target: Path = typer.Argument(..., help="Target cloud (kept fixed)."),
    source_kind: str | None = typer.Option(None, "--source-kind", help=_KIND_HELP),
    target_kind: str | None = typer.Option(None, "--target-kind", help=_KIND_HELP),
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
        help=f"Write RESULT.json here, its 4x4 as RESULT.matrix.txt (source -> target) and the settings used as RESULT.{CONFIG_USED} beside it.",
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
        help="Replace RESULT.json and the two files beside it if they exist; write into a "
        "--save-levels folder that holds other files (they are left untouched).",
    ),
) -> None:
    """Register SOURCE onto TARGET with ForestAlign; print the rotation, the motion of the source's
    centre, the kinds and the quality figures.

    Exit 0 on success, 2 on bad input, 3 when the pair cannot be registered (the message shows why).
    """
    check_options(source_kind, target_kind, levels_source, levels_target, complexity)
    settings = run_settings(
        config, {"align": {"complexity": complexity, "coarse": {"enabled": coarse}}}
    )
    T0 = load_init(init) if init is not None else None
    plan = output_plan(source, target, init, config, out, save_levels, force)
    plan = check_files(source, target, plan)
    console = Console(stderr=True)
    with claimed(plan), console.status("aligning") as status:
        request = AlignRequest(
            source_kind=source_kind,
            target_kind=target_kind,
            config=settings.align_config(),
            init=T0,
            levels_source=levels_source,
            levels_target=levels_target,
            seed=seed,
            save_levels=save_levels,
            reading=settings.read,
        )
        result = align_files(source, target, request, progress=lambda msg: status.update(msg))
    written = write_outputs(result, settings, out, save_levels)
    typer.echo(f"aligned {source.name} -> {target.name}")
    for line in kind_lines(result) + summary_lines(result) + written:
        typer.echo("  " + line)
