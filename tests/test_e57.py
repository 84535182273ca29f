"""E57 input: real and broken samples through the CLI, and a 3-scan file with poses written with pye57."""

from pathlib import Path

import laspy
import numpy as np
import pye57
import pytest
from helpers import assert_one_line_error, invoke, pair_prior, write_e57
from pye57 import libe57

from plotmosaic.errors import InputError
from plotmosaic.graph.cache import file_hash
from plotmosaic.io.e57 import list_scans, scan_ref, stored_pose
from plotmosaic.io.frame import inverse, pose_error
from plotmosaic.io.las import iter_chunks, open_las, read_cloud, read_header_info
from plotmosaic.manifest import load_manifest
from plotmosaic.poses import Poses, ScanPose, load_poses


@pytest.mark.parametrize(
    "name, needles",
    [
        ("bad-crc.e57", ("bad-crc.e57", "checksum")),
        ("empty.e57", ("empty.e57", "no scans")),
        ("ZeroPoints.e57", ("ZeroPoints.e57", "scan 0", "no points")),
        ("InvalidCVHeader.e57", ("InvalidCVHeader.e57", "scan 0")),
    ],
)
def test_bad_files_one_line_exit_2(e57_dir, name, needles):
    assert_one_line_error(invoke("info", e57_dir / name), *needles)
    assert_one_line_error(invoke("info", "--full", e57_dir / name), *needles)


@pytest.mark.parametrize(
    "name, count", [("pumpAVisualReferenceImage.e57", 155_201), ("bunnyDouble.e57", 30_571)]
)
def test_real_samples_exact_counts(e57_dir, name, count):
    result = invoke("info", "--full", e57_dir / name)
    assert result.exit_code == 0, result.output
    assert f"{count:,} points" in result.output and "invalid" not in result.output
    cloud = read_cloud(e57_dir / name)
    assert len(cloud) == count and cloud.xyz.dtype == np.float64
    assert read_header_info(e57_dir / name).point_count == count


def test_attributes_and_chunks(e57_dir):
    pump = e57_dir / "pumpAVisualReferenceImage.e57"
    cloud = read_cloud(pump)
    assert set(cloud.attrs) == {"intensity", "red", "green", "blue"}
    assert all(v.dtype == np.uint16 for v in cloud.attrs.values())
    assert (
        cloud.attrs["intensity"].max() > 1000 and cloud.attrs["red"].max() > 1000
    )  # mapped to the LAS range
    chunks = list(iter_chunks(pump, chunk_size=40_000))
    assert [len(c) for c in chunks] == [40_000] * 3 + [35_201]
    np.testing.assert_array_equal(np.vstack([c.xyz for c in chunks]), cloud.xyz)
    with open_las(pump) as reader:  # merge's view: LAS records (0.1 mm), same points
        records = list(reader.chunk_iterator(100_000))
    xyz = np.vstack([np.column_stack([r.x, r.y, r.z]) for r in records])
    assert np.abs(xyz - cloud.xyz).max() < 6e-5
    np.testing.assert_array_equal(
        np.concatenate([np.asarray(r.intensity) for r in records]), cloud.attrs["intensity"]
    )


def test_stored_pose_and_normals(e57_dir):
    T = stored_pose(e57_dir / "translationWithoutRotation.e57")
    np.testing.assert_allclose(T, [[1, 0, 0, 4], [0, 1, 0, 5], [0, 0, 1, 6], [0, 0, 0, 1]])
    assert stored_pose(e57_dir / "bunnyDouble.e57") is None
    normals = read_cloud(e57_dir / "testWithNormals.e57")
    assert {"normal_x", "normal_y", "normal_z"} <= set(normals.attrs) and len(normals) == 2


# ---------------------------------------------------------------- a 3-scan project file


SUBSET = ["P1-S0", "P1-S2", "P1-S3"]  # neighbours, as in test_register.py


@pytest.fixture(scope="module")
def project(small_sim, tmp_path_factory):
    """Three scans of the `small` plot in one E57, each with its true pose (in S0's frame) stored."""
    truth = load_poses(small_sim.ground_truth_path)
    manifest = load_manifest(small_sim.manifest_path)
    rows, points, poses, counts = [], {}, {}, {}
    for sid in SUBSET:
        xyz = read_cloud(manifest.resolve(manifest.scan(sid).path), attributes=False).xyz
        pose = inverse(truth.transform(SUBSET[0])) @ truth.transform(sid)
        state = np.zeros(len(xyz), np.int8)
        state[::97] = 2  # missing returns: points flagged invalid are dropped on reading
        rows.append((sid, xyz, pose, {"cartesianInvalidState": state}))
        points[sid], poses[sid], counts[sid] = xyz[state == 0], pose, len(xyz)
    path = write_e57(tmp_path_factory.mktemp("e57") / "plot.e57", rows)
    return path, SUBSET, points, poses, counts


