"""Synthetic scenes and pose graphs shared by several test modules (a test module never imports another)."""

from pathlib import Path

import gtsam
import laspy
import numpy as np
from pyproj import CRS

from plotmosaic.config.merge import MergeConfig
from plotmosaic.graph.posegraph import inverse
from plotmosaic.io.las import PointCloud, write_cloud
from plotmosaic.manifest import AlsTile, Manifest, Plot, Scan, dump_manifest, load_manifest
from plotmosaic.poses import Poses, ScanPose, load_poses
from plotmosaic.stages.merge import MergeSummary, merge_scans

UTM = np.array([470250.0, 3810150.0, 2100.0])


def synthetic_plot(seed: int = 0, size: float = 30.0, trees: int = 20) -> PointCloud:
    """Undulating ground, stems and crowns at UTM coordinates: enough structure for ICP/RANSAC."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-size / 2, size / 2, (15000, 2))

    def ground(x, y):
        return 0.8 * np.sin(x / 5) + 0.5 * np.cos(y / 4) + 0.05 * x

    parts = [np.c_[xy, ground(xy[:, 0], xy[:, 1])]]
    for _ in range(trees):
        cx, cy = rng.uniform(-size / 2 + 2, size / 2 - 2, 2)
        r, h = rng.uniform(0.15, 0.4), rng.uniform(8, 15)
        a, z = rng.uniform(0, 2 * np.pi, 500), rng.uniform(0, h, 500)
        base = ground(cx, cy)
        parts.append(np.c_[cx + r * np.cos(a), cy + r * np.sin(a), base + z])
        crown = rng.normal(0, 1.5, (400, 3))
        parts.append(np.c_[cx + crown[:, 0], cy + crown[:, 1], base + h + 0.8 * crown[:, 2]])
    return PointCloud(np.vstack(parts) + UTM)


def split_pair(cloud: PointCloud, seed: int = 1) -> tuple[PointCloud, PointCloud]:
    """Two independent halves of one scene (different points, same surfaces), slightly noisy."""
    rng = np.random.default_rng(seed)
    idx = rng.permutation(len(cloud))
    src, tgt = cloud.select(idx[::2]), cloud.select(idx[1::2])
    return PointCloud(src.xyz + rng.normal(0, 0.005, src.xyz.shape)), tgt


def random_pose(rng, spread=15.0, tilt_deg=2.0):
    angles = np.radians([rng.normal(0, tilt_deg), rng.normal(0, tilt_deg), rng.uniform(-180, 180)])
    T = np.eye(4)
    T[:3, :3] = gtsam.Rot3.Ypr(angles[2], angles[1], angles[0]).matrix()
    T[:3, 3] = [rng.uniform(-spread, spread), rng.uniform(-spread, spread), rng.normal(0, 0.3)]
    return T


def _icp_information(rng, n=400, sigma=0.003):
    """J^T J / sigma^2 from a random tree-like point set: a realistic, anisotropic 6x6 (right perturbation)."""
    pts = np.column_stack([rng.uniform(-15, 15, n), rng.uniform(-15, 15, n), rng.uniform(0, 12, n)])
    normals = rng.normal(size=(n, 3))
    normals[:, 2] *= 0.3  # mostly vertical stems: horizontal normals
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    J = np.column_stack([np.cross(pts, normals), normals])  # d(n . (R p + t)) / (w, v)
    return J.T @ J / sigma**2


def synthetic_pose_graph(n_scans=5, seed=0, rot_noise_deg=0.002, trans_noise=0.0005, outlier=None):
    """(truth, nodes, edges) of a plot whose every pair is an edge with small noise; `outlier`
    (source, target) names one edge turned 10 deg and 2 m wrong."""
    rng = np.random.default_rng(seed)
    truth = {f"s{k}": random_pose(rng) for k in range(n_scans)}
    ref = "s0"
    truth = {k: inverse(truth[ref]) @ T for k, T in truth.items()}  # plot frame = reference scan
    edges = []
    for a in range(n_scans):
        for b in range(a + 1, n_scans):
            i, j = f"s{b}", f"s{a}"  # source, target
            T = inverse(truth[j]) @ truth[i]
            xi = np.concatenate(
                [np.radians(rng.normal(0, rot_noise_deg, 3)), rng.normal(0, trans_noise, 3)]
            )
            T = T @ gtsam.Pose3.Expmap(xi).matrix()
            edges.append(
                {
                    "source": i,
                    "target": j,
                    "transform": T,
                    "fitness": 0.8,
                    "inlier_rmse": 0.01,
                    "overlap": 0.6,
                    "information": _icp_information(rng),
                }
            )
    if outlier is not None:
        e = next(e for e in edges if (e["source"], e["target"]) == outlier)
        e["transform"] = (
            e["transform"]
            @ gtsam.Pose3(gtsam.Rot3.Rz(np.radians(10)), np.array([2.0, 0.5, 0.0])).matrix()
        )
    nodes = {name: {"kind": "tls", "plot": "P1"} for name in truth}
    return truth, nodes, edges


# ---------------------------------------------------------------- merge sites

MERGE_SCAN_POINTS = 20_000
MERGE_CRS = "EPSG:32612"


def merge_scan_pose(rng, k: int) -> np.ndarray:
    """A scanner pose in UTM (any heading, a slight tilt), scan k a few metres on from scan k - 1."""
    yaw, tilt = rng.uniform(-np.pi, np.pi), rng.normal(0, 0.02, 2)
    cz, sz = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    Rx = np.array(
        [[1, 0, 0], [0, np.cos(tilt[0]), -np.sin(tilt[0])], [0, np.sin(tilt[0]), np.cos(tilt[0])]]
    )
    Ry = np.array(
        [[np.cos(tilt[1]), 0, np.sin(tilt[1])], [0, 1, 0], [-np.sin(tilt[1]), 0, np.cos(tilt[1])]]
    )
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry @ Rx
    T[:3, 3] = [
        470_000.0 + 15 * k + rng.uniform(0, 1),
        3_810_000.0 + 10 * k + rng.uniform(0, 1),
        2_100.0 + rng.uniform(0, 1),
    ]
    return T


def merge_scan_cloud(rng, n: int, rgb: bool) -> PointCloud:
    """A TLS-like scan in its scanner frame with the LAS attributes merge carries (+ RGB and an extra dim)."""
    r = np.sqrt(rng.uniform(0, 25.0**2, n))
    a = rng.uniform(0, 2 * np.pi, n)
    xyz = np.column_stack([r * np.cos(a), r * np.sin(a), rng.uniform(-1.5, 20.0, n)])
    nret = rng.integers(1, 4, n).astype(np.uint8)
    attrs = {
        "intensity": rng.integers(0, 65535, n).astype(np.uint16),
        "number_of_returns": nret,
        "return_number": (rng.integers(0, 3, n) % nret + 1).astype(np.uint8),
        "classification": rng.choice(np.array([1, 2, 5], np.uint8), n),
        "gps_time": np.sort(rng.uniform(1e5, 1e5 + 600, n)),
    }
    if rgb:
        attrs.update(
            {c: rng.integers(0, 65535, n).astype(np.uint16) for c in ("red", "green", "blue")}
        )
        attrs["label"] = rng.integers(0, 4, n).astype(
            np.uint8
        )  # an extra dimension, like the simulator's
    return PointCloud(xyz, attrs)


def merge_site(root: Path) -> Path:
    """Three TLS scans in scanner frames (scan c has no RGB and no label), one ALS tile in UTM, true poses in the CRS."""
    rng = np.random.default_rng(7)
    ids = ["a", "b", "c"]
    poses = {}
    for k, sid in enumerate(ids):
        write_cloud(root / f"{sid}.laz", merge_scan_cloud(rng, MERGE_SCAN_POINTS, rgb=sid != "c"))
        poses[sid] = ScanPose(merge_scan_pose(rng, k), plot="P1")
    # the ALS tile as an older LAS 1.2 point format 3 file
    als = laspy.LasData(laspy.LasHeader(point_format=3, version="1.2"))
    als.header.scales, als.header.offsets = [0.01] * 3, [470_000, 3_810_000, 0]
    xyz = rng.uniform([469_980, 3_809_980, 2_095], [470_060, 3_810_060, 2_130], (5_000, 3))
    als.x, als.y, als.z = xyz.T
    als.classification = np.full(5_000, 2, np.uint8)
    als.intensity = rng.integers(0, 4000, 5_000).astype(np.uint16)
    als.write(root / "als.laz")
    manifest = Manifest(
        plots=[
            Plot(
                id="P1", crs=MERGE_CRS, scans=[Scan(id=sid, path=Path(f"{sid}.laz")) for sid in ids]
            )
        ],
        als=[AlsTile(path=Path("als.laz"))],
    )
    (root / "manifest.toml").write_text(dump_manifest(manifest))
    Poses(poses, frame="crs", crs=CRS.from_user_input(MERGE_CRS).to_wkt()).save(root / "poses.json")
    return root


def merge_big_site(root: Path) -> Path:
    """Two scans of 400k points (no ALS): a merge that runs long enough to be interrupted."""
    rng = np.random.default_rng(5)
    poses = {}
    for k, sid in enumerate("ab"):
        write_cloud(root / f"{sid}.laz", merge_scan_cloud(rng, 400_000, rgb=True))
        poses[sid] = ScanPose(merge_scan_pose(rng, k), plot="P1")
    manifest = Manifest(
        plots=[
            Plot(
                id="P1",
                crs=MERGE_CRS,
                scans=[Scan(id=sid, path=Path(f"{sid}.laz")) for sid in "ab"],
            )
        ]
    )
    (root / "manifest.toml").write_text(dump_manifest(manifest))
    Poses(poses, frame="crs", crs=CRS.from_user_input(MERGE_CRS).to_wkt()).save(root / "poses.json")
    return root


def run_merge(site: Path, out: Path, **options) -> MergeSummary:
    """merge_scans over a site's manifest and poses, in this process (force: a test reruns it)."""
    manifest, poses = load_manifest(site / "manifest.toml"), load_poses(site / "poses.json")
    return merge_scans(manifest, poses, out, MergeConfig(force=True, **options), progress=False)


def plane_basis(normal) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(unit normal, u, v): an orthonormal frame whose u and v span the plane of `normal`."""
    n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    u = np.cross(n, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    return n, u, np.cross(n, u)
