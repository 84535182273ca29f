"""LAS/LAZ I/O: UTM precision, CRS, attributes, chunking, real clips."""

import laspy
import numpy as np
import pytest
from pyproj import CRS

from plotmosaic.io import Frame, PointCloud, iter_chunks, read_cloud, write_cloud
from plotmosaic.io.frame import apply_transform, to_global_transform, to_local_transform


def utm_cloud(n=50_000, seed=0):
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(0, 60, (n, 3)) + [470123.4567, 3810987.6543, 2101.2345]
    attrs = {
        "intensity": rng.integers(0, 65535, n).astype(np.uint16),
        "return_number": rng.integers(1, 4, n).astype(np.uint8),
        "number_of_returns": np.full(n, 3, np.uint8),
        "classification": rng.integers(0, 6, n).astype(np.uint8),
        "gps_time": rng.uniform(1e8, 2e8, n),
        "red": rng.integers(0, 65535, n).astype(np.uint16),
        "green": rng.integers(0, 65535, n).astype(np.uint16),
        "blue": rng.integers(0, 65535, n).astype(np.uint16),
        "label": rng.integers(0, 4, n).astype(np.uint8),
    }
    return PointCloud(xyz, attrs)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_utm_round_trip_keeps_millimetres(tmp_path, suffix):
    cloud = utm_cloud()
    path = write_cloud(tmp_path / f"utm{suffix}", cloud, crs="EPSG:26912")
    back = read_cloud(path)
    assert len(back) == len(cloud)
    assert np.abs(back.xyz - cloud.xyz).max() <= 0.0005 + 1e-9  # 1 mm scale => half-mm rounding
    for name, values in cloud.attrs.items():
        np.testing.assert_array_equal(back.attrs[name], values, err_msg=name)


def test_crs_round_trip(tmp_path):
    crs = CRS.from_epsg(26912)
    path = write_cloud(tmp_path / "crs.laz", utm_cloud(1000), crs=crs)
    back = read_cloud(path)
    assert back.crs is not None and back.crs.to_epsg() == 26912
    assert back.crs.equals(crs)


def test_chunked_reading_equals_whole_read(tmp_path):
    cloud = utm_cloud(12_345)
    path = write_cloud(tmp_path / "c.laz", cloud)
    chunks = list(iter_chunks(path, chunk_size=1000, attributes=["intensity"]))
    assert len(chunks) == 13
    xyz = np.vstack([c.xyz for c in chunks])
    np.testing.assert_allclose(xyz, read_cloud(path).xyz, atol=0)
    assert list(chunks[0].attrs) == ["intensity"]


def test_frame_transforms_are_exact_in_file_coordinates():
    rng = np.random.default_rng(1)
    xyz = rng.uniform(0, 50, (100, 3)) + [470000.0, 3810000.0, 2100.0]
    src, tgt = Frame.around(xyz), Frame.around(xyz + 7.0)
    assert np.all(np.abs(src.to_local(xyz)) < 60)
    c, s = np.cos(0.3), np.sin(0.3)
    T_local = np.array([[c, -s, 0, 1.5], [s, c, 0, -2.0], [0, 0, 1, 0.25], [0, 0, 0, 1]])
    T_file = to_global_transform(T_local, src, tgt)
    expected = tgt.to_global(apply_transform(T_local, src.to_local(xyz)))
    np.testing.assert_allclose(apply_transform(T_file, xyz), expected, atol=1e-6)
    np.testing.assert_allclose(to_local_transform(T_file, src, tgt), T_local, atol=1e-9)


EXPECTED_CLIPS = {"ALS_Clip.laz": 29_915, "UAS_Clip.laz": 390_877, "MLS_Clip.laz": 301_477}


@pytest.mark.parametrize("name", sorted(EXPECTED_CLIPS))
def test_real_clips_read_correctly(spanner_dir, name):
    cloud = read_cloud(spanner_dir / name)
    assert len(cloud) == EXPECTED_CLIPS[name]
    assert cloud.xyz.dtype == np.float64
    lo, hi = cloud.xyz.min(axis=0), cloud.xyz.max(axis=0)
    assert 470_600 < lo[0] < hi[0] < 470_700 and 3_810_200 < lo[1] < hi[1] < 3_810_300
    assert 2_250 < lo[2] < hi[2] < 2_350
    assert {"intensity", "return_number", "gps_time", "classification"} <= set(cloud.attrs)
    # exactly the file's integers times scale plus offset, in float64 (no float32 anywhere)
    las = laspy.read(spanner_dir / name)
    for axis, name_ in enumerate("xyz"):
        np.testing.assert_array_equal(cloud.xyz[:, axis], np.asarray(las[name_], dtype=np.float64))
    if name != "MLS_Clip.laz":  # the MLS clip carries no CRS VLR
        assert cloud.crs is not None and "UTM zone 12N" in cloud.crs.name
    else:
        assert {"red", "green", "blue"} <= set(cloud.attrs)


def test_unknown_suffix_names_the_formats(tmp_path):
    from helpers import assert_one_line_error, invoke

    (tmp_path / "cloud.xyz").write_text("1 2 3\n")
    assert_one_line_error(
        invoke("info", tmp_path / "cloud.xyz"), "cloud.xyz", ".las, .laz, .e57 or .ply"
    )