def test_project_scans_points_and_poses(project):
    path, ids, points, poses, counts = project
    scans = list_scans(path)
    assert [s.name for s in scans] == ids
    for i, sid in enumerate(ids):
        got = read_cloud(scan_ref(path, i)).xyz  # pye57 writes single-precision coordinates
        np.testing.assert_array_equal(got, points[sid].astype(np.float32))
        info = read_header_info(scan_ref(path, i))
        np.testing.assert_allclose([info.mins, info.maxs], [got.min(axis=0), got.max(axis=0)])
        np.testing.assert_allclose(stored_pose(path, i), poses[sid], atol=1e-9)
        np.testing.assert_allclose(stored_pose(path, sid), poses[sid], atol=1e-9)


def test_project_info_lists_scans(project):
    path, ids, points, poses, counts = project
    result = invoke("info", path)
    assert result.exit_code == 0, result.output
    assert "3 scan(s)" in result.output
    for i, sid in enumerate(ids):
        t = poses[sid][:3, 3]
        line = next(line for line in result.output.splitlines() if line.startswith(f"  scan {i} "))
        assert repr(sid) in line and f"({t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f})" in line
        assert f"{counts[sid]:,} points" in line
    full = invoke("info", "--full", path)
    assert f"({counts[ids[0]] - len(points[ids[0]]):,} flagged invalid)" in full.output


def test_manifest_scan_selection(project, tmp_path):
    path, ids, points, poses, counts = project
    toml = tmp_path / "m.toml"
    toml.write_text(
        f'plot_id = "P"\n[[scans]]\nid = "a"\npath = "{path}"\nscan = 2\n'
        f'[[scans]]\nid = "b"\npath = "{path}"\nscan = "{ids[0]}"\nuse_pose = true\n'
    )
    m = load_manifest(toml)
    np.testing.assert_array_equal(
        read_cloud(m.resolve(m.scan("a").path)).xyz, points[ids[2]].astype(np.float32)
    )
    np.testing.assert_array_equal(
        read_cloud(m.resolve(m.scan("b").path)).xyz, points[ids[0]].astype(np.float32)
    )
    assert m.stored_pose("a") is None  # use_pose not set
    np.testing.assert_allclose(m.stored_pose("b"), poses[ids[0]], atol=1e-9)

    toml.write_text(f'plot_id = "P"\n[[scans]]\nid = "a"\npath = "{path}"\n')
    assert_one_line_error(invoke("info", toml), "m.toml", "scan 'a'", "3 scans", *ids)
    toml.write_text(f'plot_id = "P"\n[[scans]]\nid = "a"\npath = "{path}"\nscan = 7\n')
    assert_one_line_error(invoke("info", toml), "m.toml", "scan 'a'", "no scan 7")
    toml.write_text(f'plot_id = "P"\n[[scans]]\nid = "a"\npath = "{path}"\nscan = "nope"\n')
    assert_one_line_error(invoke("info", toml), "m.toml", "'nope'")


def test_manifest_from_writes_a_valid_manifest(project, tmp_path):
    path, ids, points, poses, counts = project
    result = invoke("manifest-from", path, "--use-pose")  # stdout: absolute paths
    assert result.exit_code == 0, result.output
    (tmp_path / "stdout.toml").write_text(result.output)
    out = path.parent / "sub" / "plot.toml"
    result = invoke("manifest-from", path, "--out", out, "--plot-id", "P1")
    assert result.exit_code == 0, result.output
    assert (
        "../plot.e57" not in out.read_text()
    )  # outside the manifest's folder: absolute, no ../ chain
    for toml in (tmp_path / "stdout.toml", out):
        m = load_manifest(toml)
        assert [s.id for s in m.scans] == ids and m.plots[0].reference.id == ids[0]
        for i, sid in enumerate(ids):
            np.testing.assert_array_equal(
                read_cloud(m.resolve(m.scan(sid).path)).xyz, points[ids[i]].astype(np.float32)
            )
    m = load_manifest(tmp_path / "stdout.toml")
    rel = pair_prior(m, ids[1], ids[0])  # scan frame of ids[1] -> scan frame of ids[0]
    np.testing.assert_allclose(rel, np.linalg.inv(poses[ids[0]]) @ poses[ids[1]], atol=1e-9)
    assert pair_prior(load_manifest(out), ids[1], ids[0]) is None  # written without --use-pose
    assert_one_line_error(
        invoke("manifest-from", path, "--out", out), "plot.toml", "already exists"
    )
    assert_one_line_error(
        invoke("manifest-from", path, "--plot-id", "../x"), "--plot-id", "not allowed"
    )


