"""Global coarse stage: levelling, masked correlation, and start-from-anywhere on real clips."""

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import pytest
from scipy import ndimage
from scipy.spatial.transform import Rotation

from plotmosaic.align.coarse import CoarseConfig, coarse_align, raster
from plotmosaic.align.levelling import estimate_up, rotation_between
from plotmosaic.align.rasters import MaskedNCC, Raster
from plotmosaic.io import Frame, read_cloud
from plotmosaic.io.frame import to_local_transform


def angle_deg(a, b):
    return np.degrees(
        np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))
    )


def test_levelling_finds_vertical_on_a_slope_from_stems():
    rng = np.random.default_rng(0)
    true_up = Rotation.from_euler("xy", [30, -20], degrees=True).apply([0, 0, 1])
    slope = Rotation.from_euler("xy", [30 + 15, -20], degrees=True).apply(
        [0, 0, 1]
    )  # 15 deg terrain slope
    ground = slope + rng.normal(0, 0.05, (6000, 3))
    az = rng.uniform(0, 2 * np.pi, 2500)  # stem normals: horizontal in the true frame
    R = rotation_between(np.array([0, 0, 1.0]), true_up)
    stems = (np.column_stack([np.cos(az), np.sin(az), rng.normal(0, 0.03, az.size)])) @ R.T
    foliage = rng.normal(size=(4000, 3))
    normals = np.vstack([ground, -stems, foliage])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[rng.random(len(normals)) < 0.5] *= -1  # axial: orientation carries no information
    up, info = estimate_up(normals)
    assert angle_deg(up, true_up) < 1.0
    assert info["stem_share"] > 0.1


def test_masked_ncc_recovers_a_shift_with_partial_overlap():
    rng = np.random.default_rng(1)
    world = ndimage.gaussian_filter(rng.random((200, 200)), 2)
    tgt = Raster(
        np.array([0.0, 0.0]), 1.0, {"c": world[20:120, 30:130]}, {"c": np.ones((100, 100))}
    )
    src_img = world[60:140, 70:150]  # overlaps the target by 60 x 60 cells only
    src = Raster(np.array([500.0, 500.0]), 1.0, {"c": src_img}, {"c": np.ones((80, 80))})
    ncc = MaskedNCC(tgt, src_img.shape, min_overlap=400)
    score, overlap = ncc(src, "c")
    k = np.unravel_index(np.argmax(score), score.shape)
    t = ncc.shift_to_translation(k, src)
    # source cell (0,0) is world (60,70); target cell (0,0) is world (20,30): shift = 40, 40 cells
    np.testing.assert_allclose(t, [40 - 500.0, 40 - 500.0])
    assert score[k] > 0.99 and overlap[k] == 60 * 60


@dataclass
class Prepared:
    points: np.ndarray
    normals: np.ndarray
    kind: str
    frame: Frame


def prepare(xyz, kind):
    frame = Frame.around(xyz)
    pcd = o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(frame.to_local(xyz))
    ).voxel_down_sample(0.1)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.25, max_nn=30))
    return Prepared(np.asarray(pcd.points), np.asarray(pcd.normals), kind, frame)


def pose_error(T, G):
    D = np.linalg.inv(G) @ T
    return np.linalg.norm(D[:3, 3]), np.degrees(
        np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))
    )


