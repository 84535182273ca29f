"""The forest simulator: ground truth, determinism, ALS density, partial overlap, manifests, CLI."""

import hashlib
from pathlib import Path

import numpy as np
import pytest
from pyproj import CRS
from typer.testing import CliRunner

from plotmosaic.cli import app
from plotmosaic.config.simulate import PRESETS, ForestConfig
from plotmosaic.io.frame import apply_transform
from plotmosaic.io.las import read_cloud, read_header_info
from plotmosaic.manifest import load_manifest
from plotmosaic.poses import load_poses
from plotmosaic.simulate.mesh import FOLIAGE, GROUND, UNDERSTORY, WOODY, concat
from plotmosaic.simulate.run import make_config, scan_path, simulate
from plotmosaic.simulate.scene import Scene, build_world, plot_ids, scan_id
from plotmosaic.simulate.stats import density, overlap_fraction
from plotmosaic.simulate.trees import Tree, broadleaf_meshes, conifer_meshes

SAMPLES = Path(__file__).resolve().parents[1] / "sample_manifests"


def expected_scans(config) -> list[tuple[str, str, Path]]:
    """(plot id, scan id, relative path) of every TLS scan `simulate` writes for this config."""
    return [
        (pid, scan_id(pid, i), scan_path(pid, scan_id(pid, i)))
        for pid in plot_ids(config)
        for i in range(len(config.scan_layout))
    ]


@pytest.fixture(scope="module")
def small_world(small_sim):
    return build_world(small_sim.config, small_sim.seed)


def _world_xyz(small_sim, scan_id):
    truth = load_poses(small_sim.ground_truth_path)
    cloud = read_cloud(small_sim.scan_paths[scan_id])
    return cloud, apply_transform(truth.transform(scan_id), cloud.xyz)


def test_outputs_follow_the_contract(small_sim):
    m = load_manifest(small_sim.manifest_path)  # checks the files exist
    assert [p.id for p in m.plots] == ["P1"]
    plot = m.plots[0]
    assert plot.crs == "EPSG:26912" and plot.reference.id == "P1-S0"
    assert [s.id for s in plot.scans] == [f"P1-S{i}" for i in range(5)]
    assert all(s.kind.value == "tls" and s.approx_position is None for s in plot.scans)
    assert [t.path.as_posix() for t in m.als] == ["als/als.laz"]
    truth = load_poses(small_sim.ground_truth_path)
    assert truth.frame == "crs" and CRS.from_user_input(truth.crs).to_epsg() == 26912
    assert set(truth.scans) == {s.id for s in plot.scans}
    for sid, pose in truth.scans.items():
        t = pose.transform[:3, 3]
        assert pose.plot == "P1"
        assert abs(t[0] - 470000) < 2000 and abs(t[1] - 3810000) < 2000 and 2050 < t[2] < 2150
        up = pose.transform[:3, 2]
        assert np.degrees(np.arccos(up[2])) <= 2.0 + 1e-6  # tilt up to 2 deg
        cloud = read_cloud(small_sim.scan_paths[sid])
        assert 20_000 < len(cloud) <= 60_000
        assert {"label", "intensity", "return_number", "number_of_returns", "gps_time"} <= set(
            cloud.attrs
        )
        assert set(np.unique(cloud.attrs["label"])) == {GROUND, WOODY, FOLIAGE, UNDERSTORY}
        assert np.linalg.norm(cloud.xyz, axis=1).max() <= small_sim.config.tls.max_range_m + 0.1
    headings = [
        np.degrees(np.arctan2(p.transform[1, 0], p.transform[0, 0])) for p in truth.scans.values()
    ]
    assert np.ptp(headings) > 30  # random headings, not all aligned


def test_small_is_forest_like(small_world):
    mesh = small_world.mesh
    counts = np.bincount(mesh.labels, minlength=4)
    assert counts.min() > 1000
    trees = small_world.vegetation.trees
    assert len(trees) > 30 and any(t.conifer for t in trees) and any(not t.conifer for t in trees)
    for t in trees:
        lo, hi = (15, 30) if t.conifer else (10, 20)
        assert lo <= t.height <= hi and 0.10 <= t.dbh <= 0.80
    assert max(np.degrees(np.arccos(t.lean[2])) for t in trees) > 2  # some lean
    z = small_world.terrain.z
    assert np.ptp(z) > 2.0  # real topography, not a plane at z = 0


