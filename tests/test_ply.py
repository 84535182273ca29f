"""PLY input (plyfile): ASCII and binary round trips keep float64 coordinates and the attributes."""

import numpy as np
import pytest
from helpers import assert_one_line_error, invoke

from plotmosaic.io.las import iter_chunks, open_las, read_cloud, read_header_info


def write_ply(path, n=1000, text=False, intensity="f8", colour="u1", extra=True):
    from plyfile import PlyData, PlyElement

    fields = [("x", "f8"), ("y", "f8"), ("z", "f8")]
    fields += [("intensity", intensity)] if intensity else []
    fields += [("red", colour), ("green", colour), ("blue", colour)] if colour else []
    fields += [("nx", "f4"), ("ny", "f4"), ("nz", "f4"), ("label", "i4")] if extra else []
    v = np.zeros(n, dtype=fields)
    rng = np.random.default_rng(3)
    for c in "xyz":  # UTM-sized values: float32 would lose the millimetres
        v[c] = (
            rng.uniform(-20, 20, n) + {"x": 447_123.456789, "y": 3_897_654.321098, "z": 2_301.5}[c]
        )
    if intensity:
        v["intensity"] = rng.uniform(0, 3000, n) if intensity == "f8" else rng.integers(0, 65535, n)
    if colour:
        for c in ("red", "green", "blue"):
            v[c] = rng.integers(0, 255, n)
    if extra:
        v["nx"], v["ny"], v["nz"] = 0.0, 0.6, 0.8
        v["label"] = rng.integers(0, 9, n)
    PlyData([PlyElement.describe(v, "vertex")], text=text).write(str(path))
    return v


@pytest.mark.parametrize("text", [False, True], ids=["binary", "ascii"])
def test_round_trip_keeps_float64_and_attributes(tmp_path, text):
    path = tmp_path / "c.ply"
    v = write_ply(path, text=text)
    cloud = read_cloud(path)
    assert cloud.xyz.dtype == np.float64
    np.testing.assert_array_equal(cloud.xyz, np.column_stack([v["x"], v["y"], v["z"]]))
    np.testing.assert_array_equal(
        cloud.attrs["intensity_raw"], v["intensity"]
    )  # float64 kept as it is
    assert cloud.attrs["intensity_raw"].dtype == np.float64
    lo, hi = v["intensity"].min(), v["intensity"].max()
    np.testing.assert_array_equal(
        cloud.attrs["intensity"],
        np.rint((v["intensity"] - lo) * 65535 / (hi - lo)).astype(np.uint16),
    )
    for c in ("red", "green", "blue"):  # LAS colour is 16-bit: 8-bit values stretched by 257
        np.testing.assert_array_equal(cloud.attrs[c], v[c].astype(np.uint16) * 257)
    for ply, las in (("nx", "normal_x"), ("ny", "normal_y"), ("nz", "normal_z")):
        np.testing.assert_array_equal(cloud.attrs[las], v[ply])
    np.testing.assert_array_equal(cloud.attrs["label"], v["label"])
    assert cloud.attrs["label"].dtype == np.int32


def test_integer_intensity_exact_chunks_and_merge_view(tmp_path):
    path = tmp_path / "c.ply"
    v = write_ply(path, n=2500, intensity="u2", colour="u2", extra=False)
    chunks = list(iter_chunks(path, chunk_size=1000))
    assert [len(c) for c in chunks] == [1000, 1000, 500]
    cloud = read_cloud(path)
    assert "intensity_raw" not in cloud.attrs
    np.testing.assert_array_equal(cloud.attrs["intensity"], v["intensity"])
    np.testing.assert_array_equal(cloud.attrs["red"], v["red"])
    info = read_header_info(path)
    assert info.point_count == 2500 and set(info.dimensions) >= {
        "intensity",
        "red",
        "green",
        "blue",
    }
    np.testing.assert_allclose(info.mins, cloud.xyz.min(axis=0))
    with open_las(path) as reader:  # what merge reads: LAS records at 0.1 mm
        xyz = np.vstack([np.column_stack([r.x, r.y, r.z]) for r in reader.chunk_iterator(1000)])
    assert np.abs(xyz - cloud.xyz).max() <= 5e-5 + 1e-9


def test_info_and_bad_files(tmp_path):
    path = tmp_path / "ok.ply"
    write_ply(path, n=10)
    result = invoke("info", path)
    assert result.exit_code == 0 and "10 points, PLY" in result.output, result.output
    (tmp_path / "junk.ply").write_text("not a ply file\n")
    assert_one_line_error(invoke("info", tmp_path / "junk.ply"), "junk.ply", "not a readable PLY")
    good = (tmp_path / "ok.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(good[: len(good) - 100])
    assert_one_line_error(invoke("info", "--full", tmp_path / "cut.ply"), "cut.ply")
    write_ply(tmp_path / "empty.ply", n=0)
    assert_one_line_error(invoke("info", tmp_path / "empty.ply"), "empty.ply", "no points")
