"""Run the paper's protocol: perturb, register with each method, score against the truth.

Each pair is first put in its true place (source mapped into target coordinates by the ground
truth), optionally cropped to an overlap, then for every trial moved by a random perturbation P
about its centroid. Every method registers the same perturbed source onto the same target; the
truth for the perturbed source is inv(P), so the starting error of a method that begins at
identity is exactly the six sampled parameters (the paper's "random initialisation around the
true alignment").
"""

from __future__ import annotations

import csv
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plotmosaic.bench.failures import plot_failure
from plotmosaic.bench.methods import MethodOutput, PairInput, available, run_method
from plotmosaic.bench.overlap import crop_to_overlap, overlap_fraction
from plotmosaic.bench.protocol import (
    PARAMS,
    is_success,
    params_to_matrix,
    pose_error,
    rotation_angle,
    sample_params,
)
from plotmosaic.bench.tables import markdown_table, plot_errors, summarise
from plotmosaic.config.bench import BenchConfig
from plotmosaic.errors import InputError
from plotmosaic.io.atomic import atomic_output, write_text_atomic
from plotmosaic.io.frame import apply_transform
from plotmosaic.io.las import PointCloud
from plotmosaic.io.progress import progress_bar


@dataclass(frozen=True)
class BenchPair:
    name: str
    source: PointCloud
    target: PointCloud
    truth: np.ndarray  # 4x4 source file coords -> target file coords
    source_kind: str = "tls"
    target_kind: str = "tls"


@dataclass(frozen=True)
class BenchResult:
    rows: list[dict]
    config: BenchConfig
    skipped: dict[str, str] = field(default_factory=dict)  # method -> why it did not run
    pairs: list[str] = field(default_factory=list)

    @property
    def summary(self) -> list[dict]:
        return summarise(self.rows)

    @property
    def table(self) -> str:
        return markdown_table(self.summary)


def _cases(aligned: PointCloud, target: PointCloud, overlaps: list[float] | None):
    """(wanted %, source, target, achieved fraction) for each overlap setting."""
    if not overlaps:
        yield None, aligned, target, overlap_fraction(aligned.xyz, target.xyz)
        return
    for pct in overlaps:
        c = crop_to_overlap(aligned, target, pct / 100.0)
        yield pct, c.source, c.target, c.overlap


def run_bench(
    pairs: list[BenchPair],
    config: BenchConfig,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    failures: Path | None = None,
    max_failure_pictures: int = 3,
) -> BenchResult:
    """Every method on every trial of every pair (and overlap); one row per method x trial.

    `progress` shows a rich bar (terminals); `log` gets one line per finished trial (log files);
    `failures`: a folder for pictures of forestalign's first unsuccessful trials (column 'picture');
    the baselines miss most trials, so they get none.
    """
    skipped = {m: why for m in config.methods if (why := available(m))}
    methods = [m for m in config.methods if m not in skipped]
    if not methods:
        raise InputError(
            "--methods: none of the methods can run here ("
            + "; ".join(f"{m}: {w}" for m, w in skipped.items())
            + ")"
        )
    n_cases = len(config.overlaps) if config.overlaps else 1
    total = len(pairs) * n_cases * config.trials * len(methods)
    rows: list[dict] = []
    pictures = 0
    with progress_bar(progress) as bar:
        task = bar.add_task("bench", total=total)
        for k, pair in enumerate(pairs):
            aligned = PointCloud(
                apply_transform(pair.truth, pair.source.xyz), pair.source.attrs, pair.target.crs
            )
            # one set of perturbations per pair, shared by every method and overlap: paired comparisons
            params = sample_params(config.protocol, config.trials, config.seed + 1009 * k)
            for wanted, src, tgt, achieved in _cases(aligned, pair.target, config.overlaps):
                centre = src.xyz.mean(axis=0)
                for i, p in enumerate(params):
                    P = params_to_matrix(p, centre)
                    moved = PointCloud(apply_transform(P, src.xyz), src.attrs, src.crs)
                    truth = np.linalg.inv(P)
                    job = PairInput(moved, tgt, pair.source_kind, pair.target_kind)
                    for method in methods:
                        label = f"{pair.name} {'' if wanted is None else f'~{wanted:g}% '}{method} trial {i + 1}/{config.trials}"
                        bar.update(task, description=label)
                        out = run_method(method, job, config.methods_config, seed=config.seed + i)
                        err = pose_error(out.transform, truth, centre)
                        row = _row(pair.name, (wanted, achieved), method, i, p, err, out, config)
                        rows.append(row)
                        if (
                            failures is not None
                            and method == "forestalign"
                            and not row["success"]
                            and pictures < max_failure_pictures
                        ):
                            pictures += 1
                            row["picture"] = _failure_picture(
                                row, moved, tgt, out.transform, truth, Path(failures)
                            ).name
                        bar.advance(task)
                        if log:
                            log(
                                f"{label}: rotation {float(rotation_angle(err)[0]):.3f} deg, translation {np.linalg.norm(err[3:]):.3f} m, "
                                f"{'success' if row['success'] else 'miss'}{' (failed)' if row['failed'] else ''}, {row['seconds']:.1f} s"
                            )
    return BenchResult(rows, config, skipped, [p.name for p in pairs])


