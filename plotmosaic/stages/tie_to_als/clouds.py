"""tie-to-als clouds: each plot's scans merged into one cloud, and the ALS tile cropped around it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from plotmosaic.config.register import TieConfig
from plotmosaic.errors import InputError
from plotmosaic.graph.prepared import load_points
from plotmosaic.io import cells
from plotmosaic.io.bounded import read_scan_points
from plotmosaic.io.frame import Frame, apply_transform
from plotmosaic.io.las import PointCloud, las_offsets, read_cloud
from plotmosaic.manifest import Manifest, Plot
from plotmosaic.poses import Poses

LAS_SCALE = 0.001  # write_cloud's default: the plot and ALS clouds are written at 1 mm


def _scan_points(
    manifest: Manifest, scan, prepared: dict[str, Path], config: TieConfig
) -> np.ndarray:
    """The scan's points: register-plot's prepared (delta0-thinned) cloud when it is still there,
    else the file, within the reading budget."""
    entry = prepared.get(scan.id)
    if entry is not None and entry.is_file():
        try:
            return load_points(entry)
        except Exception:  # damaged entry: read the scan itself
            pass
    path = manifest.resolve(scan.path)
    return read_scan_points(path, config.read, config.align).xyz


class _VoxelSums:
    """Running per-voxel sums and counts over a plot's scans, one scan in memory at a time: the
    plot's centroids without concatenating its scans (memory follows the occupied voxels)."""

    def __init__(self, size: float):
        self.size = size
        self.origin: np.ndarray | None = None
        self.keys = np.zeros(0, dtype=np.int64)
        self.sums = np.zeros((0, 3))
        self.counts = np.zeros(0, dtype=np.int64)

    def add(self, xyz: np.ndarray) -> None:
        if len(xyz) == 0:
            return
        if self.origin is None:
            self.origin = Frame.around(xyz).offset
        local = xyz - self.origin
        ijk = np.floor(local / self.size).astype(np.int64)
        if not cells.fits(ijk.min(), ijk.max()):
            raise InputError(
                f"the plot spans more than {2 * cells.HALF} voxels of {self.size} m a side: "
                "raise [tie] plot_voxel"
            )
        self._merge(cells.pack(ijk), local)

    def _merge(self, keys: np.ndarray, local: np.ndarray) -> None:
        # the scan reduced to its voxels first, then merged into the sorted running ones
        keys, inverse = np.unique(keys, return_inverse=True)
        n = len(keys)
        sums = np.stack(
            [np.bincount(inverse, weights=local[:, c], minlength=n) for c in range(3)], axis=1
        )
        counts = np.bincount(inverse, minlength=n)
        at = np.searchsorted(self.keys, keys)
        known = at < len(self.keys)
        known[known] = self.keys[at[known]] == keys[known]
        self.sums[at[known]] += sums[known]
        self.counts[at[known]] += counts[known]
        new = ~known
        self.keys = np.insert(self.keys, at[new], keys[new])
        self.sums = np.insert(self.sums, at[new], sums[new], axis=0)
        self.counts = np.insert(self.counts, at[new], counts[new])

    def centroids(self) -> np.ndarray:
        return self.sums / self.counts[:, None] + self.origin


def plot_cloud(
    manifest: Manifest,
    plot: Plot,
    poses: Poses,
    config: TieConfig,
    prepared: dict[str, Path] | None = None,
) -> PointCloud:
    """All placed scans of the plot in the plot frame, thinned to `config.plot_voxel`: each
    voxel's centroid over every scan's points in it (a prepared cloud's delta0 centroids, or the
    file's points), summed scan by scan so one scan at a time is held."""
    voxels = _VoxelSums(config.plot_voxel)
    for scan in plot.scans:
        if scan.id in poses.scans:
            xyz = _scan_points(manifest, scan, prepared or {}, config)
            voxels.add(apply_transform(poses.transform(scan.id), xyz))
            del xyz
    if voxels.origin is None:
        raise InputError(f"plot {plot.id!r}: none of its scans has a pose in the poses file")
    return PointCloud(voxels.centroids())


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
