"""register-plot: prepare -> place -> plan -> pairs -> grow -> maps -> solve -> write, one module a
step.

A region manifest is done plot by plot: each plot gets its own frame (its reference scan's file
coordinates); tie-to-als then places the plots in the ALS CRS.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from plotmosaic.config.register import RegisterConfig
from plotmosaic.graph.executor import Workers
from plotmosaic.manifest import Manifest
from plotmosaic.stages.register_plot.grow import close_loops, grow, plot_pair, position_jobs
from plotmosaic.stages.register_plot.maps import onto_maps
from plotmosaic.stages.register_plot.pairs import (
    anchor_id,
    pair_settings,
    prepare,
    run_jobs,
    start_run,
)
from plotmosaic.stages.register_plot.place import als_anchor_edges, place
from plotmosaic.stages.register_plot.plan import match_signatures, plan, plan_jobs, tree_first
from plotmosaic.stages.register_plot.solve import PlotResult, solve, solve_plot
from plotmosaic.stages.register_plot.write import RegisterResult, write

__all__ = [
    "PlotResult",
    "RegisterResult",
    "als_anchor_edges",
    "anchor_id",
    "match_signatures",
    "pair_settings",
    "plot_pair",
    "plan_jobs",
    "position_jobs",
    "register_plot",
    "solve_plot",
    "tree_first",
]


def register_plot(
    manifest: str | Path | Manifest,
    out: str | Path,
    config: RegisterConfig | None = None,
    *,
    workers: Workers = Workers(),
    seed: int = 0,
    force: bool = False,
    on_result: Callable[[dict], None] | None = None,
) -> RegisterResult:
    """Register every plot of `manifest` into `out`: poses.json, graph.json and the report.

    Pair results are cached under OUT/pairs (a run resumes where it stopped; `force` recomputes);
    `on_result` sees each pair record as it is computed; `workers`: where the jobs run. Raises InputError for a bad manifest, an
    output that is a file, or a scan that cannot be read (before any pair runs)."""
    start = time.perf_counter()
    run = start_run(
        manifest, out, config, seed=seed, workers=workers, force=force, on_result=on_result
    )
    prepare(run)  # every scan read once, and a bad one named, before any pair
    priors = place(run)  # big plots' scans on the ALS tile; poses stored in the scans
    planned = plan(run, priors)  # candidate pairs by position, by signature where none
    pairs = run_jobs(run, planned.jobs)  # a spanning tree of them, by the global search
    pairs = close_loops(run, priors, planned.deferred, pairs)  # the rest from the tree's poses
    pairs = grow(run, priors, planned.ranks, pairs)  # more pairs where the graph allows
    pairs = onto_maps(run, priors, pairs)  # scans without a verified pair onto their neighbours
    solved = solve(run, priors, pairs)  # one pose graph, each plot solved in its own frame
    return write(run, priors, pairs, solved, start)
