"""Which pairs a benchmark runs, and their true transforms.

Ground truth comes as `identity` (co-registered clips such as UAS -> ALS), a JSON with a
`transform` key (source file -> target file), or a poses file (`plotmosaic.poses`, e.g. the
simulator's ground_truth.json: scan file -> common frame), from which a pair's truth is
inv(pose[target]) @ pose[source]. ALS tiles have no pose: they are the common (CRS) frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from plotmosaic.bench.run import BenchPair
from plotmosaic.errors import InputError
from plotmosaic.io.las import PointCloud, read_cloud
from plotmosaic.manifest import Manifest
from plotmosaic.poses import Poses, load_poses, read_json, rigid_matrix

PAIR_SETS = ("tls-tls", "tls-als", "prepost", "all")
ALS_MARGIN = 20.0  # metres of ALS kept around a ground scan (the paper crops ALS to 50 x 50 m)


def _pose(poses: Poses, scan_id: str, path: Path) -> np.ndarray:
    if scan_id not in poses.scans:
        raise InputError(
            f"{path}: ground truth has no pose for {scan_id!r} (have: {', '.join(sorted(poses.scans)) or 'none'}; use --source-id/--target-id)"
        )
    return poses.transform(scan_id)


def load_truth(
    gt: str,
    source_path: Path,
    target_path: Path,
    source_id: str | None = None,
    target_id: str | None = None,
) -> np.ndarray:
    """4x4 source file -> target file from `--gt` (identity | transform JSON | poses JSON)."""
    if gt.strip().lower() == "identity":
        return np.eye(4)
    path = Path(gt)
    data = read_json(path, "--gt file (give a JSON file or 'identity')")
    if isinstance(data, dict) and "scans" in data:
        poses = load_poses(path)
        sid, tid = source_id or source_path.stem, target_id or target_path.stem
        T_src = _pose(poses, sid, path)
        if tid not in poses.scans and poses.frame == "crs":
            return T_src  # a target with no pose in a CRS-frame file is in that frame (an ALS tile)
        return np.linalg.inv(_pose(poses, tid, path)) @ T_src
    if isinstance(data, dict) and "transform" in data:
        return rigid_matrix(data["transform"], f"--gt {path}")
    raise InputError(f"--gt {path}: neither a poses file ('scans') nor a JSON with a 'transform'")


def _crop_around(als: PointCloud, xyz: np.ndarray, margin: float) -> PointCloud:
    lo, hi = xyz[:, :2].min(axis=0) - margin, xyz[:, :2].max(axis=0) + margin
    keep = np.all((als.xyz[:, :2] >= lo) & (als.xyz[:, :2] <= hi), axis=1)
    return als.select(keep)


def _pair_specs(
    manifest: Manifest, which: str, max_pairs: int | None
) -> list[tuple[str, str | None]]:
    """(source id, target id or None = the ALS) of every pair of the set `which`."""
    if which not in PAIR_SETS:
        raise InputError(f"--pairs: {which!r} not one of {', '.join(PAIR_SETS)}")
    specs: list[tuple[str, str | None]] = []
    if which in ("tls-tls", "all"):
        for plot in manifest.plots:
            ref = plot.reference
            specs += [
                (s.id, ref.id)
                for s in plot.scans
                if s.id != ref.id and s.kind.value in ("tls", "mls")
            ]
    if which in ("tls-als", "all"):
        if not manifest.als:
            raise InputError(
                f"{manifest.source}: --pairs {which} needs [[als]] tiles in the manifest"
            )
        specs += [(plot.reference.id, None) for plot in manifest.plots]
    if which == "prepost":
        if len(manifest.plots) < 2:
            raise InputError(
                f"{manifest.source}: --pairs prepost needs two plots (before and after)"
            )
        pre, post = manifest.plots[0].scans, manifest.plots[1].scans
        specs += [(b.id, a.id) for a, b in zip(pre, post)]
    if max_pairs:
        specs = specs[:max_pairs]
    if not specs:
        raise InputError(f"{manifest.source}: no {which} pairs in this manifest")
    return specs


def manifest_pairs(
    manifest: Manifest, poses: Poses, which: str, max_pairs: int | None = None
) -> list[BenchPair]:
    """Pairs of a simulated (or surveyed) plot with known poses.

    tls-tls: every ground scan onto its plot's reference scan. tls-als: every plot's reference
    scan onto the ALS (cropped around the scan's true footprint). prepost: scan i of the second
    plot onto scan i of the first (the simulator's PRE/POST plots). all: tls-tls + tls-als.
    """
    specs = _pair_specs(manifest, which, max_pairs)
    clouds: dict[str, PointCloud] = {}

    def cloud(scan_id: str) -> PointCloud:
        if scan_id not in clouds:
            clouds[scan_id] = read_cloud(
                manifest.resolve(manifest.scan(scan_id).path), attributes=False
            )
        return clouds[scan_id]

    als = None
    pairs = []
    for sid, tid in specs:
        src_scan = manifest.scan(sid)
        T_src = _pose(poses, sid, Path(str(manifest.source)))
        if tid is None:
            if als is None:
                tiles = [
                    read_cloud(manifest.resolve(t.path), attributes=False) for t in manifest.als
                ]
                als = PointCloud(np.vstack([t.xyz for t in tiles]), {}, tiles[0].crs)
            src = cloud(sid)
            world = src.xyz @ T_src[:3, :3].T + T_src[:3, 3]
            crop = _crop_around(als, world, ALS_MARGIN)
            pairs.append(BenchPair(f"{sid}->ALS", src, crop, T_src, src_scan.kind.value, "als"))
        else:
            T = np.linalg.inv(_pose(poses, tid, Path(str(manifest.source)))) @ T_src
            src, tgt = cloud(sid), cloud(tid)
            kinds = src_scan.kind.value, manifest.scan(tid).kind.value
            pairs.append(BenchPair(f"{sid}->{tid}", src, tgt, T, *kinds))
    return pairs
