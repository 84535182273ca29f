"""Scan-to-map placement: one scan registered against the union of scans already placed near it.

Scans 15-20 m apart whose views are cut short by understorey overlap a neighbour by 0.1-0.2: too
thin for one pair, but the scan overlaps its two to four placed neighbours together by far more. The
map is their prepared points carried into the plot frame by their current poses (cropped to where
the scan can reach), prepared like a scan (no viewpoint: it is many stations), and the scan is
registered onto it by the one pairwise path (`register_prepared`): verified from its start when it
has one (its ALS placement or its pose in the graph), else searched from anywhere, and judged.

A verified pose becomes one edge to each map member the scan overlaps, the member's share of the
final point-to-plane problem as its information: the edges carry what the map measured, split by
whose surfaces measured it, so the pose graph weighs and checks them as it does pairs.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.align.fine import LENS_SEED
from plotmosaic.align.icp import information_matrix, nearest
from plotmosaic.align.memo import PairMemo
from plotmosaic.align.pair import Start, register_prepared
from plotmosaic.align.prepare import MIN_POINTS, PreparedCloud, prepare_cloud
from plotmosaic.align.sampling import sample
from plotmosaic.align.voxel import thin
from plotmosaic.config.align import AlignConfig, default_levels
from plotmosaic.errors import RegistrationFailed
from plotmosaic.graph.prepared import PrepareJob, get_prepared
from plotmosaic.io.frame import inverse, to_global_transform, to_local_transform
from plotmosaic.io.las import PointCloud

MAP_ID = "map"  # the target's name in a record: a map is no scan
MATCHED_POINTS = 40_000  # scan points whose matches split the map's information among members


@dataclass(frozen=True, kw_only=True)
class Member:
    """A placed scan of a map: its prepared cloud and its pose (scan file -> plot frame, rows)."""

    scan: str
    prepared: PrepareJob
    pose: tuple


@dataclass(frozen=True, kw_only=True)
class MapJob:
    """Everything a worker needs to place one scan onto its map (plain data, as PairJob)."""

    key: str
    source: str
    prepared: PrepareJob  # the scan's prepared cloud
    members: tuple[Member, ...]
    init: tuple | None  # scan file -> plot frame: its start (verified there first), None: anywhere
    margin: float  # with a start, the map is cropped this far (m) beyond where the scan reaches
    thin: float | None  # voxel (m) each member is thinned to (a whole-plot map), None: as prepared
    config: AlignConfig
    seed: int
    edge_distance: float  # correspondences (m) that give a member its share of the information
    min_edge_points: int  # fewer: the member gets no edge (it barely overlaps the scan)


def map_key(job_fields: dict) -> str:
    """A map job's key: its scans' prepared keys, the members' poses, start, crop and settings."""
    text = json.dumps(job_fields, sort_keys=True, default=_rounded)
    return "map-" + hashlib.sha256(text.encode()).hexdigest()[:32]


def _rounded(value):
    return np.round(np.asarray(value, dtype=float), 9).tolist()


def reach(src: PreparedCloud, init: np.ndarray, margin: float) -> tuple[np.ndarray, float]:
    """(centre xy in the plot frame, radius): where the scan at its start can see, with a margin."""
    xyz = src.frame.to_global(src.level_points)
    c = xyz.mean(axis=0)
    radius = float(np.percentile(np.linalg.norm(xyz[:, :2] - c[:2], axis=1), 98)) + margin
    return (init[:3, :3] @ c + init[:3, 3])[:2], radius


def map_cloud(
    job: MapJob, members: list[PreparedCloud], crop: tuple[np.ndarray, float] | None
) -> PointCloud:
    """The members' points in the plot frame (within `crop`, thinned to `job.thin`)."""
    parts = []
    for m, cloud in zip(job.members, members):
        pts = cloud.points if job.thin is None else cloud.points[thin(cloud.points, job.thin)]
        P = np.asarray(m.pose, dtype=np.float64)
        xyz = cloud.frame.to_global(pts) @ P[:3, :3].T + P[:3, 3]
        if crop is not None:
            xyz = xyz[np.linalg.norm(xyz[:, :2] - crop[0], axis=1) <= crop[1]]
        parts.append(xyz)
    return PointCloud(np.vstack(parts))


