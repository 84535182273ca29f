"""tie-to-als: anchor each plot to the ALS and optimise the whole region with the ALS frame fixed.

Per plot: merge its scans with the register-plot poses (voxel-thinned) into one plot cloud, crop
the ALS around it (by approximate CRS positions when the manifest has them, else the whole tile,
where the coarse stage has to find the plot), register plot -> ALS with ForestAlign (TLS K=3 vs
ALS K=2). Each result becomes an edge between the plot's reference scan and an "ALS" node, in one
graph with each plot's scans as register-plot placed them (its poses and sigmas as edges to the
reference). The region is solved in a local frame (ALS CRS minus a recorded offset), and poses are
written in the ALS CRS.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import gtsam
import networkx as nx
import numpy as np

from plotmosaic.align.voxel import voxel_centroids
from plotmosaic.config.register import TieConfig
from plotmosaic.errors import InputError, RegistrationFailed
from plotmosaic.graph.cache import PairCache, pair_key
from plotmosaic.graph.executor import PairJob, prepare_jobs_for
from plotmosaic.graph.posegraph import (
    Solution,
    build_graph,
    graph_from_json,
    graph_to_json,
    inverse,
    optimise,
)
from plotmosaic.graph.prepared import load_points, points_reader, prepare_held
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.frame import Frame, apply_transform, translation
from plotmosaic.io.las import PointCloud, las_offsets, read_cloud, write_cloud
from plotmosaic.manifest import Manifest, Plot, load_manifest
from plotmosaic.poses import Poses, ScanPose, load_poses
from plotmosaic.report.runs import write_tie_report
from plotmosaic.stages.register_plot import EDGE_FIELDS, compute_pairs

ALS_NODE = "ALS"
LAS_SCALE = 0.001  # write_cloud's default: the plot and ALS clouds are written at 1 mm


@dataclass
class Anchor:
    plot: str
    reference: str
    status: str  # "ok" | "failed"
    transform: np.ndarray | None = None  # plot frame -> ALS CRS
    fitness: float | None = None
    inlier_rmse: float | None = None
    overlap: float | None = None
    confidence: float | None = None
    error: str | None = None
    crop: str = "whole tile"
    residual: dict | None = None  # anchor edge residual after the joint solve


@dataclass
class TieResult:
    out: Path
    poses: Poses
    graph: nx.Graph
    anchors: list[Anchor]
    solution: Solution
    offset: np.ndarray
    unplaced: list[str] = field(default_factory=list)
    computed: int = 0
    seconds: float = 0.0


def _voxel(xyz: np.ndarray, size: float) -> np.ndarray:
    """Voxel-thinned points, computed near the origin so UTM-sized values keep their precision."""
    frame = Frame.around(xyz)
    return frame.to_global(voxel_centroids(frame.to_local(xyz), size))


def _scan_points(manifest: Manifest, scan, prepared: dict[str, Path]) -> tuple[np.ndarray, bool]:
    """(the scan's points, whether they are thinned already): register-plot's prepared (delta0-thinned)
    cloud when it is still there, else the file."""
    entry = prepared.get(scan.id)
    if entry is not None and entry.is_file():
        try:
            return load_points(entry), True
        except Exception:  # damaged entry: read the scan itself
            pass
    return read_cloud(manifest.resolve(scan.path), attributes=False).xyz, False


def plot_cloud(
    manifest: Manifest,
    plot: Plot,
    poses: Poses,
    voxel: float,
    prepared: dict[str, Path] | None = None,
) -> PointCloud:
    """All placed scans of the plot in the plot frame, voxel-thinned.

    A scan read from its file is thinned on its own first (memory: its 8M points are not kept);
    a prepared cloud is thinned already (delta0 cubes), so it joins the one pass over the plot."""
    parts = []
    for scan in plot.scans:
        if scan.id in poses.scans:
            xyz, thinned = _scan_points(manifest, scan, prepared or {})
            xyz = apply_transform(poses.transform(scan.id), xyz)
            parts.append(xyz if thinned else _voxel(xyz, voxel))
    if not parts:
        raise InputError(f"plot {plot.id!r}: none of its scans has a pose in the poses file")
    return PointCloud(_voxel(np.concatenate(parts), voxel))


def as_stored(cloud: PointCloud, scale: float = LAS_SCALE) -> PointCloud:
    """The cloud as `write_cloud(path, cloud, scale=scale)` stores it and `read_cloud` gives it back
    (coordinates rounded to `scale` around the writer's offsets): registering this in memory is
    registering the written file, without reading it back."""
    offsets = las_offsets(cloud.xyz.min(axis=0)) if len(cloud) else np.zeros(3)
    xyz = np.empty_like(cloud.xyz)
    for i in range(3):  # the writer's rounding (laspy) and the reader's scaling (io.las.read_cloud)
        raw = np.round((cloud.xyz[:, i] - offsets[i]) / scale).astype(np.int32)
        np.multiply(raw, scale, out=xyz[:, i])
        xyz[:, i] += offsets[i]
    return PointCloud(xyz, crs=cloud.crs)


def load_als(manifest: Manifest) -> tuple[PointCloud, object]:
    if not manifest.als:
        raise InputError(
            f"{manifest.source}: no [[als]] tile in the manifest; tie-to-als needs one"
        )
    clouds = [read_cloud(manifest.resolve(t.path), attributes=False) for t in manifest.als]
    crs = next((c.crs for c in clouds if c.crs is not None), None)
    return PointCloud(np.concatenate([c.xyz for c in clouds]), crs=crs), crs


def crop_als(
    als: PointCloud, plot: Plot, cloud: PointCloud, buffer: float
) -> tuple[PointCloud, str]:
    """ALS within the plot's footprint + buffer when its approximate CRS positions are known, else all of it."""
    approx = [
        s.approx_position
        for s in plot.scans
        if s.approx_position is not None and s.approx_position_frame == "crs"
    ]
    if not approx:
        return als, "whole tile"
    centre = np.mean(np.asarray(approx)[:, :2], axis=0)
    lo, hi = cloud.xyz[:, :2].min(axis=0), cloud.xyz[:, :2].max(axis=0)
    radius = float(np.linalg.norm(hi - lo) / 2 + buffer)
    keep = np.linalg.norm(als.xyz[:, :2] - centre, axis=1) <= radius
    if keep.sum() < 100:
        raise InputError(
            f"plot {plot.id!r}: the ALS has only {int(keep.sum())} points within {radius:.0f} m of the "
            f"plot's approximate position ({centre[0]:.1f}, {centre[1]:.1f}); wrong CRS or position?"
        )
    return als.select(keep), f"{radius:.0f} m around ({centre[0]:.1f}, {centre[1]:.1f})"


def _plot_reference(plot: Plot, poses: Poses, G: nx.Graph | None) -> str:
    """The scan whose frame is the plot frame (identity pose); the manifest's reference otherwise."""
    placed = [s.id for s in plot.scans if s.id in poses.scans]
    recorded = poses.extra.get("plots", {}).get(plot.id, {}).get("reference")
    if recorded in placed:
        return recorded
    for sid in placed:
        if np.allclose(poses.transform(sid), np.eye(4), atol=1e-9):
            return sid
    return plot.reference.id if plot.reference.id in placed else placed[0]


def _plot_edges(plot: Plot, poses: Poses, G: nx.Graph | None, ref: str) -> tuple[dict, list[dict]]:
    """Within-plot edges: each placed scan to the reference as register-plot placed it, its sigmas as
    information. Not the pairs again: register-plot's solve also held them by the ALS placements
    (and confirmed unsure pairs through them), which a re-solve without them would lose (3 cm on
    the `large` preset at 60k); pairs never cross plots, so one anchor moves a plot as one piece."""
    ids = [s.id for s in plot.scans]
    if G is not None and all(s in G for s in ids):
        nodes = {n: dict(G.nodes[n]) for n in ids}  # the scans' files, for `plotmosaic report`
    else:
        nodes = {s.id: {"plot": plot.id, "kind": s.kind.value} for s in plot.scans}
    edges = []
    P_ref = poses.transform(ref)
    for sid in ids:
        if sid == ref or sid not in poses.scans:
            continue
        sp = poses.scans[sid]
        info = (
            None
            if sp.sigma is None
            else np.diag(1.0 / np.maximum(np.asarray(sp.sigma, float), 1e-6) ** 2)
        )
        edges.append(
            {
                "source": sid,
                "target": ref,
                "transform": inverse(P_ref) @ sp.transform,
                "information": info,
                "fitness": 1.0,
                "overlap": 1.0,
                "status": "ok",
                "from_poses": True,
            }
        )
    return nodes, edges


def tie_to_als(
    manifest: str | Path | Manifest,
    poses_path: str | Path,
    out: str | Path,
    config: TieConfig | None = None,
    seed: int = 0,
    jobs: int | None = None,
    executor: str = "local",
    scheduler: str | None = None,
    progress: bool = True,
) -> TieResult:
    start = time.perf_counter()
    config = config or TieConfig()
    manifest = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    poses_path, out = Path(poses_path), Path(out)
    poses = load_poses(poses_path)
    if poses.frame != "plot":
        raise InputError(
            f"{poses_path}: expected register-plot poses (frame 'plot'), got frame {poses.frame!r}"
        )
    graph_path = poses_path.parent / "graph.json"
    G_plot = graph_from_json(json.loads(graph_path.read_text())) if graph_path.is_file() else None
    out.mkdir(parents=True, exist_ok=True)

    if any(s.id == ALS_NODE for s in manifest.scans):
        raise InputError(
            f"{manifest.source}: scan id {ALS_NODE!r} is reserved for the ALS frame in tie-to-als; rename the scan"
        )
    als, crs = load_als(manifest)
    if crs is None:
        raise InputError(
            f"{manifest.resolve(manifest.als[0].path)}: the ALS tile has no CRS; cannot georeference"
        )
    als_frame = Frame.around(als.xyz)  # the region is solved in ALS CRS - offset
    als_k = manifest.als[0].k

    # 1. plot clouds and ALS crops, written once as outputs; their pairs run (and are cached) like any
    # pair, prepared here from the points in memory (exactly what the files hold): nothing is read back
    jobs_list, anchors, refs = [], {}, {}
    config_json = config.align.model_dump_json()
    cache = PairCache(out / "pairs")
    # register-plot's prepared clouds (voxel grids of every scan): no scan is read again to build the plots
    recorded = poses.extra.get("prepared") or {}
    prepared_scans = {
        sid: poses_path.parent / "prepared" / Path(name).name for sid, name in recorded.items()
    }
    for plot in manifest.plots:
        if not any(s.id in poses.scans for s in plot.scans):
            anchors[plot.id] = Anchor(
                plot.id, "", "failed", error="no scan of this plot was placed by register-plot"
            )
            continue
        ref = refs[plot.id] = _plot_reference(plot, poses, G_plot)
        cloud = plot_cloud(manifest, plot, poses, config.plot_voxel, prepared_scans)
        crop, how = crop_als(als, plot, cloud, config.buffer)
        src = write_cloud(out / "plots" / f"{plot.id}.laz", cloud, scale=LAS_SCALE)
        tgt = write_cloud(out / "plots" / f"{plot.id}_als.laz", crop, crs=crs, scale=LAS_SCALE)
        # a merged plot may pass for one scan about the reference scanner (align/viewpoint.py); its only
        # partner is the ALS, which has no scanner, so the final ICP's side test never runs on it
        kind = plot.reference.kind.value
        key = pair_key(src, tgt, kind, "als", plot.reference.k, als_k, config_json, seed)
        job = PairJob(
            key,
            plot.id,
            ALS_NODE,
            str(src),
            str(tgt),
            kind,
            "als",
            plot.reference.k,
            als_k,
            config_json,
            seed,
            str(out / "prepared"),
        )
        if not cache.path(key).is_file():  # a cached result needs neither cloud prepared
            held = (as_stored(cloud), as_stored(crop))
            for pj, points in zip(prepare_jobs_for(job), held):
                prepare_held(pj, points)
        del cloud, crop
        jobs_list.append(job)
        anchors[plot.id] = Anchor(plot.id, ref, "pending", crop=how)
    records, computed = compute_pairs(jobs_list, cache, executor, jobs, scheduler, False, progress)

    # 2. one graph: every plot's pairwise edges + an anchor edge per plot to the fixed ALS node
    nodes, edges = {ALS_NODE: {"kind": "als", "plot": None}}, []
    for plot in manifest.plots:
        if plot.id in refs:
            n, e = _plot_edges(plot, poses, G_plot, refs[plot.id])
            nodes.update(n)
            edges += e
    for job in jobs_list:
        rec, anchor = records[job.key], anchors[job.source]
        if rec.get("status") != "ok":
            anchor.status, anchor.error = "failed", rec.get("error")
            continue
        T = np.asarray(rec["transform"], float)  # plot frame -> ALS CRS
        P_ref = poses.transform(anchor.reference)
        # edge: reference scan file -> ALS local frame; information moved onto the reference scan's tangent
        info = np.asarray(rec["information"], float)
        Ad = gtsam.Pose3(P_ref).AdjointMap()
        edge = {k: rec.get(k) for k in EDGE_FIELDS}
        edge.update(
            source=anchor.reference,
            target=ALS_NODE,
            anchor=job.source,
            transform=translation(-als_frame.offset) @ T @ P_ref,
            information=Ad.T @ info @ Ad,
        )
        edges.append(edge)
        anchor.status, anchor.transform = "ok", T
        anchor.fitness, anchor.inlier_rmse, anchor.overlap, anchor.confidence = (
            rec.get("fitness"),
            rec.get("inlier_rmse"),
            rec.get("overlap"),
            rec.get("confidence"),
        )
    if not any(a.status == "ok" for a in anchors.values()):
        raise RegistrationFailed(
            "no plot could be registered to the ALS: "
            + "; ".join(f"{a.plot}: {a.error}" for a in anchors.values())
        )
    G = build_graph(nodes, edges)
    for _u, _v, e in G.edges(data=True):  # register-plot decisions stand; the rest is re-checked
        e["dropped"] = bool(e.get("dropped"))
    sol = optimise(G, ALS_NODE, config.graph)
    for a in anchors.values():
        if a.status == "ok":
            a.residual = G.edges[a.reference, ALS_NODE].get("residual_after")

    E = translation(als_frame.offset)
    scans = {}
    for name, X in sol.poses.items():
        if name == ALS_NODE:
            continue
        scans[name] = ScanPose(E @ X, G.nodes[name].get("plot"), sol.sigmas[name])
    unplaced = sorted(s.id for s in manifest.scans if s.id not in scans)
    extra = {
        "offset": [float(v) for v in als_frame.offset],
        "unplaced": unplaced,
        "anchors": {a.plot: _anchor_dict(a) for a in anchors.values()},
    }
    result_poses = Poses(scans, frame="crs", crs=crs.to_wkt(), extra=extra)
    result = TieResult(
        out, result_poses, G, list(anchors.values()), sol, als_frame.offset, unplaced, computed
    )
    write_text_atomic(out / "graph.json", json.dumps(graph_to_json(G)))
    result_poses.save(out / "poses.json")
    entries = {
        str(manifest.resolve(s.path)): prepared_scans[s.id]
        for s in manifest.scans
        if s.id in prepared_scans
    }
    result.seconds = time.perf_counter() - start  # the report shows the work before it
    write_tie_report(
        result,
        manifest,
        als,
        config,
        seed,
        reader=points_reader(entries),
        earlier=poses,
        earlier_report=poses_path.parent / "report.html",
    )
    result.seconds = time.perf_counter() - start
    return result


def _anchor_dict(a: Anchor) -> dict:
    return {
        "reference": a.reference,
        "status": a.status,
        "fitness": a.fitness,
        "inlier_rmse": a.inlier_rmse,
        "overlap": a.overlap,
        "confidence": a.confidence,
        "error": a.error,
        "crop": a.crop,
        "residual": a.residual,
    }
