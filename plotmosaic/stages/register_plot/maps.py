"""Maps: every scan without a verified pair placed onto the union of the placed scans near it.

A round gives each such scan a map of its neighbours at the poses the pose graph holds now (its start
too: that pose, or its ALS placement; a scan nothing placed is searched against the whole plot), and
its verified placement becomes edges to the neighbours it overlaps. The graph is solved again and the
next round measures the maps from there, until no scan moves (the survey settles as one), so a scan
placed by its ALS placement alone ends up held by its neighbours' surfaces too.
"""

from __future__ import annotations

import numpy as np

from plotmosaic.graph.cache import PairCache, settings_json
from plotmosaic.graph.executor import run_pairs
from plotmosaic.graph.jobs import ScanFile, prepare_job
from plotmosaic.graph.maps import MapJob, Member, map_key, run_map_job
from plotmosaic.graph.pairs import reach_distance
from plotmosaic.graph.prepared import PrepareJob, get_prepared
from plotmosaic.graph.survey import SurveySettings, refine_survey
from plotmosaic.io.frame import inverse, pose_error
from plotmosaic.manifest import Plot
from plotmosaic.stages.register_plot.grow import graph_poses
from plotmosaic.stages.register_plot.pairs import Pairs, Run
from plotmosaic.stages.register_plot.place import Priors


def onto_maps(run: Run, priors: Priors, pairs: Pairs) -> Pairs:
    """The pairs with the edges of the survey refined on its maps (or of the last map round)."""
    maps = run.config.maps
    if not maps.enabled:
        return pairs
    cache = PairCache(run.out / "maps")
    prepared = _prepare_jobs(run)
    before = graph_poses(run.manifest, run.config, pairs, priors.anchors)
    placing = _without_pairs(run, pairs)
    for _ in range(maps.rounds):
        jobs = [
            job
            for plot in run.manifest.plots
            for job in _plot_jobs(run, plot, priors, before, placing, prepared)
        ]
        if not jobs:
            break
        records = _run(run, cache, jobs)
        edges = tuple(e for job in jobs for e in _edges(records.get(job.key, {})))
        pairs = Pairs(jobs=pairs.jobs, records=pairs.records, computed=pairs.computed, maps=edges)
        after = graph_poses(run.manifest, run.config, pairs, priors.anchors)
        if _settled(before, after, maps.settled_m, maps.settled_deg):
            break
        before = after
    if not maps.survey:
        return pairs
    surveyed = _surveyed(
        run, prepared, pairs, graph_poses(run.manifest, run.config, pairs, priors.anchors)
    )
    return Pairs(jobs=pairs.jobs, records=pairs.records, computed=pairs.computed, maps=surveyed)


def _surveyed(
    run: Run, prepared: dict[str, PrepareJob], pairs: Pairs, poses: dict[str, np.ndarray]
) -> tuple[dict, ...]:
    """The map edges again from the survey refined as one (graph/survey.py): the verified map
    placements' scan-member pairs, both ways, every plot with its reference among them."""
    maps = run.config.maps
    settings = SurveySettings(
        lens_distance=run.config.align.lens_distance,
        points=maps.survey_points,
        schedule=tuple(maps.survey_schedule),
        kernel=run.config.align.final_polish_kernel,
        min_points=maps.min_edge_points,
        patch=maps.survey_patch_m,
    )
    out: list[dict] = [e for e in pairs.maps if e.get("status") != "ok"]
    for plot in run.manifest.plots:
        ids = {s.id for s in plot.scans}
        own = [e for e in pairs.maps if e.get("status") == "ok" and e["source"] in ids]
        linked = sorted(
            {(e["source"], e["target"]) for e in own} | {(e["target"], e["source"]) for e in own}
        )
        scans = {s for pair in linked for s in pair}
        if plot.reference.id not in scans or not all(s in poses for s in scans):
            out += own
            continue
        clouds = {s: get_prepared(prepared[s])[0] for s in sorted(scans)}
        _, edges = refine_survey(
            clouds, {s: poses[s] for s in scans}, linked, plot.reference.id, settings
        )
        by_source = {e["source"]: e for e in own}
        for e in edges:
            verified = by_source.get(e.source) or by_source.get(e.target)
            out.append(
                {
                    "source": e.source,
                    "target": e.target,
                    "key": f"survey:{e.source}:{e.target}",
                    "status": "ok",
                    "transform": e.transform.tolist(),
                    "information": e.information.tolist(),
                    "confidence": verified.get("confidence"),
                    "overlap": verified.get("overlap"),
                    "via": "map",
                }
            )
    return tuple(out)


def _without_pairs(run: Run, pairs: Pairs) -> set[str]:
    """Scans of plots of three or more scans with no verified pair."""
    paired = {
        s
        for j in pairs.jobs
        if pairs.records.get(j.key, {}).get("status") == "ok"
        for s in (j.source, j.target)
    }
    return {s.id for p in run.manifest.plots if len(p.scans) >= 3 for s in p.scans} - paired