def test_scans_lie_on_the_scene_surfaces(small_sim, small_world):
    """Each scan mapped by its ground-truth pose lies on the mesh within the range noise."""
    scene = Scene(small_world.mesh)
    tls = small_sim.config.tls
    for sid in small_sim.scan_paths:
        cloud, world = _world_xyz(small_sim, sid)
        rng = np.linalg.norm(cloud.xyz, axis=1)
        sigma = tls.range_noise_m + tls.range_noise_per_m * rng
        d = scene.distance(world - small_world.origin)
        assert np.mean(d <= 4 * sigma + 0.0015) > 0.999, sid
        assert np.median(d) < 0.005
        # The labels come from the surface they lie on.
        closest = scene.raycaster.compute_closest_points(
            __import__("open3d").core.Tensor((world - small_world.origin).astype(np.float32))
        )
        lab = small_world.mesh.labels[closest["primitive_ids"].numpy()]
        assert np.mean(lab == cloud.attrs["label"]) > 0.97
    # The check can fail: a pose off by 1 degree / 10 cm puts the points off the surfaces.
    cloud, _ = _world_xyz(small_sim, "P1-S1")
    T = load_poses(small_sim.ground_truth_path).transform("P1-S1").copy()
    c, s = np.cos(np.radians(1)), np.sin(np.radians(1))
    T[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ T[:3, :3]
    T[:3, 3] += [0.1, 0, 0]
    assert np.median(scene.distance(apply_transform(T, cloud.xyz) - small_world.origin)) > 0.02


def test_ground_points_follow_the_terrain(small_sim, small_world):
    cloud, world = _world_xyz(small_sim, "P1-S0")
    local = world - small_world.origin
    ground = cloud.attrs["label"] == GROUND
    dz = local[ground, 2] - small_world.terrain.height(local[ground, 0], local[ground, 1])
    assert np.percentile(np.abs(dz), 99) < 0.03


def test_same_seed_same_files(small_sim, tmp_path):
    again = simulate(tmp_path / "again", "small", seed=0)
    other = simulate(tmp_path / "other", "small", seed=1)

    def digest(path):
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()

    for sid, path in small_sim.scan_paths.items():
        assert digest(path) == digest(again.scan_paths[sid]), sid
        assert digest(path) != digest(other.scan_paths[sid]), sid
    assert digest(small_sim.als_paths[0]) == digest(again.als_paths[0])
    assert digest(small_sim.ground_truth_path) == digest(again.ground_truth_path)
    assert digest(small_sim.manifest_path) == digest(again.manifest_path)
    assert digest(small_sim.ground_truth_path) != digest(other.ground_truth_path)


def test_als_tile(small_sim, small_world):
    info = read_header_info(small_sim.als_paths[0])
    assert info.crs is not None and info.crs.to_epsg() == 26912
    als = read_cloud(small_sim.als_paths[0])
    assert abs(als.xyz[:, 0].mean() - 470250) < 100 and abs(als.xyz[:, 1].mean() - 3810150) < 100
    local = als.xyz - small_world.origin
    ext = small_sim.als_extent
    requested = small_sim.config.als.density_per_m2
    whole = density(local[:, :2], ext)
    cx, cy = (ext[0] + ext[2]) / 2, (ext[1] + ext[3]) / 2
    centre = density(local[:, :2], (cx - 15, cy - 15, cx + 15, cy + 15))
    print(
        f"ALS density requested {requested}, whole tile {whole:.2f}, central 30 x 30 m {centre:.2f} pts/m2"
    )
    assert abs(whole / requested - 1) < 0.2 and abs(centre / requested - 1) < 0.2
    nr, rn = als.attrs["number_of_returns"], als.attrs["return_number"]
    assert nr.max() >= 3 and (rn <= nr).all() and (rn >= 1).all()
    lab, cls = als.attrs["label"], als.attrs["classification"]
    assert set(np.unique(cls)) <= {2, 3, 4, 5}
    assert (cls[lab == GROUND] == 2).all() and (cls[lab == FOLIAGE] == 5).mean() > 0.95
    # Multiple returns through canopy gaps: some last returns of multi-return pulses are ground.
    assert ((rn == nr) & (nr > 1) & (lab == GROUND)).sum() > 50
    # ALS sees canopy and ground, little mid-story.
    assert (lab == GROUND).mean() > 0.2 and (lab == FOLIAGE).mean() > 0.2


def test_scans_overlap_only_partly(small_sim):
    _, centre = _world_xyz(small_sim, "P1-S0")
    fractions = {}
    for sid in ["P1-S1", "P1-S2", "P1-S3", "P1-S4"]:
        _, corner = _world_xyz(small_sim, sid)
        fractions[sid] = (
            overlap_fraction(centre, corner, 0.05),
            overlap_fraction(centre, corner, 0.25),
        )
    print(
        "overlap of P1-S0 with corner scans (5 cm, 25 cm):",
        {k: tuple(round(v, 3) for v in f) for k, f in fractions.items()},
    )
    assert overlap_fraction(centre, centre, 0.05) == 1.0
    for f5, f25 in fractions.values():
        assert 0.01 < f5 < f25 < 0.9  # they share a lot, but occlusion hides much from each other


def test_sample_manifests_match_the_simulator(small_sim):
    plot = load_manifest(SAMPLES / "plot.toml", check_files=False)
    written = load_manifest(small_sim.manifest_path)
    assert [(s.id, s.path, s.reference) for s in plot.scans] == [
        (s.id, s.path, s.reference) for s in written.scans
    ]
    assert [p.id for p in plot.plots] == [p.id for p in written.plots] and plot.plots[
        0
    ].crs == "EPSG:26912"
    assert [t.path for t in plot.als] == [t.path for t in written.als]
    region = load_manifest(SAMPLES / "region.toml", check_files=False)
    expected = expected_scans(make_config("region"))
    assert [(p.id, s.id, s.path) for p in region.plots for s in p.scans] == expected
    assert all(p.crs == "EPSG:26912" and p.reference.id.endswith("-S0") for p in region.plots)
    assert [t.path for t in region.als] == [t.path for t in written.als]
    # and the simulator's own naming agrees for the small preset it ran
    assert [(p.id, s.id, s.path) for p in written.plots for s in p.scans] == expected_scans(
        small_sim.config
    )


def test_presets_are_valid():
    assert set(PRESETS) == {
        "small",
        "paper",
        "region",
        "region10",
        "large",
        "understorey",
        "grassland",
        "prepost",
        "scattered",
        "bare-stems",
    }
    # the forests unlike ours (issue 53): six scans, 30 m range, a 40 m scene
    for name, crowns in (("scattered", "scattered"), ("bare-stems", "none")):
        cfg = PRESETS[name]
        assert cfg.forest.crowns == crowns and len(cfg.scan_layout) == 6
        assert cfg.tls.max_range_m == 30.0
    assert (
        PRESETS["bare-stems"].forest.shrubs_per_ha
        == PRESETS["bare-stems"].forest.saplings_per_ha
        == 0
    )
    assert all(
        PRESETS[n].forest.crowns == "branches"
        for n in PRESETS
        if n not in ("scattered", "bare-stems")
    )
    assert PRESETS["small"].tls.points_per_scan <= 60_000
    assert PRESETS["grassland"].forest.trees_per_ha == 0
    assert len(PRESETS["region"].plot_centres) >= 3 and PRESETS["prepost"].prepost


def test_prepost_thins_only_the_understory():
    cfg = make_config(
        "prepost", tree_density=60, grass_density=0.4, shrub_density=400, **{"scene_margin_m": 10.0}
    )
    world = build_world(cfg, 3)
    pre, post = world.mesh, world.post_mesh
    for label in (GROUND, WOODY, FOLIAGE):
        assert (post.labels == label).sum() == (pre.labels == label).sum()
    kept = (post.labels == UNDERSTORY).sum() / (pre.labels == UNDERSTORY).sum()
    assert 0.1 < kept < 0.5
    assert [s.plot_id for s in world.sites] == ["PRE"] * 5 + ["POST"] * 5
    d = [np.linalg.norm(a.xy - b.xy) for a, b in zip(world.sites[:5], world.sites[5:])]
    assert all(0.5 < x < 1.0 for x in d)


def test_cli(tmp_path):
    runner = CliRunner()
    out = tmp_path / "sim"
    result = runner.invoke(
        app,
        [
            "simulate",
            str(out),
            "--preset",
            "small",
            "--seed",
            "2",
            "--approx-positions",
            "--points-per-scan",
            "20000",
        ],
    )
    assert result.exit_code == 0, result.output
    assert "5 TLS scans" in result.output and "manifest.toml" in result.output
    m = load_manifest(out / "manifest.toml")
    truth = load_poses(out / "ground_truth.json")
    for s in m.scans:
        assert s.approx_position_frame == "crs"
        err = np.linalg.norm(np.array(s.approx_position) - truth.transform(s.id)[:3, 3])
        assert 0.1 < err < 20  # noisy by metres
    again = runner.invoke(app, ["simulate", str(out)])
    assert again.exit_code == 2 and "not empty" in again.output
    bad = runner.invoke(app, ["simulate", str(tmp_path / "x"), "--preset", "huge"])
    assert bad.exit_code == 2 and "unknown preset" in bad.output


def test_scale_presets_validate():
    from plotmosaic.config.simulate import grid_layout

    large = PRESETS["large"]
    assert (
        len(large.scan_layout) >= 36 and not large.approx_positions and len(large.plot_centres) == 1
    )
    xy = np.array(large.scan_layout)
    gaps = np.sort(np.linalg.norm(xy[:, None] - xy[None], axis=2), axis=1)[:, 1]
    assert 15.0 <= gaps.min() and gaps.max() <= 20.0
    assert (
        0.7e4 <= np.ptp(xy[:, 0]) * np.ptp(xy[:, 1])
        and (np.ptp(xy[:, 0]) + 30) * (np.ptp(xy[:, 1]) + 30) <= 1.5e4
    )  # ~1 ha
    assert large.tls.points_per_scan == 1_000_000
    region = PRESETS["region10"]
    centres = np.array(region.plot_centres)
    assert (
        len(centres) >= 10
        and np.sort(np.linalg.norm(centres[:, None] - centres[None], axis=2), axis=1)[:, 1].min()
        >= 60
    )
    under = PRESETS["understorey"]
    assert under.forest.shrubs_per_ha >= 5000 and len(under.scan_layout) >= 2
    assert grid_layout(3, 10.0) == [(x, y) for y in (-10.0, 0.0, 10.0) for x in (-10.0, 0.0, 10.0)]
    assert make_config("large", points_per_scan=60_000).tls.points_per_scan == 60_000


def test_tiny_large_and_understorey_simulate(tmp_path):
    from plotmosaic.config.simulate import grid_layout

    tiny = dict(
        points_per_scan=4000,
        tree_density=80,
        shrub_density=200,
        grass_density=0.2,
        scene_margin_m=6.0,
        scan_layout=grid_layout(2, 16.0),
        **{"terrain.cell": 1.0},
    )
    large = simulate(tmp_path / "large", "large", seed=0, **tiny)
    m = load_manifest(large.manifest_path)
    assert len(m.scans) == 4 and all(s.approx_position is None for s in m.scans)
    under = simulate(
        tmp_path / "under", "understorey", seed=0, points_per_scan=8000, scene_margin_m=6.0
    )
    near = [
        np.mean(np.linalg.norm(read_cloud(p, attributes=False).xyz, axis=1) <= 5.0)
        for p in under.scan_paths.values()
    ]
    assert len(near) == 3 and min(near) > 0.5  # most returns from within 5 m of the scanner


def test_cli_scan_grid_and_one_line_errors(tmp_path):
    runner = CliRunner()
    bad = runner.invoke(app, ["simulate", str(tmp_path / "x"), "--preset", "huge"])
    assert (
        bad.exit_code == 2
        and bad.output.startswith("error: unknown preset")
        and len(bad.output.splitlines()) == 1
    )
    assert not (tmp_path / "x").exists()
    res = runner.invoke(
        app,
        [
            "simulate",
            str(tmp_path / "g"),
            "--preset",
            "small",
            "--scan-grid",
            "2",
            "--scan-spacing",
            "15",
            "--points-per-scan",
            "3000",
            "--tree-density",
            "60",
            "--grass-density",
            "0.2",
        ],
    )
    assert res.exit_code == 0, res.output
    truth = load_poses(tmp_path / "g" / "ground_truth.json")
    xy = np.array([p.transform[:2, 3] for p in truth.scans.values()])
    assert (
        len(xy) == 4
        and 14.0 < np.sort(np.linalg.norm(xy[:, None] - xy[None], axis=2), axis=1)[:, 1].min()
    )
    mixed = runner.invoke(app, ["simulate", str(tmp_path / "y"), "--views", "2"])
    assert mixed.exit_code == 2 and "--from-cloud" in mixed.output


def _tree(conifer: bool) -> Tree:
    return Tree(0.0, 0.0, 0.4, 20.0, conifer, np.array([0.0, 0.0, 1.0]), 8.0, 3.0, True)


@pytest.mark.parametrize("conifer", [True, False])
def test_crowns_scattered_and_none(conifer):
    """`crowns`: scattered keeps the foliage of the branch crown but no branch, spread through the
    crown volume; none leaves the stem alone. Every mode keeps the same stem."""
    make = conifer_meshes if conifer else broadleaf_meshes
    meshes = {}
    for crowns in ("branches", "scattered", "none"):
        cfg = ForestConfig(crowns=crowns)
        meshes[crowns] = concat(make(_tree(conifer), 0.0, cfg, np.random.default_rng(5), 7))
    woody = {k: int((m.labels == WOODY).sum()) for k, m in meshes.items()}
    foliage = {k: int((m.labels == FOLIAGE).sum()) for k, m in meshes.items()}
    stem = woody["none"]
    assert foliage["none"] == 0 and stem > 0
    assert woody["scattered"] == stem < woody["branches"]  # the stem, no branch
    assert 0.5 < foliage["scattered"] / foliage["branches"] < 2.0  # about the same foliage
    # scattered: every element inside the crown volume (a cone from the crown base to the top, or an
    # ellipsoid around the crown's middle), as no branch carries it out
    m = meshes["scattered"]
    v = m.vertices[m.triangles[m.labels == FOLIAGE]].mean(axis=1)
    if conifer:
        depth = np.clip((20.0 - v[:, 2]) / 12.0, 0, None)  # 0 at the top, 1 at the crown base
        inside = (v[:, 2] > 8.0) & (np.linalg.norm(v[:, :2], axis=1) <= 3.0 * depth + 0.1)
    else:
        inside = np.linalg.norm((v - [0.0, 0.0, 14.0]) / [3.0, 3.0, 6.0], axis=1) <= 1.02
    assert inside.mean() > 0.99


def test_cli_stands_unlike_ours_and_drawn_forests(tmp_path):
    """`--preset bare-stems --tree-density N`, `--crowns`, and `--drawn` (the same seed, the same files)."""
    runner = CliRunner()
    small = ["--points-per-scan", "3000"]
    res = runner.invoke(
        app,
        ["simulate", str(tmp_path / "b"), "--preset", "bare-stems", "--tree-density", "50", *small],
    )
    assert res.exit_code == 0, res.output
    assert len(load_manifest(tmp_path / "b" / "manifest.toml").scans) == 6
    labels = read_cloud(tmp_path / "b" / "P1" / "P1-S0.laz").attrs["label"]
    assert (labels == FOLIAGE).sum() == 0 and (labels == WOODY).sum() > 0  # bare stems
    res = runner.invoke(
        app,
        ["simulate", str(tmp_path / "c"), "--crowns", "scattered", "--tree-density", "60", *small],
    )
    assert res.exit_code == 0, res.output
    bad = runner.invoke(app, ["simulate", str(tmp_path / "x"), "--crowns", "leafy"])
    assert bad.exit_code == 2 and bad.output.startswith("error: simulation setting forest.crowns")
    digests = []
    for name, seed in (("d1", "4"), ("d2", "4"), ("d3", "5")):
        res = runner.invoke(
            app,
            [
                "simulate",
                str(tmp_path / name),
                "--drawn",
                "--seed",
                seed,
                "--points-per-scan",
                "5000",
            ],
        )
        assert res.exit_code == 0, res.output
        files = sorted((tmp_path / name).rglob("*.laz"))
        files += [tmp_path / name / "ground_truth.json", tmp_path / name / "manifest.toml"]
        assert len(files) == 8  # six scans, the truth, the manifest
        digests.append([hashlib.sha256(f.read_bytes()).hexdigest() for f in files])
    assert digests[0] == digests[1] and digests[0] != digests[2]
    truth = load_poses(tmp_path / "d1" / "ground_truth.json")
    cloud = read_cloud(tmp_path / "d1" / "P1" / "P1-S1.laz", attributes=False).xyz
    world = apply_transform(truth.transform("P1-S1"), cloud) - truth.transform("P1-S1")[:3, 3]
    assert np.linalg.norm(world, axis=1).max() <= 30.0 + 0.02  # within range of its scanner
    clash = runner.invoke(app, ["simulate", str(tmp_path / "y"), "--drawn", "--preset", "small"])
    assert clash.exit_code == 2 and "--drawn: --preset" in clash.output