def test_manifest_from_bad_files(e57_dir):
    assert_one_line_error(invoke("manifest-from", e57_dir / "empty.e57"), "empty.e57", "no scans")
    assert_one_line_error(
        invoke("manifest-from", e57_dir / "ZeroPoints.e57"), "ZeroPoints.e57", "scan 0", "no points"
    )
    assert_one_line_error(
        invoke("manifest-from", e57_dir / "bad-crc.e57"), "bad-crc.e57", "checksum"
    )


def write_spherical_e57(
    path: Path, rae: np.ndarray, state: np.ndarray, intensity: np.ndarray
) -> Path:
    """A one-scan E57 in spherical coordinates (double range, scaled-integer angles), with libE57 itself."""
    n = len(rae)
    with pye57.E57(str(path), mode="w") as e57:
        imf = e57.image_file
        scan = libe57.StructureNode(imf)
        scan.set("guid", libe57.StringNode(imf, "{spherical-test}"))
        scan.set("name", libe57.StringNode(imf, "sph"))
        proto = libe57.StructureNode(imf)
        proto.set("sphericalRange", libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE, 0.0, 1000.0))
        for name in ("sphericalAzimuth", "sphericalElevation"):  # 1e-6 rad steps
            proto.set(name, libe57.ScaledIntegerNode(imf, 0, -4_000_000, 4_000_000, 1e-6, 0.0))
        proto.set("sphericalInvalidState", libe57.IntegerNode(imf, 0, 0, 2))
        proto.set("intensity", libe57.IntegerNode(imf, 0, 0, 4095))
        proto.set("isIntensityInvalid", libe57.IntegerNode(imf, 0, 0, 1))
        points = libe57.CompressedVectorNode(imf, proto, libe57.VectorNode(imf, True))
        scan.set("points", points)
        e57.data3d.append(scan)
        arrays = {
            "sphericalRange": rae[:, 0].copy(),
            "sphericalAzimuth": rae[:, 1].copy(),
            "sphericalElevation": rae[:, 2].copy(),
            "sphericalInvalidState": state.astype(np.int8),
            "intensity": intensity.astype(np.uint16),
            "isIntensityInvalid": (np.arange(n) % 7 == 0).astype(np.int8),
        }
        buffers = libe57.VectorSourceDestBuffer()
        for name, array in arrays.items():
            buffers.append(libe57.SourceDestBuffer(imf, name, array, n, True, True))
        writer = points.writer(buffers)
        writer.write(n)
        writer.close()
    return path


def test_spherical_scaled_integer_and_invalid_points(tmp_path):
    rng = np.random.default_rng(5)
    n = 3000
    rae = np.column_stack(
        [rng.uniform(1, 50, n), rng.uniform(-3.1, 3.1, n), rng.uniform(-1.2, 1.2, n)]
    )
    rae[:, 1:] = np.round(rae[:, 1:] * 1e6) / 1e6  # what the scaled integers hold
    state = np.where(np.arange(n) % 10 == 0, 2, 0)  # every tenth point missing
    intensity = rng.integers(1, 4096, n)
    path = write_spherical_e57(tmp_path / "sph.e57", rae, state, intensity)
    chunks = list(iter_chunks(path, chunk_size=1000))
    assert len(chunks) == 3
    cloud = read_cloud(path)
    r, az, el = rae[state == 0].T
    expected = np.column_stack(
        [r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)]
    )
    np.testing.assert_allclose(cloud.xyz, expected, atol=1e-9)
    assert len(cloud) == n - n // 10 and cloud.attrs["intensity"].dtype == np.uint16
    keep = state == 0
    no_value = (np.arange(n) % 7 == 0)[
        keep
    ]  # isIntensityInvalid: written as 0, the others scaled from 0..4095
    np.testing.assert_array_equal(cloud.attrs["intensity"][no_value], 0)
    expected_i = np.rint(intensity[keep][~no_value] * 65535 / 4095).astype(np.uint16)
    np.testing.assert_array_equal(cloud.attrs["intensity"][~no_value], expected_i)
    result = invoke("info", "--full", path)
    assert (
        result.exit_code == 0 and f"{n:,} points ({n // 10:,} flagged invalid)" in result.output
    ), result.output


