"""`plotmosaic export`: matrices, a PDAL pipeline, an E57 with poses and COPC, each read back and
held against `plotmosaic merge` of the same inputs on the small simulated plot."""

import json
import shutil
import subprocess
from pathlib import Path

import copclib
import laspy
import numpy as np
import pye57
import pytest
from helpers import assert_one_line_error, invoke, write_e57
from scipy.spatial.transform import Rotation

from plotmosaic.config.merge import MergeConfig
from plotmosaic.io import PointCloud, write_cloud
from plotmosaic.io.frame import apply_transform
from plotmosaic.io.las import read_cloud
from plotmosaic.manifest import Manifest, Plot, Scan, dump_manifest, load_manifest
from plotmosaic.poses import Poses, ScanPose, load_poses
from plotmosaic.stages.export import write_copc
from plotmosaic.stages.merge import merge_scans


@pytest.fixture(scope="module")
def inputs(small_sim):
    return small_sim.manifest_path, small_sim.ground_truth_path


@pytest.fixture(scope="module")
def merged(inputs, tmp_path_factory):
    """`merge` of the small plot: (points as written, point_source_id, header)."""
    manifest, poses = inputs
    out = tmp_path_factory.mktemp("merged") / "merged.laz"
    merge_scans(load_manifest(manifest), load_poses(poses), out, MergeConfig(), progress=False)
    las = laspy.read(out)
    return np.column_stack([las.x, las.y, las.z]), np.asarray(las.point_source_id), las


def _export(inputs, to, out, *more):
    manifest, poses = inputs
    return invoke("export", manifest, "--poses", poses, "--to", to, "--out", out, *more)


def _scans(inputs):
    manifest = load_manifest(inputs[0])
    return [(s.id, manifest.resolve(s.path)) for s in manifest.scans]


def test_matrices_reproduce_the_merged_points(inputs, merged, tmp_path):
    out = tmp_path / "matrices"
    result = _export(inputs, "matrices", out)
    assert result.exit_code == 0, result.output
    xyz, ids, _ = merged
    poses = load_poses(inputs[1])
    index = json.loads((out / "matrices.json").read_text())
    assert index["frame"] == "crs" and "UTM" in index["crs_name"]
    for k, (sid, path) in enumerate(_scans(inputs)):
        M = np.loadtxt(out / f"{sid}.txt")
        assert M.shape == (4, 4) and np.array_equal(M, poses.transform(sid))  # every digit
        posed = apply_transform(M, read_cloud(path, attributes=False).xyz)
        assert np.abs(posed - xyz[ids == k]).max() <= 0.001  # merge's 1 mm rounding
        assert index["scans"][k] == {
            "id": sid,
            "source_id": k,
            "file": str(path),
            "matrix": f"{sid}.txt",
        }


def test_pdal_pipeline_names_its_stages_in_order_with_the_poses(inputs, merged, tmp_path):
    out = tmp_path / "merge.json"
    result = _export(inputs, "pdal", out)
    assert result.exit_code == 0, result.output
    stages = json.loads(out.read_text())["pipeline"]
    scans = _scans(inputs)
    poses = load_poses(inputs[1])
    per_scan = ["readers.las", "filters.transformation", "filters.assign"]
    assert [s["type"] for s in stages] == per_scan * len(scans) + [
        "filters.merge",
        "writers.las",
    ]
    tags = [s["tag"] for s in stages]
    assert len(set(tags)) == len(tags)
    for stage in stages:  # each names only stages before it
        before = tags[: tags.index(stage["tag"])]
        assert all(i in before for i in stage.get("inputs", []))
    for k, (sid, path) in enumerate(scans):
        reader, pose, assign = stages[3 * k : 3 * k + 3]
        assert reader["filename"] == str(path.resolve())
        matrix = np.array([float(v) for v in pose["matrix"].split()]).reshape(4, 4)
        assert np.array_equal(matrix, poses.transform(sid))
        assert assign["value"] == f"PointSourceId = {k}"
    writer = stages[-1]
    header = merged[2].header
    assert writer["filename"] == str(tmp_path / "merge.laz")
    assert writer["dataformat_id"] == header.point_format.id
    assert [writer[f"offset_{a}"] for a in "xyz"] == list(header.offsets)
    assert [writer[f"scale_{a}"] for a in "xyz"] == list(header.scales)
    if shutil.which("pdal"):  # where PDAL is installed, the pipeline must rebuild the merge
        subprocess.run(["pdal", "pipeline", str(out)], check=True)
        las = laspy.read(tmp_path / "merge.laz")
        assert np.array_equal(np.sort(las.X), np.sort(merged[2].X))