def _row(
    pair: str,
    overlap: tuple[float | None, float],
    method: str,
    trial: int,
    start: np.ndarray,
    err: np.ndarray,
    out: MethodOutput,
    config: BenchConfig,
) -> dict:
    """One trial of one method: its start, its error (six parameters), success and what it said;
    `overlap` is the one asked for and the one the cut achieved."""
    wanted, achieved = overlap
    ok = bool(is_success(err, config.success_rotation_deg, config.success_translation_m)[0])
    return {
        "pair": pair,
        "overlap_wanted": wanted,
        "overlap": achieved,
        "method": method,
        "trial": trial,
        **{f"init_{name}": float(v) for name, v in zip(PARAMS, start)},
        **{name: float(v) for name, v in zip(PARAMS, err)},
        "success": ok,
        "failed": out.failed,
        "seconds": out.seconds,
        "note": out.note,
        "confidence": out.confidence,
        "picture": "",
    }


def _failure_picture(
    row: dict,
    moved: PointCloud,
    target: PointCloud,
    estimate: np.ndarray,
    truth: np.ndarray,
    folder: Path,
) -> Path:
    slug = "".join(
        ch if ch.isalnum() else "-" for ch in f"{row['pair']}-{row['method']}-trial{row['trial']}"
    ).strip("-")
    err = np.array([row[p] for p in PARAMS])
    init = ", ".join(f"{row[f'init_{p}']:+.1f}" for p in PARAMS)
    title = (
        f"{row['pair']}, {row['method']}, trial {row['trial']}: start (roll, pitch, yaw deg; x, y, z m) = ({init})\n"
        f"error {float(rotation_angle(err)[0]):.2f} deg / {np.linalg.norm(err[3:]):.2f} m"
        f"{' (the method refused it)' if row['failed'] else ''} {row['note']}"
    )
    return plot_failure(moved.xyz, target.xyz, estimate, truth, folder / f"{slug}.png", title)


# ---------------------------------------------------------------- outputs

CSV_FIELDS = [
    "pair",
    "overlap_wanted",
    "overlap",
    "method",
    "trial",
    *[f"init_{p}" for p in PARAMS],
    *PARAMS,
    "success",
    "failed",
    "seconds",
    "note",
    "confidence",
    "picture",
]


def write_trials_csv(rows: list[dict], path: str | Path) -> Path:
    with atomic_output(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=CSV_FIELDS, extrasaction="ignore")
        writer.writeheader()
        for r in rows:
            writer.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in CSV_FIELDS})
    return Path(path)


def write_outputs(
    result: BenchResult, out: str | Path, title: str = "", command: str | None = None
) -> dict[str, Path]:
    """trials.csv, table.md, errors.png (+ one PNG per overlap when swept), summary.json."""
    out = Path(out)
    paths = {"trials": write_trials_csv(result.rows, out / "trials.csv")}
    header = f"## {title}\n\n" if title else ""
    if command:
        header += f"```\n{command}\n```\n\n"
    notes = "".join(f"\n{m}: not run ({why})\n" for m, why in result.skipped.items())
    proto = result.config.protocol
    footer = (
        f"\nProtocol `{proto.name}`: uniform +-{proto.roll:g}/{proto.pitch:g}/{proto.yaw:g} deg roll/pitch/yaw, "
        f"+-{proto.tx:g}/{proto.ty:g}/{proto.tz:g} m; {result.config.trials} trials per pair, seed {result.config.seed}; "
        f"pairs: {', '.join(result.pairs)}. RMSE over all trials; a method that reports failure is scored as identity "
        f"(its initial error) or, when it refuses an estimate it made, as that estimate (column 'failed'); "
        f"success = rotation error < {result.config.success_rotation_deg:g} deg and translation error < {100 * result.config.success_translation_m:g} cm.\n"
    )
    paths["table"] = write_text_atomic(out / "table.md", header + result.table + footer + notes)
    paths["plot"] = plot_errors(result.rows, out / "errors.png", title)
    summary = {
        "protocol": proto.model_dump(),
        "trials": result.config.trials,
        "seed": result.config.seed,
        "pairs": result.pairs,
        "skipped": result.skipped,
        "command": command,
        "summary": result.summary,
    }
    paths["summary"] = write_text_atomic(out / "summary.json", json.dumps(summary, indent=1))
    return paths