class _Members:
    """The members' own points in the map's local frame (no merged voxel grid: the same members at
    the same poses give the same correspondences), one KD-tree over them, and their normals on demand."""

    def __init__(self, clouds: list[PreparedCloud], poses: list[np.ndarray], frame) -> None:
        parts, self.clouds, self.R = [], clouds, [P[:3, :3] for P in poses]
        for cloud, P in zip(clouds, poses):
            parts.append(
                frame.to_local(cloud.frame.to_global(cloud.points) @ P[:3, :3].T + P[:3, 3])
            )
        self.points = np.vstack(parts)
        self.member = np.repeat(np.arange(len(parts)), [len(x) for x in parts])
        self.row = np.concatenate([np.arange(len(x)) for x in parts])
        self.tree = cKDTree(self.points)

    def normals(self, idx: np.ndarray) -> np.ndarray:
        out = np.empty((len(idx), 3))
        for m in np.unique(self.member[idx]):
            sel = self.member[idx] == m
            out[sel] = self.clouds[m].target_normals(self.row[idx][sel]) @ self.R[m].T
        return out


def matched(
    src: PreparedCloud, T: np.ndarray, members: _Members, job: MapJob
) -> tuple[np.ndarray, np.ndarray]:
    """(scan points, member rows) matched at the map's pose T (source local -> map local): the
    scan's points within `edge_distance` of a member's surface, seeded sample of them."""
    d, idx = nearest(members.tree, src.points @ T[:3, :3].T + T[:3, 3], job.edge_distance)
    near = np.flatnonzero(np.isfinite(d))
    keep = near[sample(len(near), MATCHED_POINTS, np.random.default_rng(LENS_SEED))]
    return src.points[keep], idx[keep]


def member_edges(
    src: PreparedCloud,
    target: PreparedCloud,
    T: np.ndarray,
    p: np.ndarray,
    rows: np.ndarray,
    members: _Members,
    job: MapJob,
) -> list[dict]:
    """One edge to each member with enough of the last correspondences: the scan in the member's
    file frame, and the information of the member's own share of the point-to-plane problem."""
    T_plot = to_global_transform(T, src.frame, target.frame)
    p_file = src.frame.to_global(p)
    q_plot = target.frame.to_global(members.points[rows])
    n_plot = members.normals(rows)
    edges = []
    for m, member in enumerate(job.members):
        sel = members.member[rows] == m
        if sel.sum() < job.min_edge_points:
            continue
        info, _ = information_matrix(p_file[sel], q_plot[sel], n_plot[sel], T_plot)
        pose = np.asarray(member.pose, dtype=np.float64)
        edges.append(
            {
                "source": job.source,
                "target": member.scan,
                "transform": (inverse(pose) @ T_plot).tolist(),
                "information": info.tolist(),
                "points": int(sel.sum()),
            }
        )
    return edges


def run_map_job(job: MapJob) -> dict:
    """Worker: the scan registered onto its map; a record with its per-member edges, or failed."""
    start = time.perf_counter()
    record = {"source": job.source, "target": MAP_ID, "key": job.key, "via": "map"}
    try:
        config = job.config
        src, _ = get_prepared(job.prepared)
        members = [get_prepared(m.prepared)[0] for m in job.members]
        kind = job.members[0].prepared.kind
        init = None if job.init is None else np.asarray(job.init, dtype=np.float64)
        crop = None if init is None else reach(src, init, job.margin)
        cloud = map_cloud(job, members, crop)
        if len(cloud) < MIN_POINTS:
            raise RegistrationFailed("no placed scan reaches where the scan stands: no map")
        target = prepare_cloud(cloud, kind, default_levels(kind), config, job.seed + 1, "map")
        target = replace(target, viewpoint=None)  # many stations: no side test against one
        result = register_prepared(
            src,
            target,
            config,
            init,
            job.seed,
            start=Start.PRIOR if init is None else Start.STORED,
            memo=PairMemo(),
        )
        poses = [np.asarray(m.pose, dtype=np.float64) for m in job.members]
        team = _Members(members, poses, target.frame)
        T = to_local_transform(result.transform, src.frame, target.frame)
        p, rows = matched(src, T, team, job)
        edges = member_edges(src, target, T, p, rows, team, job)
        if not edges:
            raise RegistrationFailed("placed on the map, but overlapping no member enough")
        record.update(
            status="ok",
            transform=result.transform.tolist(),
            confidence=result.confidence,
            overlap=result.overlap,
            fitness=result.fitness,
            inlier_rmse=result.inlier_rmse,
            members=[m.scan for m in job.members],
            edges=edges,
        )
    except RegistrationFailed as exc:
        record.update(status="failed", error=str(exc), cacheable=True)
        res = getattr(exc, "result", None)
        if res is not None:
            record.update(overlap=res.overlap, confidence=res.confidence)
    except Exception as exc:  # a bug or out of memory: recorded, retried on the next run
        record.update(status="failed", error=f"{type(exc).__name__}: {exc}", cacheable=False)
    record["seconds"] = time.perf_counter() - start
    return record
