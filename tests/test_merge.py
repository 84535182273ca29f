"""`plotmosaic merge`: posed scans streamed into one georeferenced LAS 1.4 file."""

import json

import laspy
import numpy as np
import pytest
from builders import MERGE_CRS, MERGE_SCAN_POINTS, merge_site, run_merge
from helpers import assert_one_line_error, invoke
from pyproj import CRS

import plotmosaic.stages.merge as merge_module
from plotmosaic.config.merge import MergeConfig
from plotmosaic.errors import InputError
from plotmosaic.io import write_cloud
from plotmosaic.io.frame import apply_transform
from plotmosaic.io.las import read_cloud
from plotmosaic.manifest import load_manifest
from plotmosaic.poses import Poses, load_poses
from plotmosaic.stages.merge import merge_scans, read_source_table

N, UTM = MERGE_SCAN_POINTS, MERGE_CRS
ATTRS = (
    "intensity",
    "return_number",
    "number_of_returns",
    "classification",
    "gps_time",
    "red",
    "green",
    "blue",
    "label",
)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    return merge_site(tmp_path_factory.mktemp("merge_site"))


def _expected(site, ids=("a", "b", "c")):
    poses = load_poses(site / "poses.json")
    clouds = {sid: read_cloud(site / f"{sid}.laz") for sid in ids}
    return {sid: apply_transform(poses.transform(sid), c.xyz) for sid, c in clouds.items()}, clouds


def _run(*args):
    return invoke("merge", *args)


_one_line_error = assert_one_line_error


def test_merge_equals_posed_inputs(site, tmp_path):
    out = tmp_path / "merged.laz"
    result = _run(site / "manifest.toml", "--poses", site / "poses.json", "--out", out)
    assert result.exit_code == 0, result.output
    assert "WGS 84 / UTM zone 12N" in result.output and "60,000" in result.output

    las = laspy.read(out)
    assert str(las.header.version) == "1.4" and las.header.point_format.id == 7
    assert np.allclose(las.header.scales, 0.001) and np.all(las.header.offsets % 1000 == 0)
    assert len(las.points) == 3 * N
    expected, clouds = _expected(site)
    xyz = np.column_stack([las.x, las.y, las.z])
    for index, sid in enumerate(["a", "b", "c"]):
        part = slice(index * N, (index + 1) * N)  # scans in manifest order, points in file order
        assert np.all(las.point_source_id[part] == index)
        assert np.abs(xyz[part] - expected[sid]).max() < 0.001
        for name in ATTRS:
            want = clouds[sid].attrs.get(name, np.zeros(N))  # scan c has no RGB and no label: zero
            assert np.array_equal(np.asarray(las[name][part]), want), name
    assert CRS.from_wkt(las.header.parse_crs().to_wkt()) == CRS.from_user_input(UTM)

    table = read_source_table(out)
    assert [(t["source_id"], t["id"]) for t in table] == [(0, "a"), (1, "b"), (2, "c")]
    side = json.loads((tmp_path / "merged.laz.json").read_text())
    assert [(s["id"], s["points_in"], s["points_out"]) for s in side["sources"]] == [
        (sid, N, N) for sid in "abc"
    ]
    assert side["poses"].endswith("poses.json") and CRS.from_wkt(
        side["crs"]
    ) == CRS.from_user_input(UTM)
    assert np.allclose(side["bounds"]["min"], xyz.min(axis=0), atol=0.001)


def _read(path):
    las = laspy.read(path)
    return np.column_stack([las.X, las.Y, las.Z]), np.asarray(las.point_source_id), las.header