def _prepare_jobs(run: Run) -> dict[str, PrepareJob]:
    """scan id -> its prepare job (the entries `prepare` made)."""
    return {
        s.id: prepare_job(run.settings, ScanFile.of(run.manifest, s)) for s in run.manifest.scans
    }


def _start(scan: str, poses: dict[str, np.ndarray], priors: Priors) -> np.ndarray | None:
    """Where the scan starts: its pose in the graph, else its ALS placement, else the pose its
    refused placement ended at (verified on the map like any start), else nowhere."""
    if scan in poses:
        return poses[scan]
    als = priors.placed.get(scan) if scan in priors.from_als else priors.refused.get(scan)
    # placements are in the ALS frame: carried into the plot frame by a scan placed in both
    both = sorted(k for k in poses if k in priors.from_als)
    if als is None or not both:
        return None
    return poses[both[0]] @ inverse(priors.placed[both[0]]) @ als


def _plot_jobs(
    run: Run,
    plot: Plot,
    priors: Priors,
    poses: dict[str, np.ndarray],
    placing: set[str],
    prepared: dict[str, PrepareJob],
) -> list[MapJob]:
    """The plot's map jobs: one for each scan to place that has placed scans to place it on."""
    maps = run.config.maps
    ids = [s.id for s in plot.scans]
    placed = [i for i in ids if i in poses]
    if len(placed) < 1:
        return []
    xy = np.array([poses[i][:2, 3] for i in placed])
    far = reach_distance(xy, maps.reach, None) if len(placed) >= 2 else None
    jobs = []
    for scan in (i for i in ids if i in placing):
        start = _start(scan, poses, priors)
        if start is None:  # placed by nothing: searched against the whole plot, thinned
            near, thin = [i for i in placed if i != scan], maps.thin_voxel
        else:
            d = {i: float(np.linalg.norm(poses[i][:2, 3] - start[:2, 3])) for i in placed}
            near = [i for i in placed if i != scan and (far is None or d[i] <= far)]
            thin = None
        if not near:
            continue
        members = tuple(Member(scan=i, prepared=prepared[i], pose=_rows(poses[i])) for i in near)
        fields = {
            "source": prepared[scan].key,
            "members": [(m.prepared.key, m.pose) for m in members],
            "init": None if start is None else _rows(start),
            "settings": settings_json(run.config.align),
            "maps": maps.model_dump(),
            "seed": run.seed,
        }
        jobs.append(
            MapJob(
                key=map_key(fields),
                source=scan,
                prepared=prepared[scan],
                members=members,
                init=None if start is None else _rows(start),
                margin=maps.margin_m,
                thin=thin,
                config=run.config.align,
                seed=run.seed,
                edge_distance=maps.edge_distance,
                min_edge_points=maps.min_edge_points,
            )
        )
    return jobs


def _rows(T: np.ndarray) -> tuple:
    return tuple(tuple(float(v) for v in row) for row in np.asarray(T, dtype=np.float64))


def _run(run: Run, cache: PairCache, jobs: list[MapJob]) -> dict[str, dict]:
    """Records by key, from the cache where present (a re-run repeats no map placement)."""
    records = {} if run.force else {j.key: r for j in jobs if (r := cache.get(j.key)) is not None}

    def keep(record: dict) -> None:
        if record.get("status") == "ok" or record.pop("cacheable", False):
            cache.put(record["key"], record)
        records[record["key"]] = record
        if run.on_result is not None:
            run.on_result(record)

    todo = [j for j in jobs if j.key not in records]
    run_pairs(todo, run.workers, keep, worker=run_map_job, label="scans onto maps")
    return records


def _edges(record: dict) -> list[dict]:
    """A verified map placement's edges, one to each member it overlaps; a refused one as a failed
    record (the report names it as the scan's attempt)."""
    if not record:
        return []
    if record.get("status") != "ok":
        keep = ("source", "target", "key", "status", "error", "overlap", "confidence")
        return [{k: record.get(k) for k in keep}]
    return [
        {
            "source": e["source"],
            "target": e["target"],
            "key": f"{record['key']}:{e['target']}",
            "status": "ok",
            "transform": e["transform"],
            "information": e["information"],
            "confidence": record.get("confidence"),
            "overlap": record.get("overlap"),
            "fitness": record.get("fitness"),
            "inlier_rmse": record.get("inlier_rmse"),
            "seconds": record.get("seconds"),
            "via": "map",
        }
        for e in record.get("edges", [])
    ]


def _settled(
    before: dict[str, np.ndarray], after: dict[str, np.ndarray], metres: float, degrees: float
) -> bool:
    """No scan placed before moved or turned more than this, and none was placed anew."""
    if set(after) - set(before):
        return False
    for scan, T in after.items():
        deg, m = pose_error(before[scan], T)
        if m > metres or deg > degrees:
            return False
    return True
