"""One start refined stage by stage: a correspondence search carried across the stages gives the
pose a fresh search in every stage gives, to the bit."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from plotmosaic.align.icp import IcpOptions, MovingNearest, point_to_plane_icp
from plotmosaic.config.align import IcpStage

SCHEDULE = [(0.6, 8), (0.25, 8), (0.1, 6), (0.04, 8)]


def _scene(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A ground plane, two walls and a few stems: every direction held, (points, normals)."""
    g = rng.uniform(0, 10, (6000, 2))
    ground = np.column_stack([g, 0.05 * g[:, 0]])
    wall_x = np.column_stack([np.zeros(3000), rng.uniform(0, 10, (3000, 2))])
    wall_y = np.column_stack([rng.uniform(0, 10, 3000), np.zeros(3000), rng.uniform(0, 10, 3000)])
    t = rng.uniform(0, 2 * np.pi, 3000)
    stems = np.column_stack([4 + 0.2 * np.cos(t), 6 + 0.2 * np.sin(t), rng.uniform(0, 8, 3000)])
    normals = np.vstack(
        [
            np.tile([-0.05, 0.0, 1.0] / np.hypot(0.05, 1.0), (6000, 1)),
            np.tile([1.0, 0.0, 0.0], (3000, 1)),
            np.tile([0.0, 1.0, 0.0], (3000, 1)),
            np.column_stack([np.cos(t), np.sin(t), np.zeros(3000)]),
        ]
    )
    return np.vstack([ground, wall_x, wall_y, stems]), normals


def _refine(source, target, normals, tree, T, carried: bool) -> np.ndarray:
    kept = MovingNearest(tree) if carried else None
    for d, n in SCHEDULE:
        options = IcpOptions(
            stages=(IcpStage(max_distance=d, iterations=n),), kernel_floor=d, tol=1e-4
        )
        search = kept or MovingNearest(tree)  # carried across stages, or fresh for each
        T = point_to_plane_icp(source, target, normals, T, options, search).T
    return T


def test_a_search_carried_across_stages_gives_the_same_pose():
    rng = np.random.default_rng(4)
    target, normals = _scene(rng)
    tree = cKDTree(target)
    source = target[rng.choice(len(target), 2000, replace=False)] + rng.normal(0, 0.01, (2000, 3))
    for k in range(3):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec([0.0, 0.02 * k, 0.05 - 0.03 * k]).as_matrix()
        T[:3, 3] = [0.3 - 0.2 * k, 0.1 * k, -0.1]
        fresh = _refine(source, target, normals, tree, T, carried=False)
        carried = _refine(source, target, normals, tree, T, carried=True)
        assert carried.tobytes() == fresh.tobytes()
        assert not np.allclose(fresh, T)  # the refinement did move


def test_an_icp_told_an_axis_turns_only_about_it():
    """A start tilted 3 deg off the truth: turning about the vertical alone keeps the tilt (the
    coarse stage's loose matches must not decide it), turning freely removes it."""
    rng = np.random.default_rng(3)
    target, normals = _scene(rng)
    tree = cKDTree(target)
    source = target[rng.choice(len(target), 4000, replace=False)]
    start = np.eye(4)
    start[:3, :3] = Rotation.from_euler("xz", [3.0, 4.0], degrees=True).as_matrix()
    start[:3, 3] = [0.2, -0.1, 0.05]
    up = np.array([0.0, 0.0, 1.0])
    stages = (IcpStage(max_distance=1.0, iterations=30), IcpStage(max_distance=0.3, iterations=30))
    about = point_to_plane_icp(
        source, target, normals, start, IcpOptions(stages=stages, axis=up), MovingNearest(tree)
    ).T
    free = point_to_plane_icp(
        source, target, normals, start, IcpOptions(stages=stages), MovingNearest(tree)
    ).T
    turned = about[:3, :3] @ start[:3, :3].T
    assert np.allclose(turned @ up, up, atol=1e-9)  # a turn about the axis alone
    tilt = np.degrees(np.arccos(about[2, 2]))
    assert abs(tilt - 3.0) < 1e-6
    assert np.degrees(np.arccos(np.clip(free[2, 2], -1, 1))) < 0.1  # freely: tilted into place