def test_e57_holds_every_scan_with_its_pose(inputs, merged, tmp_path):
    out = tmp_path / "plot.e57"
    result = _export(inputs, "e57", out)
    assert result.exit_code == 0, result.output
    xyz, ids, _ = merged
    poses = load_poses(inputs[1])
    scans = _scans(inputs)
    e57 = pye57.E57(str(out))
    assert e57.scan_count == len(scans)
    for k, (sid, path) in enumerate(scans):
        header = e57.get_header(k)
        assert header["name"].value() == sid
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = header.rotation_matrix, header.translation
        assert np.abs(T - poses.transform(sid)).max() < 1e-12
        assert header.point_count == (ids == k).sum() == read_cloud(path).xyz.shape[0]
        data = e57.read_scan_raw(k)
        local = np.column_stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]])
        assert np.abs(apply_transform(T, local) - xyz[ids == k]).max() <= 0.001


def _rows(X, Y, Z, source, gps):
    rows = np.column_stack([X, Y, Z, source, gps.view(np.int64)]).astype(np.int64)
    return rows[np.lexsort(rows.T[::-1])]


def _nodes(path):
    """{key: stored records} of a COPC file, and the checks that every point lies in its node's
    cube (COPC's: centre +- halfsize of the info VLR, halved at each level)."""
    reader = copclib.FileReader(str(path))
    info, header = reader.copc_config.copc_info, reader.copc_config.las_header
    dtype = laspy.PointFormat(header.point_format_id).dtype()
    low = np.array([info.center_x, info.center_y, info.center_z]) - info.halfsize
    scale, offset = (np.array([v.x, v.y, v.z]) for v in (header.scale, header.offset))
    out = {}
    for node in reader.GetAllNodes():
        raw = np.asarray(reader.GetPointData(node)).view(dtype)
        key = (node.key.d, node.key.x, node.key.y, node.key.z)
        edge = 2 * info.halfsize / 2 ** key[0]
        xyz = np.column_stack([raw["X"], raw["Y"], raw["Z"]]) * scale + offset
        lo = low + np.array(key[1:]) * edge
        assert np.all(xyz >= lo - 1e-6) and np.all(xyz <= lo + edge + 1e-6), key
        out[key] = raw
    return out


