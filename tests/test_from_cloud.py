"""Virtual scans cut from a real cloud: occlusion, exact truth, determinism, CLI round trip, the TreeLS plot."""

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from typer.testing import CliRunner

from plotmosaic.cli import app
from plotmosaic.io.frame import apply_transform, inverse
from plotmosaic.io.las import PointCloud, read_cloud, write_cloud
from plotmosaic.manifest import load_manifest
from plotmosaic.poses import load_poses
from plotmosaic.simulate.from_cloud import cut_views, grid_positions, parse_positions

TREELS = Path(__file__).resolve().parents[2] / "shared" / "data" / "treels" / "pine_plot.laz"
UTM = np.array([470_000.0, 3_810_000.0, 2100.0])


def _scene() -> dict[str, np.ndarray]:
    """Flat ground 20 x 16 m, a trunk (radius 0.4 m) at x = 5 and a wall at x = 10, points every ~5-10 cm."""
    g = np.arange(-4.0, 16.0, 0.1)
    gx, gy = np.meshgrid(g, np.arange(-8.0, 8.0, 0.1))
    ground = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    a, z = np.meshgrid(np.linspace(0, 2 * np.pi, 60, endpoint=False), np.arange(0.05, 4.0, 0.05))
    trunk = np.column_stack([5 + 0.4 * np.cos(a.ravel()), 0.4 * np.sin(a.ravel()), z.ravel()])
    wy, wz = np.meshgrid(np.arange(-4.0, 4.0, 0.05), np.arange(0.05, 3.0, 0.05))
    wall = np.column_stack([np.full(wy.size, 10.0), wy.ravel(), wz.ravel()])
    return {"ground": ground, "trunk": trunk, "wall": wall}


@pytest.fixture(scope="module")
def scene():
    parts = _scene()
    xyz = np.vstack(list(parts.values()))
    labels = np.concatenate([np.full(len(v), i) for i, v in enumerate(parts.values())])
    return xyz, labels


def _seen(view, n):
    mask = np.zeros(n, dtype=bool)
    mask[view.index] = True
    return mask


def test_trunk_hides_its_back_and_its_shadow(scene):
    xyz, labels = scene
    (view,) = cut_views(xyz, [(0.0, 0.0)], seed=0, full_density_range=100.0)
    seen = _seen(view, len(xyz))
    assert np.allclose(view.position, [0.0, 0.0, 1.5])
    trunk, wall = labels == 1, labels == 2
    front = trunk & (xyz[:, 0] < 4.8) & (xyz[:, 2] < 3.0)
    back = trunk & (xyz[:, 0] > 5.15)
    assert seen[front].mean() > 0.95 and seen[back].mean() < 0.02
    # the wall behind the trunk: its shadow (|y| < 0.8 * 2 * 0.4 at twice the distance) is hidden, the rest seen
    shadow = wall & (np.abs(xyz[:, 1]) < 0.6) & (xyz[:, 2] < 2.5)
    lit = wall & (np.abs(xyz[:, 1]) > 1.5)
    assert seen[shadow].mean() < 0.02 and seen[lit].mean() > 0.95
    # ground is seen in front of the trunk, hidden in its shadow and behind the wall
    ground = labels == 0
    near = ground & (np.hypot(xyz[:, 0], xyz[:, 1]) > 1.0) & (xyz[:, 0] < 4.0)
    hidden = ground & (xyz[:, 0] > 6.0) & (xyz[:, 0] < 9.5) & (np.abs(xyz[:, 1]) < 0.3)
    beyond = ground & (xyz[:, 0] > 11.0) & (np.abs(xyz[:, 1]) < 3.0)
    assert seen[near].mean() > 0.9 and seen[hidden].mean() < 0.05 and seen[beyond].mean() < 0.05


def test_density_falls_with_range_and_max_range_cuts(scene):
    xyz, labels = scene
    (view,) = cut_views(xyz, [(0.0, 0.0)], seed=1, full_density_range=2.0, max_range=9.0)
    r = np.linalg.norm(view.points, axis=1)
    assert r.max() <= 9.0 + 1e-9 and r.min() >= 0.5
    ground = labels[view.index] == 0
    d = np.hypot(*(xyz[view.index][:, :2]).T)
    # ground points per m2 at 2-3 m against 6-8 m: (r0/r)^2 makes the far ring ~7x sparser

    def ring(lo, hi):
        return ((d >= lo) & (d < hi) & ground).sum() / (np.pi * (hi**2 - lo**2))

    assert ring(2.0, 3.0) > 4 * ring(6.0, 8.0)


def test_truth_maps_each_view_back_exactly_even_in_utm(scene):
    xyz, _ = scene
    world = xyz + UTM
    views = cut_views(world, [tuple(UTM[:2] + [0.0, 0.0]), tuple(UTM[:2] + [3.0, -4.0])], seed=3)
    for view in views:
        T = view.truth
        assert (
            np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
            and np.linalg.det(T[:3, :3]) > 0
        )
        assert np.abs(apply_transform(T, view.points) - world[view.index]).max() < 1e-6
        assert (
            np.linalg.norm(view.points, axis=1).min() >= 0.5
        )  # scanner at the origin of its own frame
        assert np.abs(view.points).max() < 100  # a local frame, not UTM
    rel = inverse(views[1].truth) @ views[0].truth  # the two frames are distinct, random headings
    assert np.degrees(np.arccos(np.clip((np.trace(rel[:3, :3]) - 1) / 2, -1, 1))) > 1.0


