"""`plotmosaic bench`: the paper's evaluation protocol on a pair or on a simulated plot."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

import typer

from plotmosaic.bench.methods import METHODS
from plotmosaic.bench.pairs import load_truth, manifest_pairs
from plotmosaic.bench.protocol import get_protocol
from plotmosaic.bench.run import BenchPair, BenchResult, run_bench, write_outputs
from plotmosaic.commands.common import handle_errors
from plotmosaic.config.align import KINDS
from plotmosaic.config.bench import BenchConfig, MethodsConfig
from plotmosaic.errors import InputError
from plotmosaic.io.las import read_cloud
from plotmosaic.io.outputs import OutputPlan, check_outputs, claimed, inputs_of, manifest_inputs
from plotmosaic.manifest import load_manifest
from plotmosaic.poses import load_poses

# what bench/run.py writes in OUT
BENCH_NAMES = ("trials.csv", "table.md", "errors.png", "summary.json", "failures")


def _floats(text: str | None, option: str) -> list[float] | None:
    if not text:
        return None
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"{option}: {text!r} is not a comma-separated list of numbers") from None


@handle_errors
def bench_command(
    source: Path | None = typer.Argument(
        None, help="Source cloud (LAS/LAZ); omit with --manifest."
    ),
    target: Path | None = typer.Argument(
        None, help="Target cloud (LAS/LAZ); omit with --manifest."
    ),
    gt: str = typer.Option(
        ...,
        "--gt",
        help="Ground truth: 'identity', a JSON with 'transform' (source -> target), or a poses file.",
    ),
    manifest: Path | None = typer.Option(
        None, "--manifest", help="Bench pairs of a plot with known poses (e.g. sim/manifest.toml)."
    ),
    pairs: str = typer.Option(
        "tls-tls", "--pairs", help="With --manifest: tls-tls | tls-als | prepost | all."
    ),
    max_pairs: int | None = typer.Option(
        None, "--max-pairs", min=1, help="With --manifest: only the first N pairs."
    ),
    source_id: str | None = typer.Option(
        None, "--source-id", help="Source scan id in a poses --gt (default: file stem)."
    ),
    target_id: str | None = typer.Option(
        None, "--target-id", help="Target scan id in a poses --gt (default: file stem)."
    ),
    source_kind: str = typer.Option(KINDS[0], "--source-kind", help=" | ".join(KINDS)),
    target_kind: str = typer.Option(KINDS[0], "--target-kind", help=" | ".join(KINDS)),
    trials: int = typer.Option(10, "--trials", min=1, help="Random perturbations per pair."),
    protocol: str = typer.Option(
        "paper",
        "--protocol",
        help="paper (+-45 deg, +-15 m) | beyond (yaw +-180, roll/pitch +-10, +-25 m) | custom",
    ),
    max_rotation: float | None = typer.Option(
        None, "--max-rotation", help="custom: +- roll/pitch (deg), default 45."
    ),
    max_yaw: float | None = typer.Option(
        None, "--max-yaw", help="custom: +- yaw (deg), default = --max-rotation."
    ),
    max_translation: float | None = typer.Option(
        None, "--max-translation", help="custom: +- x/y/z (m), default 15."
    ),
    methods: str = typer.Option(
        "forestalign,icp,fpfh-ransac,cpd",
        "--methods",
        help="Comma-separated: forestalign, icp, fpfh-ransac, cpd.",
    ),
    overlap: str | None = typer.Option(
        None, "--overlap", help="Crop to these overlaps in percent, e.g. 28,15,5,1 (paper Table 1)."
    ),
    no_coarse: bool = typer.Option(
        False,
        "--no-coarse",
        help="forestalign without its global stage, from identity (the paper's local setting).",
    ),
    seed: int = typer.Option(0, "--seed"),
    out: Path = typer.Option(
        Path("bench"), "--out", help="Folder for trials.csv, table.md, errors.png, summary.json."
    ),
    title: str = typer.Option("", "--title", help="Heading of table.md."),
    failure_pictures: int = typer.Option(
        3,
        "--failure-pictures",
        help="PNGs of forestalign's first N unsuccessful trials in OUT/failures.",
    ),
    force: bool = typer.Option(
        False, "--force", help="Write into an OUT holding other files (they are left untouched)."
    ),
) -> None:
    """Paper-style benchmark: per-parameter RMSE, success rate and time over seeded random trials."""
    try:
        proto = get_protocol(protocol, max_rotation, max_yaw, max_translation)
    except ValueError as exc:
        raise InputError(f"--protocol: {exc}") from None
    names = [m.strip() for m in methods.split(",") if m.strip()]
    for m in names:
        if m not in METHODS:
            raise InputError(f"--methods: unknown method {m!r} (choose from {', '.join(METHODS)})")
    config = BenchConfig(
        protocol=proto,
        trials=trials,
        seed=seed,
        methods=names,
        overlaps=_floats(overlap, "--overlap"),
        methods_config=MethodsConfig(no_coarse=no_coarse),
    )
    gt_file = [] if gt.strip().lower() == "identity" else [(Path(gt), "--gt file")]
    if manifest is not None:
        if source or target:
            raise InputError("give either SOURCE TARGET or --manifest, not both")
        m = load_manifest(manifest)
        plan = check_outputs(_plan(out, manifest_inputs(m) + inputs_of(gt_file), force))
        bench_pairs = manifest_pairs(m, load_poses(gt), pairs, max_pairs)
    else:
        if source is None or target is None:
            raise InputError("give SOURCE and TARGET clouds (or --manifest)")
        inputs = inputs_of([(source, "SOURCE"), (target, "TARGET"), *gt_file])
        plan = check_outputs(_plan(out, inputs, force))
        T = load_truth(gt, source, target, source_id, target_id)
        src, tgt = read_cloud(source, attributes=False), read_cloud(target, attributes=False)
        name = f"{source.stem}->{target.stem}"
        bench_pairs = [BenchPair(name, src, tgt, T, source_kind.lower(), target_kind.lower())]
    with claimed(plan):
        result, paths = _run(bench_pairs, config, out, title, failure_pictures)
    typer.echo(result.table, nl=False)
    for m, why in result.skipped.items():
        typer.echo(f"{m}: not run ({why})")
    typer.echo(f"wrote {paths['trials']}, {paths['table']}, {paths['plot']}, {paths['summary']}")


def _plan(out: Path, inputs, force: bool) -> OutputPlan:
    return OutputPlan("bench", inputs, folder=out, names=BENCH_NAMES, force=force)


def _run(
    pairs: list[BenchPair], config: BenchConfig, out: Path, title: str, failure_pictures: int
) -> tuple[BenchResult, dict[str, Path]]:
    """Run the trials (a bar on a terminal, else one line a trial) and write OUT."""
    tty = sys.stderr.isatty()
    result = run_bench(
        pairs,
        config,
        progress=tty,
        log=None if tty else (lambda msg: typer.echo(msg, err=True)),
        failures=out / "failures",
        max_failure_pictures=failure_pictures,
    )
    command = "plotmosaic " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    return result, write_outputs(result, out, title, command)