def test_copc_holds_every_merged_point(inputs, merged, tmp_path):
    out = tmp_path / "plot.copc.laz"
    result = _export(inputs, "copc", out)
    assert result.exit_code == 0, result.output
    las = merged[2]
    with laspy.CopcReader.open(out) as reader:
        points = reader.query()
        assert list(reader.header.scales) == list(las.header.scales)
        assert list(reader.header.offsets) == list(las.header.offsets)
    assert len(points) == len(las.points)
    assert np.array_equal(
        _rows(points.X, points.Y, points.Z, points.point_source_id, np.asarray(points.gps_time)),
        _rows(las.X, las.Y, las.Z, las.point_source_id, np.asarray(las.gps_time)),
    )
    with laspy.open(out) as plain:  # the CRS is the merge's
        assert plain.header.parse_crs() == las.header.parse_crs()
    side = json.loads((tmp_path / "plot.copc.laz.json").read_text())
    assert [s["points_out"] for s in side["sources"]] == list(np.bincount(las.point_source_id))
    nodes = _nodes(out)
    assert sum(len(r) for r in nodes.values()) == len(las.points)
    for d, x, y, z in nodes:  # every node's parent is there
        assert d == 0 or (d - 1, x // 2, y // 2, z // 2) in nodes


def test_copc_streamed_regions_build_the_same_octree(inputs, tmp_path):
    """A memory budget far below the cloud streams the regions through spill files: the octree,
    node by node, is the one built in memory."""
    manifest, poses = load_manifest(inputs[0]), load_poses(inputs[1])
    trees = []
    for mb in (1, 512):
        out = tmp_path / f"{mb}.copc.laz"
        write_copc(manifest, poses, out, MergeConfig(tile_memory_mb=mb), progress=False)
        trees.append(_nodes(out))
    assert trees[0].keys() == trees[1].keys() and len(trees[0]) > 1
    for key, raw in trees[0].items():
        assert np.array_equal(raw, trees[1][key]), key
    assert not list(tmp_path.glob(".*"))  # no scratch left


def test_bad_options_and_outputs_are_one_line_errors(inputs, tmp_path):
    assert_one_line_error(_export(inputs, "las", tmp_path / "x"), "--to 'las'", "matrices")
    assert_one_line_error(
        _export(inputs, "matrices", tmp_path / "m", "--voxel", "0.1"), "--voxel", "matrices"
    )
    assert_one_line_error(_export(inputs, "e57", tmp_path / "x.laz"), ".e57")
    assert_one_line_error(_export(inputs, "copc", tmp_path / "x.laz"), ".copc.laz")
    assert_one_line_error(
        _export(inputs, "copc", tmp_path / "x.copc.laz", "--voxel", "-1"), "--voxel"
    )
    scan = _scans(inputs)[0][1]
    assert_one_line_error(
        _export(inputs, "pdal", tmp_path / "p.json", "--cloud", scan), "would replace", "scan"
    )
    assert not list(tmp_path.iterdir())  # nothing written


def test_an_earlier_export_is_replaced_only_with_force(inputs, tmp_path):
    out = tmp_path / "plot.e57"
    out.write_bytes(b"not ours")
    assert_one_line_error(_export(inputs, "e57", out), "already exists", "--force")
    assert out.read_bytes() == b"not ours"
    assert _export(inputs, "e57", out, "--force").exit_code == 0
    assert pye57.E57(str(out)).scan_count == len(_scans(inputs))
    folder = tmp_path / "m"
    folder.mkdir()
    (folder / "P1-S0.txt").write_text("mine")  # a file the user made, named as a matrix
    assert_one_line_error(_export(inputs, "matrices", folder, "--force"), "not replacing it")
    assert (folder / "P1-S0.txt").read_text() == "mine"


def test_e57_keeps_millimetres_of_a_scan_stored_in_utm(tmp_path):
    """A scan file in UTM coordinates: the E57 stores it about a whole-km origin folded into the
    pose (pye57 writes float32 points), and pose @ points gives back the merged coordinates."""
    rng = np.random.default_rng(3)
    xyz = rng.uniform([470_210, 3_810_140, 2_095], [470_250, 3_810_180, 2_125], (5_000, 3))
    write_cloud(tmp_path / "utm.laz", PointCloud(xyz))
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("z", 0.3).as_matrix()
    pose[:3, 3] = [12.5, -3.25, 0.5]
    plot = Plot(id="P1", crs="EPSG:26912", scans=[Scan(id="utm", path=Path("utm.laz"))])
    (tmp_path / "m.toml").write_text(dump_manifest(Manifest(plots=[plot])))
    Poses({"utm": ScanPose(pose, plot="P1")}, frame="crs").save(tmp_path / "p.json")
    out = tmp_path / "utm.e57"
    result = _export((tmp_path / "m.toml", tmp_path / "p.json"), "e57", out)
    assert result.exit_code == 0, result.output
    e57 = pye57.E57(str(out))
    header, data = e57.get_header(0), e57.read_scan_raw(0)
    local = np.column_stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]])
    assert np.abs(local).max() < 1000  # about the origin, not at UTM magnitudes
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = header.rotation_matrix, header.translation
    stored = read_cloud(tmp_path / "utm.laz").xyz
    assert np.abs(apply_transform(T, local) - apply_transform(pose, stored)).max() < 0.0005


def test_scans_in_an_e57_project_export_to_e57_but_not_to_pdal(tmp_path):
    rng = np.random.default_rng(5)
    clouds = [rng.uniform(-20, 20, (3_000, 3)) for _ in range(2)]
    write_e57(
        tmp_path / "plot.e57", [(f"s{k}", xyz, np.eye(4), {}) for k, xyz in enumerate(clouds)]
    )
    scans = [Scan(id=f"s{k}", path=Path("plot.e57"), scan=k) for k in range(2)]
    (tmp_path / "m.toml").write_text(dump_manifest(Manifest(plots=[Plot(id="P1", scans=scans)])))
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 2.0, 3.0]
    Poses({"s0": ScanPose(np.eye(4)), "s1": ScanPose(pose)}).save(tmp_path / "p.json")
    inputs = (tmp_path / "m.toml", tmp_path / "p.json")
    assert_one_line_error(_export(inputs, "pdal", tmp_path / "x.json"), "plot.e57", "E57")
    result = _export(inputs, "e57", tmp_path / "out.e57")
    assert result.exit_code == 0, result.output
    e57 = pye57.E57(str(tmp_path / "out.e57"))
    assert e57.scan_count == 2 and np.allclose(e57.get_header(1).translation, [1, 2, 3])
    data = e57.read_scan_raw(1)
    assert np.abs(data["cartesianX"] - clouds[1][:, 0]).max() < 1e-5