def test_voxel_thinning_is_deterministic_and_one_point_per_voxel(site, tmp_path):
    full, full_ids, header = _read(run_merge(site, tmp_path / "full.laz").out)
    step = 2000  # 2 m in mm units
    runs = [
        _read(run_merge(site, tmp_path / f"v{c}.laz", voxel=2.0, chunk_size=c).out)
        for c in (3_000, 7_777, 1_000_000)
    ]
    ints, ids, h = runs[0]
    for other_ints, other_ids, _ in runs[1:]:  # independent of the chunk size
        assert np.array_equal(ints, other_ints) and np.array_equal(ids, other_ids)
    assert np.array_equal(h.offsets, header.offsets)
    keys = [tuple(v) for v in ints // step]
    assert len(set(keys)) == len(keys)  # at most one point per voxel
    assert len(keys) == len({tuple(v) for v in full // step})  # and every occupied voxel kept
    assert len(ints) < 0.8 * len(full)
    # each kept point is the first point of its voxel in scan order
    _, first = np.unique(full // step, axis=0, return_index=True)
    assert np.array_equal(ints, full[np.sort(first)]) and np.array_equal(
        ids, full_ids[np.sort(first)]
    )


def test_bbox_crop_and_als(site, tmp_path):
    full = laspy.read(run_merge(site, tmp_path / "full.laz").out)
    fullxyz = np.column_stack([full.x, full.y, full.z])
    bbox = (470_000.0, 3_810_000.0, 470_025.0, 3_810_030.0, 2_095.0, 2_110.0)
    lo, hi = np.array([bbox[0], bbox[1], bbox[4]]), np.array([bbox[2], bbox[3], bbox[5]])
    summary = run_merge(site, tmp_path / "crop.laz", bbox=bbox)
    inside = np.all(
        (fullxyz >= lo) & (fullxyz <= hi), axis=1
    )  # the crop applies to the written coordinates
    las = laspy.read(summary.out)
    assert len(las.points) == inside.sum() == summary.points_out and 0 < inside.sum() < len(inside)
    assert np.array_equal(np.column_stack([las.x, las.y, las.z]), fullxyz[inside])
    assert np.array_equal(las.point_source_id, full.point_source_id[inside])

    summary = run_merge(site, tmp_path / "als.laz", include_als=True)
    las = laspy.read(summary.out)
    als = read_cloud(site / "als.laz")
    part = las.point_source_id == 3  # ALS after the three scans
    assert part.sum() == len(als) and summary.sources[-1].kind == "als"
    assert np.abs(np.column_stack([las.x, las.y, las.z])[part] - als.xyz).max() < 0.001
    assert np.all(las.classification[part] == 2)
    assert np.array_equal(las.intensity[part], als.attrs["intensity"])


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_failure_mid_write_leaves_earlier_output(site, tmp_path, monkeypatch, error):
    out = tmp_path / "merged.laz"
    run_merge(site, out)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    real, calls = merge_module.write_chunk, []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) > 1:
            raise error("disk on fire")
        return real(*args, **kwargs)

    monkeypatch.setattr(merge_module, "write_chunk", failing)
    with pytest.raises(error):
        run_merge(site, out, chunk_size=5_000)
    assert len(calls) == 2
    assert {
        p.name: p.read_bytes() for p in tmp_path.iterdir()
    } == before  # no temp file, same bytes

    fresh = tmp_path / "fresh" / "new.laz"
    calls.clear()
    with pytest.raises(error):
        run_merge(site, fresh, chunk_size=5_000)
    assert list(fresh.parent.iterdir()) == []


def test_refuses_to_overwrite_without_force(site, tmp_path):
    out = tmp_path / "merged.laz"
    out.write_bytes(b"keep me")
    args = [site / "manifest.toml", "--poses", site / "poses.json", "--out", out]
    _one_line_error(_run(*args), "merged.laz", "--force")
    assert out.read_bytes() == b"keep me"
    assert _run(*args, "--force").exit_code == 0
    assert len(laspy.read(out).points) == 3 * N


def test_missing_pose_and_ignored_pose(site, tmp_path):
    poses = load_poses(site / "poses.json")
    poses.scans["zz"] = poses.scans.pop("b")
    poses.save(tmp_path / "poses.json")
    args = [site / "manifest.toml", "--poses", tmp_path / "poses.json", "--out", tmp_path / "m.laz"]
    _one_line_error(_run(*args), "'b'", "--skip-missing")
    assert not (tmp_path / "m.laz").exists()
    result = _run(*args, "--skip-missing")
    assert result.exit_code == 0, result.output
    assert "left out (no pose): b" in result.output and "zz" in result.output
    las = laspy.read(tmp_path / "m.laz")
    assert sorted(set(las.point_source_id)) == [0, 2]  # c keeps its manifest index


def test_plot_frame_without_crs(site, tmp_path):
    poses = load_poses(site / "poses.json")
    Poses(poses.scans, frame="plot").save(tmp_path / "poses.json")
    manifest = load_manifest(site / "manifest.toml")
    # the plot's CRS from the manifest is used when the poses carry none
    summary = merge_scans(
        manifest, load_poses(tmp_path / "poses.json"), tmp_path / "m.laz", progress=False
    )
    assert summary.crs_source.startswith("manifest") and CRS.from_wkt(
        summary.crs
    ) == CRS.from_user_input(UTM)
    with pytest.raises(InputError, match="--include-als"):
        merge_scans(
            manifest,
            load_poses(tmp_path / "poses.json"),
            tmp_path / "x.laz",
            MergeConfig(include_als=True),
            progress=False,
        )
    bare = manifest.model_copy(
        update={"plots": [manifest.plots[0].model_copy(update={"crs": None})]}
    )
    summary = merge_scans(
        bare, load_poses(tmp_path / "poses.json"), tmp_path / "n.laz", progress=False
    )
    assert summary.crs is None and laspy.read(tmp_path / "n.laz").header.parse_crs() is None


def test_bad_options_are_one_line_errors(site, tmp_path):
    base = [site / "manifest.toml", "--poses", site / "poses.json"]
    _one_line_error(_run(*base, "--out", tmp_path / "m.laz", "--bbox", "1,2,3"), "--bbox")
    _one_line_error(_run(*base, "--out", tmp_path / "m.laz", "--bbox", "5,2,3,4"), "--bbox")
    _one_line_error(_run(*base, "--out", tmp_path / "m.laz", "--bbox", "a,b,c,d"), "--bbox")
    _one_line_error(
        _run(*base, "--out", tmp_path / "m.laz", "--bbox", "0,0,1,1"), "--bbox", "does not overlap"
    )
    _one_line_error(_run(*base, "--out", tmp_path / "m.laz", "--voxel", "0"), "--voxel")
    _one_line_error(_run(*base, "--out", tmp_path / "m.txt"), "m.txt", ".laz")
    (tmp_path / "afile").write_text("not a folder")
    _one_line_error(_run(*base, "--out", tmp_path / "afile" / "m.laz"), "afile")
    _one_line_error(
        _run(*base[:2], tmp_path / "nope.json", "--out", tmp_path / "m.laz"), "nope.json"
    )
    assert not (tmp_path / "m.laz").exists()


def test_truncated_scan_is_named_and_leaves_nothing(site, tmp_path):
    for name in ("a.laz", "b.laz", "c.laz", "als.laz", "manifest.toml", "poses.json"):
        (tmp_path / name).write_bytes((site / name).read_bytes())
    data = (site / "b.laz").read_bytes()
    (tmp_path / "b.laz").write_bytes(data[: len(data) // 2])
    _one_line_error(
        _run(
            tmp_path / "manifest.toml",
            "--poses",
            tmp_path / "poses.json",
            "--out",
            tmp_path / "out" / "m.laz",
        ),
        "b.laz",
        "truncated",
    )
    assert not (tmp_path / "out").exists()  # the folder the run made is gone with it


def test_als_tile_in_another_crs_is_refused(site, tmp_path):
    for name in ("a.laz", "b.laz", "c.laz", "manifest.toml", "poses.json"):
        (tmp_path / name).write_bytes((site / name).read_bytes())
    write_cloud(tmp_path / "als.laz", read_cloud(site / "als.laz"), crs=CRS.from_epsg(32613))
    manifest, poses = load_manifest(tmp_path / "manifest.toml"), load_poses(tmp_path / "poses.json")
    with pytest.raises(InputError, match="als.laz: ALS tile is in WGS 84 / UTM zone 13N"):
        merge_scans(
            manifest, poses, tmp_path / "m.laz", MergeConfig(include_als=True), progress=False
        )
    assert not (tmp_path / "m.laz").exists()
