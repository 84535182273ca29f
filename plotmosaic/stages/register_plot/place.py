"""Place: the priors of a run's pairs, from ALS placements of big plots and poses stored in the scans."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plotmosaic.config.register import RegisterConfig
from plotmosaic.graph.cache import PairCache
from plotmosaic.graph.compute import EDGE_FIELDS, compute_pairs
from plotmosaic.graph.executor import Workers
from plotmosaic.graph.jobs import JobSettings, PairJob
from plotmosaic.graph.pairs import manifest_positions
from plotmosaic.graph.placement import placed_poses, placement_jobs, sure_placements
from plotmosaic.io.frame import translation
from plotmosaic.manifest import Manifest, Plot
from plotmosaic.stages.register_plot.pairs import Run, anchor_id


@dataclass(frozen=True, kw_only=True)
class Priors:
    """What is known of the scans' poses before their pairs run."""

    placed: dict[str, np.ndarray]  # scan id -> pose: ALS placements, else poses stored in the scans
    placement: list[PairJob]  # the scan -> ALS tile jobs of big plots without positions
    placement_records: dict[str, dict]
    from_als: set[str]  # scans placed by the ALS step (not stored E57 poses)
    verify_first: set[str]  # scans whose prior is checked before any search
    # plot id -> its scan -> ALS node edges (none unless als_anchors)
    anchors: dict[str, list[dict]]
    # scan id -> the pose its refused ALS placement ended at: never a pose, a start that its map
    # verifies (or not)
    refused: dict[str, np.ndarray]


def placement_plan(
    manifest: Manifest, config: RegisterConfig, seed: int, prepared: Path
) -> list[PairJob]:
    """The scan -> ALS tile jobs of every big plot without positions (prepared clouds in `prepared`)."""
    # the scans prepared with the pairs' settings: one prepared cloud serves both
    settings = JobSettings(config.placement, seed, str(prepared), config.read, config.align)
    jobs = []
    for plot in manifest.plots:
        if len(plot.scans) > config.pairs.all_pairs_up_to and manifest_positions(plot) is None:
            jobs += placement_jobs(manifest, plot, settings)
    return jobs


def place_scans(
    manifest: Manifest,
    config: RegisterConfig,
    seed: int,
    out: Path,
    workers: Workers = Workers(),
    force: bool = False,
) -> tuple[dict[str, np.ndarray], list[PairJob], dict[str, dict]]:
    """Scans of big plots without positions registered to the ALS tile (N pairs instead of N(N-1)/2)."""
    jobs = placement_plan(manifest, config, seed, out / "prepared") if config.place_on_als else []
    if not jobs:
        return {}, [], {}
    records, _ = compute_pairs(jobs, PairCache(out / "placement"), workers, force)
    return placed_poses(jobs, records, config.placement_min_confidence), jobs, records


def als_anchor_edges(
    plot: Plot, placement: list[PairJob], records: dict[str, dict], placed: set[str]
) -> list[dict]:
    """Edges scan -> the plot's ALS node from its kept ALS placements, in a local ALS frame (the ALS
    file coordinates less the placements' mean position, rounded to 1 m: UTM-sized translations
    would make the ALS node's rotation ill-conditioned)."""
    ids = {s.id for s in plot.scans}
    use = [j for j in placement if j.source in ids and j.source in placed]
    if not use:
        return []
    Ts = [np.asarray(records[j.key]["transform"], dtype=float) for j in use]
    shift = translation(-np.round(np.mean([T[:3, 3] for T in Ts], axis=0)))
    out = []
    for j, T in zip(use, Ts, strict=True):
        e = {k: records[j.key].get(k) for k in EDGE_FIELDS}
        e.update(source=j.source, target=anchor_id(plot), transform=shift @ T, via="als")
        out.append(e)
    return out


def place(run: Run) -> Priors:
    """The run's priors: big plots placed on the ALS tile, else the poses stored in the scan files."""
    manifest, config = run.manifest, run.config
    placed, placement, placement_records = place_scans(
        manifest, config, run.seed, run.out, run.workers, run.force
    )
    # poses stored in the scan files (E57 `use_pose = true`) are priors like the ALS step's, one
    # plot at a time so that frames never mix within a plot; the pairwise judge verifies them
    stored = manifest.stored_poses()
    verify_first: set[str] = set()
    for plot in manifest.plots:
        if not any(s.id in placed for s in plot.scans):
            placed.update({s.id: stored[s.id] for s in plot.scans if s.id in stored})
            verify_first |= {s.id for s in plot.scans if s.id in stored}
    sure = config.placed_priors
    if sure.verify_first:  # two sure ALS placements: their relative pose is as good as a stored one
        verify_first |= sure_placements(
            placement, placement_records, sure.sure_placement_confidence
        )
    from_als = set(placed) - set(stored)
    anchors = {
        plot.id: als_anchor_edges(plot, placement, placement_records, from_als)
        if config.als_anchors
        else []
        for plot in manifest.plots
    }
    refused = {
        j.source: np.asarray(r["refused_transform"], dtype=np.float64)
        for j in placement
        if j.source not in placed
        and (r := placement_records.get(j.key, {})).get("refused_transform") is not None
    }
    return Priors(
        refused=refused,
        placed=placed,
        placement=placement,
        placement_records=placement_records,
        from_als=from_als,
        verify_first=verify_first,
        anchors=anchors,
    )