@pytest.mark.slow
def test_coarse_finds_drone_clip_inside_als_from_far_away(spanner_dir):
    """UAS -> ALS, perturbed far beyond ICP's reach (paper protocol range): found to within ICP range."""
    uas = read_cloud(spanner_dir / "UAS_Clip.laz", attributes=False).xyz
    als = read_cloud(spanner_dir / "ALS_Clip.laz", attributes=False).xyz
    R = Rotation.from_euler("xyz", [25, -30, 140], degrees=True).as_matrix()
    c = uas.mean(axis=0)
    P = np.eye(4)
    P[:3, :3], P[:3, 3] = R, c - R @ c + [12.0, -9.0, 6.0]
    moved = uas @ P[:3, :3].T + P[:3, 3]
    src, tgt = prepare(moved, "uls"), prepare(als, "als")
    result = coarse_align(src, tgt, CoarseConfig(), seed=0)
    truth = to_local_transform(np.linalg.inv(P), src.frame, tgt.frame)
    dt, dr = pose_error(result.transform, truth)
    assert dt < 0.3 and dr < 1.0, (dt, dr)
    assert 0.0 < result.confidence <= 1.0
    assert result.hypotheses and {"transform", "score", "yaw_deg"} <= set(
        result.hypotheses[0].to_dict()
    )
    again = coarse_align(src, tgt, CoarseConfig(), seed=0)
    # deterministic up to the summation order of Open3D's parallel reductions
    np.testing.assert_allclose(again.transform, result.transform, atol=1e-9)


def test_headings_on_coarser_cells_first_only_where_a_cloud_is_airborne():
    config = CoarseConfig()
    assert raster.pyramid("tls", "als", config) == config.heading_pyramid == 2
    assert raster.pyramid("uls", "als", config) == raster.pyramid("tls", "uls", config) == 2
    assert raster.pyramid("tls", "tls", config) == raster.pyramid("mls", "tls", config) == 1


def test_heading_pyramid_scores_every_heading_on_coarser_cells_and_finds_the_same_pose(
    spanner_dir, monkeypatch
):
    """The ground-based MLS clip placed on the ALS clip from far away, as register-plot places a scan
    on a tile: every heading is scored on cells twice the raster cell, and only the best
    `pyramid_headings` (and half steps beside the best of them) on the raster cell; the pose is the
    one every heading on the raster cell finds (the clips' own co-registration is ~0.4 m off)."""
    mls = read_cloud(spanner_dir / "MLS_Clip.laz", attributes=False).xyz
    als = read_cloud(spanner_dir / "ALS_Clip.laz", attributes=False).xyz
    R = Rotation.from_euler("xyz", [4, -3, 115], degrees=True).as_matrix()
    c = mls.mean(axis=0)
    P = np.eye(4)
    P[:3, :3], P[:3, 3] = R, c - R @ c + [-10.0, 7.0, 3.0]
    src, tgt = prepare(mls @ P[:3, :3].T + P[:3, 3], "mls"), prepare(als, "als")
    truth = to_local_transform(np.linalg.inv(P), src.frame, tgt.frame)
    config = CoarseConfig(fpfh=False, settled_generators=1)
    every = coarse_align(src, tgt, config.model_copy(update={"heading_pyramid": 1}), seed=0)
    cells: list[float] = []
    real = raster._Correlation.peaks
    monkeypatch.setattr(
        raster._Correlation, "peaks", lambda self, y: cells.append(self.cell) or real(self, y)
    )
    result = coarse_align(src, tgt, config, seed=0)
    dt, dr = pose_error(result.transform, every.transform)
    assert dt < 0.01 and dr < 0.05, (dt, dr)
    dt, dr = pose_error(result.transform, truth)
    assert dt < 0.5 and dr < 2.0, (dt, dr)
    base = min(cells)
    pairs = cells.count(2 * base) // 90  # vertical pairs searched: 90 headings at 4 deg each
    assert pairs >= 1 and cells.count(2 * base) == 90 * pairs
    assert set(cells) == {base, 2 * base}
    fine = cells.count(base)
    assert fine <= pairs * (config.pyramid_headings + 2 * config.refine_headings) < 90 * pairs
    # two ground-based views: every heading on the raster cell
    cells.clear()
    coarse_align(prepare(mls @ P[:3, :3].T + P[:3, 3], "mls"), prepare(mls, "mls"), config, seed=0)
    assert len(set(cells)) == 1 and len(cells) >= 90