def test_scans_of_one_file_have_their_own_cache_keys(project):
    """graph/cache.file_hash tells the scans of one E57 apart, else their pairs would share a cache entry."""
    path = project[0]
    keys = [file_hash(scan_ref(path, i)) for i in range(3)]
    assert len(set(keys)) == 3 and all(k.startswith(file_hash(path)) for k in keys)


@pytest.mark.slow
def test_register_plot_from_e57(project, tmp_path):
    path, ids, points, poses, counts = project
    toml = tmp_path / "m.toml"
    toml.write_text(
        'plot_id = "P1"\n'
        + "".join(
            f'[[scans]]\nid = "{s}"\npath = "{path}"\nscan = {i}\n' for i, s in enumerate(ids)
        )
    )
    result = invoke("register-plot", toml, "--out", tmp_path / "out", "-j", "1")
    assert result.exit_code == 0, result.output
    got = load_poses(tmp_path / "out" / "poses.json")
    for sid in ids:  # the stored poses are the truth in S0's frame
        rot, trans = pose_error(got.transform(sid), poses[sid])
        assert trans < 0.02 and rot < 0.1, (sid, trans, rot)


def test_merge_carries_intensity_and_colour(e57_dir, tmp_path):
    """Two E57 scans (one with intensity + colour, one with colour) merged: counts, positions and attributes kept."""
    pump, cube = e57_dir / "pumpAVisualReferenceImage.e57", e57_dir / "ColouredCubeFloat.e57"
    toml = tmp_path / "m.toml"
    toml.write_text(
        f'plot_id = "P"\n[[scans]]\nid = "pump"\npath = "{pump}"\n[[scans]]\nid = "cube"\npath = "{cube}"\nscan = 0\n'
    )
    shift = np.eye(4)
    shift[:3, 3] = [10, 0, 0]
    Poses(
        {"pump": ScanPose(np.eye(4), "P", None), "cube": ScanPose(shift, "P", None)},
        frame="plot",
        crs=None,
    ).save(tmp_path / "poses.json")
    result = invoke(
        "merge", toml, "--poses", tmp_path / "poses.json", "--out", tmp_path / "merged.laz"
    )
    assert result.exit_code == 0, result.output
    las = laspy.read(tmp_path / "merged.laz")
    assert np.bincount(las.point_source_id).tolist() == [155_201, 7_680]
    src = read_cloud(pump)
    mine = las.point_source_id == 0  # merge keeps each file's point order
    np.testing.assert_allclose(
        np.column_stack([las.x, las.y, las.z])[mine], src.xyz, atol=6e-4
    )  # 1 mm output grid
    for name in ("intensity", "red", "green", "blue"):
        np.testing.assert_array_equal(np.asarray(las[name])[mine], src.attrs[name])
    cube = read_cloud(cube)
    np.testing.assert_allclose(
        np.column_stack([las.x, las.y, las.z])[~mine], cube.xyz + [10, 0, 0], atol=6e-4
    )
    np.testing.assert_array_equal(np.asarray(las.blue)[~mine], cube.attrs["blue"])


def test_bad_stored_pose_only_matters_where_used(tmp_path):
    """A non-unit quaternion: the points still read, info says why, use_pose names file and scan."""
    xyz = np.random.default_rng(2).uniform(-5, 5, (200, 3))
    path = tmp_path / "q.e57"
    with pye57.E57(str(path), mode="w") as e57:
        data = {"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2]}
        e57.write_scan_raw(
            data, name="q", rotation=np.array([2.0, 0, 0, 0]), translation=np.array([1.0, 2, 3])
        )
    assert len(read_cloud(path)) == 200
    assert "unusable stored pose" in invoke("info", path).output
    toml = tmp_path / "m.toml"
    toml.write_text(f'plot_id = "P"\n[[scans]]\nid = "a"\npath = "{path}"\nuse_pose = true\n')
    with pytest.raises(InputError, match="q.e57: scan 0 \\('q'\\): unusable stored pose"):
        load_manifest(toml).stored_pose("a")
