"""tie-to-als's plot cloud: per-voxel centroids over every scan, summed one scan at a time."""

import numpy as np
import pytest

from plotmosaic.config.register import TieConfig
from plotmosaic.errors import InputError
from plotmosaic.io.frame import Frame
from plotmosaic.io.las import read_cloud
from plotmosaic.manifest import load_manifest
from plotmosaic.poses import Poses, load_poses
from plotmosaic.stages.tie_to_als import plot_cloud


def centroids_at_once(parts: list[np.ndarray], size: float) -> np.ndarray:
    """The plot's voxel centroids from all its points together, on the grid the first scan sets."""
    xyz = np.concatenate(parts)
    origin = Frame.around(parts[0]).offset
    ijk = np.floor((xyz - origin) / size).astype(np.int64)
    _, inverse, counts = np.unique(ijk, axis=0, return_inverse=True, return_counts=True)
    sums = np.stack([np.bincount(inverse.ravel(), weights=xyz[:, c] - origin[c]) for c in range(3)])
    return sums.T / counts[:, None] + origin


def test_scan_by_scan_sums_equal_the_centroids_of_all_points(small_sim):
    manifest = load_manifest(small_sim.manifest_path)
    truth = load_poses(small_sim.ground_truth_path)
    plot = manifest.plots[0].model_copy(update={"scans": manifest.plots[0].scans[:3]})
    config = TieConfig()
    cloud = plot_cloud(manifest, plot, truth, config)
    parts = [
        truth.transform(s.id)[:3, :3] @ read_cloud(manifest.resolve(s.path)).xyz.T
        + truth.transform(s.id)[:3, 3:]
        for s in plot.scans
    ]
    expected = centroids_at_once([p.T for p in parts], config.plot_voxel)
    assert cloud.xyz.shape == expected.shape
    # the same voxels in the same (x, y, z) order, the same centroids up to summation order
    assert np.abs(cloud.xyz - expected).max() < 1e-9
    assert len(cloud) < sum(p.shape[1] for p in parts)


def test_a_plot_without_placed_scans_is_refused(small_sim):
    manifest = load_manifest(small_sim.manifest_path)
    with pytest.raises(InputError, match="none of its scans has a pose"):
        plot_cloud(manifest, manifest.plots[0], Poses({}), TieConfig())
