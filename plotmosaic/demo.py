"""The end-to-end demo: simulate a plot, register it, tie it to ALS, merge, and check against truth."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plotmosaic.config.merge import MergeConfig
from plotmosaic.errors import InputError
from plotmosaic.graph.executor import Workers
from plotmosaic.graph.posegraph import inverse, pose_error
from plotmosaic.io.outputs import OutputPlan, check_outputs, claimed
from plotmosaic.manifest import load_manifest
from plotmosaic.poses import Poses, load_poses
from plotmosaic.report.build import Stage, add_stages
from plotmosaic.simulate.run import simulate
from plotmosaic.stages.merge import merge_scans, sidecar_path
from plotmosaic.stages.register_plot import register_plot
from plotmosaic.stages.tie_to_als import tie_to_als

DEMO_PRESET = "paper"
DEMO_POINTS_PER_SCAN = 400_000  # the paper preset at a modest size: minutes, not hours, on 2 cores
MERGED = "merged.laz"
# what the demo writes in its folder: one sub-folder per stage, the merged cloud and its sidecar
DEMO_NAMES = ("sim", "register", "georeferenced", MERGED, sidecar_path(Path(MERGED)).name)


@dataclass(frozen=True)
class DemoResult:
    outdir: Path
    manifest: Path
    merged: Path
    reports: list[Path]
    html: Path  # the final report.html (georeferenced): summary, slice, distances, map
    plot_errors: dict[str, tuple[float, float]]  # scan -> (deg, m), relative to the plot reference
    # (the reference scans themselves not listed: they are the frame)
    geo_errors: dict[str, tuple[float, float]]  # scan -> (deg, m), in the ALS CRS
    seconds: dict[str, float] = field(default_factory=dict)


def plot_frame_errors(estimated: Poses, truth: Poses) -> dict[str, tuple[float, float]]:
    """Errors of register-plot poses: both sides expressed relative to each plot's reference scan
    (the reference itself left out: it is the frame, its error zero by construction)."""
    errors = {}
    refs = {
        p: next(
            s
            for s, sp in estimated.scans.items()
            if sp.plot == p and np.allclose(sp.transform, np.eye(4))
        )
        for p in {sp.plot for sp in estimated.scans.values()}
    }
    for sid, sp in estimated.scans.items():
        ref = refs[sp.plot]
        if sid == ref:
            continue
        true_rel = inverse(truth.transform(ref)) @ truth.transform(sid)
        errors[sid] = pose_error(sp.transform, true_rel)
    return errors


def georeferenced_errors(estimated: Poses, truth: Poses) -> dict[str, tuple[float, float]]:
    return {
        sid: pose_error(sp.transform, truth.transform(sid)) for sid, sp in estimated.scans.items()
    }


def run_demo(
    outdir: str | Path,
    seed: int = 0,
    points_per_scan: int = DEMO_POINTS_PER_SCAN,
    jobs: int | None = None,
    force: bool = False,
    echo=print,
) -> DemoResult:
    outdir = Path(outdir)
    if outdir.exists() and any(outdir.iterdir()) and not force:
        raise InputError(f"{outdir}: folder is not empty (use --force to reuse it)")
    plan = check_outputs(OutputPlan("demo", folder=outdir, names=DEMO_NAMES, force=force))
    with claimed(plan):
        return _run(outdir, seed, points_per_scan, jobs, echo)


def _run(outdir: Path, seed: int, points_per_scan: int, jobs: int | None, echo) -> DemoResult:
    seconds: dict[str, float] = {}
    workers, geo = Workers(jobs=jobs), outdir / "georeferenced"

    def stage(name: str, start: float) -> None:
        seconds[name] = time.perf_counter() - start
        echo(f"  {name}: {seconds[name]:.1f} s")

    echo(f"1/4 simulating a '{DEMO_PRESET}' forest plot ({points_per_scan:,} points a scan) ...")
    t = time.perf_counter()
    sim = simulate(
        outdir / "sim", DEMO_PRESET, seed=seed, figures=False, points_per_scan=points_per_scan
    )
    stage("simulate", t)
    manifest = load_manifest(sim.manifest_path)
    truth = load_poses(sim.ground_truth_path)

    echo("2/4 register-plot: pairwise ForestAlign (from any start pose) + pose graph ...")
    t = time.perf_counter()
    reg = register_plot(manifest, outdir / "register", workers=workers, seed=seed)
    stage("register-plot", t)

    echo("3/4 tie-to-als: plot -> ALS anchors, joint optimisation in the ALS CRS ...")
    t = time.perf_counter()
    tie = tie_to_als(manifest, outdir / "register" / "poses.json", geo, seed=seed, workers=workers)
    stage("tie-to-als", t)

    echo("4/4 merge: one georeferenced LAZ ...")
    t = time.perf_counter()
    merged = outdir / MERGED
    config = MergeConfig(voxel=0.02, force=True)
    merge_scans(manifest, tie.poses, merged, config, poses_path=geo / "poses.json")
    stage("merge", t)

    page = geo / "report.html"
    # the demo's own stage times, known only now, join the final report's time table
    if page.is_file():
        note = "wall time, report included"
        add_stages(page, [Stage(f"demo: {name}", s, note) for name, s in seconds.items()])

    return DemoResult(
        outdir=outdir,
        html=page,
        manifest=sim.manifest_path,
        merged=merged,
        reports=[outdir / "register" / "report.md", geo / "report.md"],
        plot_errors=plot_frame_errors(reg.poses, truth),
        geo_errors=georeferenced_errors(tie.poses, truth),
        seconds=seconds,
    )
