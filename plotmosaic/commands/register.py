"""`plotmosaic register-plot` and `plotmosaic tie-to-als`."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from plotmosaic.commands.common import (
    CONFIG_HELP,
    CONFIG_USED,
    check_poses_match,
    check_scan_files,
    handle_errors,
    no_empty_output,
    run_settings,
    write_config_used,
)
from plotmosaic.config.register import PairSelection, RegisterConfig, TieConfig
from plotmosaic.errors import InputError, PlotmosaicError
from plotmosaic.graph.executor import Workers
from plotmosaic.graph.unplaced import unplaced_reasons
from plotmosaic.io.atomic import check_output_dir
from plotmosaic.io.outputs import (
    Input,
    OutputPlan,
    check_outputs,
    claimed,
    inputs_of,
    manifest_inputs,
)
from plotmosaic.report.plot_figures import PLOT_FIGURES
from plotmosaic.report.tables import edge_counts, fmt
from plotmosaic.stages.register_plot import register_plot
from plotmosaic.stages.tie_to_als import tie_to_als

_REGISTER = RegisterConfig.model_fields
_PAIRS = PairSelection.model_fields
_TIE = TieConfig.model_fields


@contextlib.contextmanager
def _recorded(out: Path, settings, command: str) -> Iterator[None]:
    """Run the stage; the settings it used land in OUT/config-used.toml (also when it fails with
    a result folder to explain)."""
    try:
        yield
    except PlotmosaicError:
        if out.is_dir() and any(out.iterdir()):
            write_config_used(out / CONFIG_USED, settings, command)
        raise
    write_config_used(out / CONFIG_USED, settings, command)


REPORT_FIGURES = PLOT_FIGURES  # per plot: every picture a run's page may write
# what both stages write into OUT besides the per-plot figures (stages/*/write, report/)
_COMMON = ("poses.json", "graph.json", "report.md", "report.html", "view3d.html", CONFIG_USED)
_FORCE_HELP = "write into an OUT holding other files (they are left untouched; never an input)"


def register_plan(manifest, config: Path | None, out: Path, force: bool) -> OutputPlan:
    """What register-plot writes in OUT (stages/register_plot, report/) and what it reads."""
    figures = [f"{p.id}_{f}.png" for p in manifest.plots for f in (*REPORT_FIGURES, "graph")]
    return OutputPlan(
        "register-plot",
        manifest_inputs(manifest) + inputs_of([(config, "--config file")]),
        folder=out,
        names=(*_COMMON, "pairs", "prepared", "placement", "maps", *figures),
        force=force,
        legacy="pairs",  # a folder register-plot wrote before folders had a record
    )


def tie_plan(manifest, poses: Path, config: Path | None, out: Path, force: bool) -> OutputPlan:
    """What tie-to-als writes in OUT (stages/tie_to_als, report/) and what it reads: the
    register-plot folder of --poses (its poses, graph, report and prepared clouds) included."""
    figures = [f"{p.id}_{f}.png" for p in manifest.plots for f in REPORT_FIGURES]
    earlier = poses.parent
    inputs = manifest_inputs(manifest) + inputs_of(
        [
            (poses, "poses file"),
            (earlier / "graph.json", "graph beside --poses"),
            (earlier / "report.html", "report beside --poses"),
            (config, "--config file"),
        ]
    )
    inputs += (Input(earlier / "prepared", "prepared clouds beside --poses", folder=True),)
    return OutputPlan(
        "tie-to-als",
        inputs,
        folder=out,
        names=(*_COMMON, "pairs", "prepared", "plots", *figures),
        force=force,
        legacy="plots",  # a folder tie-to-als wrote before folders had a record
    )


def _check_jobs(jobs: int | None) -> None:
    if jobs is not None and jobs < 1:
        raise InputError(f"--jobs must be at least 1, not {jobs}")


@handle_errors
def register_plot_command(
    manifest: Path = typer.Argument(..., help="Manifest (.toml) of one plot or a region of plots."),
    out: Path = typer.Option(
        ...,
        "--out",
        help="Output folder: poses.json, graph.json, report.md, pictures, pairs/ cache.",
    ),
    jobs: int | None = typer.Option(
        None,
        "--jobs",
        "--workers",
        "-j",
        help="Thread budget shared by worker processes, "
        "their two-thread maps and KD-tree queries (default: number of cores).",
    ),
    executor: str = typer.Option(
        "local", "--executor", help="local (process pool) or dask (a Dask distributed cluster)."
    ),
    scheduler: str | None = typer.Option(
        None,
        "--scheduler",
        help="Dask scheduler address, e.g. tcp://host:8786 (with --executor dask).",
    ),
    max_distance: float | None = typer.Option(
        None,
        "--max-distance",
        help="With approximate positions: skip pairs of scans farther apart (m) "
        f"(default register_plot.max_distance, {_REGISTER['max_distance'].default:g}).",
    ),
    place_on_als: bool | None = typer.Option(
        None,
        "--place-on-als/--no-place-on-als",
        help=f"Plots of more than {_PAIRS['all_pairs_up_to'].default} scans without "
        "positions: register each scan to the ALS first, then only neighbours to each other "
        f"(default register_plot.place_on_als, {'on' if _REGISTER['place_on_als'].default else 'off'}).",
    ),
    config: Path | None = typer.Option(None, "--config", help=CONFIG_HELP),
    seed: int = typer.Option(0, "--seed", help="Random seed (same inputs + seed = same result)."),
    force: bool = typer.Option(
        False,
        "--force",
        help="Register every pair again, ignoring the cache in OUT/pairs/; and "
        + _FORCE_HELP
        + ".",
    ),
) -> None:
    """Register every overlapping pair of scans in each plot and place all scans with a pose graph."""
    _check_jobs(jobs)
    if executor not in ("local", "dask"):
        raise InputError(f"--executor must be 'local' or 'dask', not {executor!r}")
    if scheduler and executor != "dask":
        raise InputError("--scheduler needs --executor dask")
    if max_distance is not None and max_distance <= 0:
        raise InputError(f"--max-distance must be positive, not {max_distance}")
    settings = run_settings(
        config, {"register_plot": {"max_distance": max_distance, "place_on_als": place_on_als}}
    )
    manifest = check_scan_files(manifest)  # bad input found before any work
    plan = check_outputs(register_plan(manifest, config, out, force))
    check_output_dir(out)
    with _recorded(out, settings, "register-plot"), claimed(plan):
        workers = Workers(executor, jobs, scheduler)
        result = register_plot(
            manifest, out, settings.register_config(), workers=workers, seed=seed, force=force
        )
    _summary(
        result.graph,
        [
            (p.plot, p.reference, p.solution.poses, p.solution.sigmas, p.solution.dropped)
            for p in result.plots
        ],
        result.unplaced,
    )
    typer.echo(
        f"pairs: {result.pairs} ({result.computed} registered now, {result.pairs - result.computed} cached); "
        f"{result.seconds:.1f} s"
    )
    typer.echo(
        f"wrote {out / 'poses.json'}, {out / 'graph.json'}, {out / 'report.md'}, {out / CONFIG_USED}"
    )


@handle_errors
def tie_to_als_command(
    manifest: Path = typer.Argument(
        ..., help="Manifest (.toml) with the plots and [[als]] tile(s)."
    ),
    poses: Path = typer.Option(
        ..., "--poses", help="poses.json from register-plot (graph.json beside it is used too)."
    ),
    out: Path = typer.Option(
        ..., "--out", help="Output folder: poses.json in the ALS CRS, graph.json, report.md."
    ),
    buffer: float | None = typer.Option(
        None,
        "--buffer",
        help="ALS kept around each plot (m) when approximate CRS positions are known "
        f"(default tie_to_als.buffer, {_TIE['buffer'].default:g}).",
    ),
    config: Path | None = typer.Option(None, "--config", help=CONFIG_HELP),
    seed: int = typer.Option(0, "--seed", help="Random seed."),
    jobs: int | None = typer.Option(
        None, "--jobs", "-j", help="Plots registered to the ALS at once (default: cores)."
    ),
    force: bool = typer.Option(
        False, "--force", help=_FORCE_HELP[0].upper() + _FORCE_HELP[1:] + "."
    ),
) -> None:
    """Register each plot to the ALS and optimise the whole region with the ALS frame fixed."""
    _check_jobs(jobs)
    if buffer is not None and buffer < 0:
        raise InputError(f"--buffer must not be negative, not {buffer}")
    settings = run_settings(config, {"tie_to_als": {"buffer": buffer}})
    manifest = check_scan_files(manifest)  # bad input found before any work (and before OUT exists)
    check_poses_match(manifest, poses)
    plan = check_outputs(tie_plan(manifest, poses, config, out, force))
    check_output_dir(out)
    with no_empty_output(out), _recorded(out, settings, "tie-to-als"), claimed(plan):
        result = tie_to_als(manifest, poses, out, settings.tie_config(), seed, Workers(jobs=jobs))

    table = Table(title="anchors (plot -> ALS)", title_justify="left")
    columns = ("plot", "status", "fitness", "inlier RMSE (cm)", "fine margin", "ALS - TLS (cm)")
    for name in columns:
        table.add_column(name)
    for a in result.anchors:
        status = a.status if a.status == "ok" else f"failed: {a.error}"
        figures = fmt(a.fitness, 1, 3), fmt(a.inlier_rmse, 100, 2), fmt(a.fine_margin, 1, 2)
        table.add_row(a.plot, status, *figures, _als_offset(a.fit or {}))
    Console(highlight=False).print(table)
    poses = {k: v.transform for k, v in result.poses.scans.items()}
    sigmas = {k: v.sigma for k, v in result.poses.scans.items()}
    _summary(
        result.graph,
        [("region, ALS CRS", "ALS fixed", poses, sigmas, result.solution.dropped)],
        result.unplaced,
    )
    typer.echo(
        f"{result.seconds:.1f} s; wrote {out / 'poses.json'} (ALS CRS), {out / 'report.md'}, "
        f"{out / CONFIG_USED}"
    )


def _als_offset(fit: dict) -> str:
    """The ALS returns' median offset from the TLS surfaces (NMAD): what says how well an anchor holds."""
    if fit.get("als_offset_median_m") is None:
        return "-"
    return f"{fit['als_offset_median_m'] * 100:+.1f} ({fit['als_offset_nmad_m'] * 100:.1f})"


def _summary(G, solves, unplaced: list[str]) -> None:
    console = Console(highlight=False)
    console.print(edge_counts(G, len(G.graph.get("failed", []))))
    for plot, ref, poses, sigmas, dropped in solves:
        for d in dropped:
            console.print(f"  dropped {d['source']} -> {d['target']} ({d['reason']})")
        table = Table(title=f"{plot} (reference {ref})", title_justify="left")
        for name in ("scan", "x (m)", "y (m)", "z (m)", "sigma xyz (mm)", "sigma rot (deg)"):
            table.add_column(name, justify="left" if name == "scan" else "right")
        for name, T in poses.items():
            if name == "ALS":
                continue
            if name == ref:  # the frame itself: its pose and sigmas are zero by construction
                table.add_row(name, *(["-"] * 5))
                continue
            s = sigmas[name]
            sigma_t = " ".join(f"{v * 1000:.1f}" for v in s[3:])
            sigma_r = " ".join(f"{np.degrees(v):.4f}" for v in s[:3])
            table.add_row(name, *(f"{v:.3f}" for v in T[:3, 3]), sigma_t, sigma_r)
        console.print(table)
    for u in unplaced_reasons(G, unplaced):
        console.print(f"not placed: {u.line()}")
