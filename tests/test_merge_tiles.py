"""`plotmosaic merge` thinning by tiles and `--tiles` output: the same points as the whole cloud."""

import json

import laspy
import numpy as np
import pytest
from builders import MERGE_SCAN_POINTS, merge_site, run_merge
from helpers import assert_one_line_error, invoke

import plotmosaic.stages.merge as merge_module
from plotmosaic.stages.merge import read_source_table

N = MERGE_SCAN_POINTS
_one_line_error = assert_one_line_error


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    return merge_site(tmp_path_factory.mktemp("merge_site"))


def _run(*args):
    return invoke("merge", *args)


def _first_per_voxel(ints: np.ndarray, step: int) -> np.ndarray:
    """Reference: indices of the first point (in stream order) of each voxel of the whole cloud."""
    _, first = np.unique(ints // step, axis=0, return_index=True)
    return np.sort(first)


def _rows(las) -> np.ndarray:
    """Every point as one sortable row (coordinates, source, time): compares clouds as sets."""
    rows = np.column_stack(
        [las.X, las.Y, las.Z, las.point_source_id, np.asarray(las.gps_time).view(np.int64)]
    )
    return rows[np.lexsort(rows.T[::-1])]


def test_first_in_voxel_packed_and_wide_paths_agree():
    rng = np.random.default_rng(3)
    ijk = rng.integers(0, 40, (5_000, 3))
    want = np.sort(np.unique(ijk, axis=0, return_index=True)[1])
    assert np.array_equal(merge_module.first_in_voxel(ijk), want)
    wide = ijk.copy()
    wide[wide[:, 0] == 7, 2] += (
        1 << 62
    )  # span too wide to pack: the lexsort path must give the same choice
    assert np.array_equal(
        merge_module.first_in_voxel(wide), np.sort(np.unique(wide, axis=0, return_index=True)[1])
    )


def test_tiled_thinning_equals_whole_cloud_thinning(site, tmp_path, monkeypatch):
    full = laspy.read(run_merge(site, tmp_path / "full.laz").out)
    ints = np.column_stack([full.X, full.Y, full.Z])
    step = 300  # 0.3 m
    want = _first_per_voxel(ints, step)
    one_tile = laspy.read(
        run_merge(site, tmp_path / "one.laz", voxel=0.3).out
    )  # fits the default budget
    assert np.array_equal(
        np.column_stack([one_tile.X, one_tile.Y, one_tile.Z]), ints[want]
    )  # stream order
    assert np.array_equal(one_tile.point_source_id, full.point_source_id[want])

    sub = laspy.ScaleAwarePointRecord(
        full.points.array[want], full.header.point_format, full.header.scales, full.header.offsets
    )
    real_split, splits = merge_module._split, []
    monkeypatch.setattr(merge_module, "_split", lambda *a: splits.append(1) or real_split(*a))
    for name in (
        "grid",
        "cut",
    ):  # many tiles from the start; one tile cut again and again to fit the budget
        if name == "cut":
            monkeypatch.setattr(merge_module, "auto_tile_edge", lambda *a: 1 << 40)
        summary = run_merge(
            site, tmp_path / f"{name}.laz", voxel=0.3, tile_memory_mb=1, chunk_size=7_777
        )  # ~7k points a tile
        tiled = laspy.read(summary.out)
        assert np.array_equal(
            _rows(tiled), _rows(laspy.LasData(full.header, sub))
        )  # the same winners, tile by tile
        assert summary.points_out == len(want) == len(tiled.points)
        assert [s.points_out for s in summary.sources] == list(
            np.bincount(full.point_source_id[want], minlength=3)[:3]
        )
    assert len(splits) > 3  # the budget forced the single tile to be cut
    assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]  # spill folder removed


def test_tiled_output_covers_every_point_once(site, tmp_path):
    full = laspy.read(run_merge(site, tmp_path / "full.laz").out)
    result = _run(
        site / "manifest.toml",
        "--poses",
        site / "poses.json",
        "--out",
        tmp_path / "tiles",
        "--tiles",
        "--tile-size",
        "10",
    )
    assert result.exit_code == 0, result.output
    index = json.loads((tmp_path / "tiles" / "index.json").read_text())
    files = sorted(p.name for p in (tmp_path / "tiles").glob("*.laz"))
    assert files == sorted(t["file"] for t in index["tiles"]) and len(files) > 4
    parts = []
    for tile in index["tiles"]:
        las = laspy.read(tmp_path / "tiles" / tile["file"])
        assert tile["file"] == f"tile_{tile['origin'][0]:.0f}_{tile['origin'][1]:.0f}.laz" and tile[
            "points"
        ] == len(las.points)
        assert np.all(
            (las.x >= tile["origin"][0]) & (las.x < tile["origin"][0] + 10)
        )  # each point in its own tile
        assert np.all((las.y >= tile["origin"][1]) & (las.y < tile["origin"][1] + 10))
        assert (
            las.header.parse_crs() is not None
            and read_source_table(tmp_path / "tiles" / tile["file"])[0]["id"] == "a"
        )
        parts.append(np.asarray(las.points.array))
    merged = laspy.ScaleAwarePointRecord(
        np.concatenate(parts), full.header.point_format, full.header.scales, full.header.offsets
    )
    assert np.array_equal(
        _rows(laspy.LasData(full.header, merged)), _rows(full)
    )  # every point exactly once
    assert index["points_out"] == 3 * N and [s["points_out"] for s in index["sources"]] == [N, N, N]

    # with thinning, the tiles together are the whole-cloud thinning; --force replaces the folder
    result = _run(
        site / "manifest.toml",
        "--poses",
        site / "poses.json",
        "--out",
        tmp_path / "tiles",
        "--tiles",
        "--tile-size",
        "10",
        "--voxel",
        "0.5",
        "--force",
    )
    assert result.exit_code == 0, result.output
    kept = sum(len(laspy.read(p).points) for p in (tmp_path / "tiles").glob("*.laz"))
    assert kept == len(_first_per_voxel(np.column_stack([full.X, full.Y, full.Z]), 500))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["full.laz", "full.laz.json", "tiles"]


def test_tile_options_are_checked(site, tmp_path):
    base = [site / "manifest.toml", "--poses", site / "poses.json", "--tiles"]
    _one_line_error(
        _run(*base, "--out", tmp_path / "t", "--tile-size", "10", "--voxel", "0.3"),
        "--tile-size 10",
        "--voxel 0.3",
    )
    _one_line_error(_run(*base, "--out", tmp_path / "t", "--tile-size", "0"), "--tile-size")
    _one_line_error(_run(*base, "--out", tmp_path / "t", "--memory-mb", "0"), "--memory-mb")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    _one_line_error(_run(*base, "--out", tmp_path / "mine", "--force"), "mine", "not a tile folder")
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep" and not (tmp_path / "t").exists()


def test_stable_order_packed_and_fallback_agree():
    keys = np.random.default_rng(1).integers(0, 50, 10_000)
    want = np.argsort(keys, kind="stable")
    assert np.array_equal(merge_module.stable_order(keys, 6), want)
    assert np.array_equal(
        merge_module.stable_order(keys, 60), want
    )  # too wide to pack with the index