def test_same_seed_same_views_other_seed_other_frame(scene):
    xyz, _ = scene
    a = cut_views(xyz, [(0.0, 0.0)], seed=5)[0]
    b = cut_views(xyz, [(0.0, 0.0)], seed=5)[0]
    c = cut_views(xyz, [(0.0, 0.0)], seed=6)[0]
    assert (
        np.array_equal(a.index, b.index)
        and np.array_equal(a.truth, b.truth)
        and np.array_equal(a.points, b.points)
    )
    assert not np.array_equal(a.truth, c.truth)


def test_range_noise_moves_points_along_their_rays(scene):
    xyz, _ = scene
    (view,) = cut_views(xyz, [(0.0, 0.0)], seed=2, range_noise=0.003)
    true_local = apply_transform(inverse(view.truth), xyz[view.index])
    dr = np.linalg.norm(view.points, axis=1) - np.linalg.norm(true_local, axis=1)
    assert 0.002 < dr.std() < 0.004
    cos = (
        np.einsum("ij,ij->i", view.points, true_local)
        / np.linalg.norm(view.points, axis=1)
        / np.linalg.norm(true_local, axis=1)
    )
    assert cos.min() > 1 - 1e-9


def test_positions_grid_and_parsing():
    xyz = np.array([[0.0, 0.0, 0.0], [10.0, 20.0, 5.0]])
    assert grid_positions(xyz, 2, 6.0) == [(2.0, 10.0), (8.0, 10.0)]
    assert len(grid_positions(xyz, 5, 2.0)) == 5
    assert parse_positions("1,2; 3,4,5") == [(1.0, 2.0), (3.0, 4.0, 5.0)]
    from plotmosaic.errors import InputError

    with pytest.raises(InputError, match="entry 2"):
        parse_positions("1,2;3,a")


def test_scanner_standing_in_a_trunk_is_moved_out(scene):
    xyz, _ = scene
    (view,) = cut_views(xyz, [(5.0, 0.0)], seed=0)
    assert np.hypot(view.position[0] - 5.0, view.position[1]) > 0.4 + 0.3 - 1e-9


def test_cli_round_trip_writes_a_manifest_info_accepts(scene, tmp_path):
    xyz, labels = scene
    src = write_cloud(
        tmp_path / "real.laz", PointCloud(xyz + UTM, {"classification": labels.astype(np.uint8)})
    )
    out = tmp_path / "views"
    runner = CliRunner()
    res = runner.invoke(
        app,
        [
            "simulate",
            str(out),
            "--from-cloud",
            str(src),
            "--positions",
            f"{UTM[0]},{UTM[1]};{UTM[0] + 2},{UTM[1] + 3}",
            "--seed",
            "4",
        ],
    )
    assert res.exit_code == 0, res.output
    m = load_manifest(out / "manifest.toml")
    assert [s.id for s in m.scans] == ["P1-S0", "P1-S1"] and m.plots[0].reference.id == "P1-S0"
    assert runner.invoke(app, ["info", str(out / "manifest.toml")]).exit_code == 0
    truth = load_poses(out / "ground_truth.json")
    assert truth.frame == "plot" and truth.extra["from_cloud"]["seed"] == 4
    tree = cKDTree(xyz + UTM - UTM)
    for scan in m.scans:
        cloud = read_cloud(m.resolve(scan.path))
        assert np.abs(cloud.xyz).max() < 100 and "classification" in cloud.attrs
        back = apply_transform(truth.transform(scan.id), cloud.xyz) - UTM
        dist, _ = tree.query(back)
        assert dist.max() < 0.002  # the LAS millimetre grid
    # bad input: one line, exit 2
    for args, culprit in (
        (["--positions", "1,x"], "--positions"),
        (["--preset", "paper", "--views", "2", "--spacing", "5"], "--preset"),
        (["--positions", "0,0", "--views", "2"], "not both"),
        ([], "--positions"),
    ):
        res = runner.invoke(
            app, ["simulate", str(tmp_path / "bad"), "--from-cloud", str(src), *args]
        )
        assert (
            res.exit_code == 2
            and culprit in res.output
            and len(res.output.strip().splitlines()) == 1
        ), res.output
    res = runner.invoke(
        app, ["simulate", str(tmp_path / "far"), "--from-cloud", str(src), "--positions", "0,0"]
    )
    assert res.exit_code == 2 and "from the nearest point" in res.output


@pytest.mark.skipif(not TREELS.is_file(), reason="shared/data/treels not present")
def test_treels_plot_two_views_six_metres_apart():
    cloud = read_cloud(TREELS, attributes=False)
    views = cut_views(cloud.xyz, grid_positions(cloud.xyz, 2, 6.0), seed=0)
    assert np.linalg.norm(views[0].position[:2] - views[1].position[:2]) >= 6.0
    for view in views:
        assert 15_000 < len(view.points) < 0.6 * len(cloud)
        assert np.abs(apply_transform(view.truth, view.points) - cloud.xyz[view.index]).max() < 1e-9
        assert 1.0 < view.position[2] - np.percentile(cloud.xyz[view.index][:, 2], 1) < 3.0
    shared = np.intersect1d(views[0].index, views[1].index)
    assert 0.05 * len(views[0].index) < len(shared) < 0.8 * len(views[0].index)  # partial overlap
