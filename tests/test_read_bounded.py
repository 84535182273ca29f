"""Reading a scan for registration within `[read] max_points_in_memory` (io/bounded.py)."""

import tracemalloc

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from plotmosaic.align.pipeline import AlignRequest, align_clouds
from plotmosaic.config.align import AlignConfig
from plotmosaic.config.reading import ReadingConfig
from plotmosaic.config.settings import SettingsError, settings_from_dict
from plotmosaic.errors import InputError
from plotmosaic.graph.prepared import PrepareJob, get_prepared, points_reader, prepared_key
from plotmosaic.io.bounded import read_bounded, read_thinned
from plotmosaic.io.las import PointCloud, read_cloud, read_header_info, write_cloud
from plotmosaic.poses import load_poses

N = 1_000_000
BUDGET = 200_000
CELL = 0.0125


@pytest.fixture(scope="module")
def big_scan(tmp_path_factory):
    """A scan-like LAZ of N points at UTM coordinates: ground crowding 1/r^2 around the scanner, stems."""
    rng = np.random.default_rng(3)
    n_ground = N * 3 // 4
    r = np.exp(rng.uniform(np.log(0.5), np.log(40.0), n_ground))
    a = rng.uniform(0, 2 * np.pi, n_ground)
    ground = np.c_[r * np.cos(a), r * np.sin(a), 0.02 * rng.standard_normal(n_ground) - 1.6]
    n_stem = N - n_ground
    centres = rng.uniform(-30, 30, (40, 2))[rng.integers(0, 40, n_stem)]
    b = rng.uniform(0, 2 * np.pi, n_stem)
    stems = np.c_[centres + 0.2 * np.c_[np.cos(b), np.sin(b)], rng.uniform(-1.6, 15, n_stem)]
    xyz = np.vstack([ground, stems])[rng.permutation(N)] + [470123.0, 3810456.0, 2100.0]
    return write_cloud(tmp_path_factory.mktemp("big") / "scan.laz", PointCloud(xyz))


def first_per_cell(xyz, origin, first_cell, cell):
    """Reference: the first point (file order) of each `cell` cube of the grid nested in first_cell's."""
    level = int(round(np.log2(cell / first_cell)))
    idx = np.floor((xyz - origin) / first_cell).astype(np.int64) >> level
    _, first = np.unique(idx, axis=0, return_index=True)
    return xyz[np.sort(first)]


def test_a_scan_over_the_budget_is_thinned_to_a_bounded_cloud(big_scan):
    thinned = read_thinned(big_scan, BUDGET, CELL)
    assert thinned.points_read == N
    assert 0 < len(thinned.cloud) <= BUDGET
    assert thinned.cell > CELL  # the 1.25 cm grid holds more than the budget: coarsened
    full = read_cloud(big_scan, attributes=False).xyz
    expected = first_per_cell(full, thinned.origin, CELL, thinned.cell)
    np.testing.assert_array_equal(thinned.cloud.xyz, expected)  # points of the file, bit for bit
    # the extent stays: each extreme point's cell keeps a point
    lo, hi = full.min(axis=0), full.max(axis=0)
    assert np.all(thinned.cloud.xyz.min(axis=0) - lo <= thinned.cell)
    assert np.all(hi - thinned.cloud.xyz.max(axis=0) <= thinned.cell)


def test_thinning_is_deterministic_and_needs_a_fraction_of_the_whole_cloud(big_scan):
    tracemalloc.start()
    try:
        thinned = read_thinned(big_scan, BUDGET, CELL)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    # the whole float64 cloud alone would be N x 24 bytes; the kept rows, one chunk and the work
    # arrays of the cell keys stay within a few times the budget's float64 size, whatever N
    assert peak < min(N, 4 * BUDGET) * 24, peak
    again = read_thinned(big_scan, BUDGET, CELL)
    np.testing.assert_array_equal(thinned.cloud.xyz, again.cloud.xyz)


def test_a_scan_within_the_budget_is_read_whole_and_silently(big_scan, capsys):
    within = read_bounded(big_scan, ReadingConfig(max_points_in_memory=N), 0.025)
    np.testing.assert_array_equal(within.xyz, read_cloud(big_scan, attributes=False).xyz)
    assert capsys.readouterr().err == ""
    over = read_bounded(big_scan, ReadingConfig(max_points_in_memory=BUDGET), 0.025)
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "thinned on reading to" in lines[0], lines
    assert f"{len(over):,} points" in lines[0]


def test_the_budget_is_in_the_cache_key_only_of_a_scan_it_thins(big_scan):
    config = AlignConfig()

    def key(budget):
        return prepared_key(
            big_scan, "tls", 3, config, 0, ReadingConfig(max_points_in_memory=budget)
        )

    assert key(N) == key(2 * N) == prepared_key(big_scan, "tls", 3, config, 0)
    assert key(BUDGET) != key(N)
    assert key(BUDGET) != key(BUDGET // 2)


def test_the_budget_is_a_bounded_setting():
    settings = settings_from_dict({"read": {"max_points_in_memory": 5_000_000}})
    assert settings.read.max_points_in_memory == 5_000_000
    with pytest.raises(SettingsError, match="read.max_points_in_memory"):
        settings_from_dict({"read": {"max_points_in_memory": 5}})
    with pytest.raises(SettingsError, match="read.cell_share"):
        settings_from_dict({"read": {"cell_share": 2.0}})


@pytest.mark.slow
def test_thinned_scans_still_align(small_sim):
    """Both scans of a pair held to 30k points (coarsened far past 1.25 cm): still on the truth."""
    truth = load_poses(small_sim.ground_truth_path)
    src = read_thinned(small_sim.scan_paths["P1-S1"], 30_000, CELL).cloud
    tgt = read_thinned(small_sim.scan_paths["P1-S0"], 30_000, CELL).cloud
    assert len(src) <= 30_000 and len(tgt) <= 30_000
    result = align_clouds(src, tgt, AlignRequest(source_kind="tls", target_kind="tls", seed=0))
    T_true = np.linalg.inv(truth.transform("P1-S0")) @ truth.transform("P1-S1")
    D = np.linalg.inv(T_true) @ result.transform
    centre = src.xyz.mean(axis=0)
    moved = D[:3, :3] @ centre + D[:3, 3] - centre
    angle = np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))
    assert np.abs(moved).max() < 0.02 and angle < 0.12, (moved, angle)


def test_a_prepare_job_reads_its_scan_within_its_budget(small_sim, tmp_path, capsys):
    path = str(small_sim.scan_paths["P1-S0"])
    config = AlignConfig()
    reading = ReadingConfig(max_points_in_memory=20_000)
    key = prepared_key(path, "tls", 3, config, 0, reading)
    job = PrepareJob(key, "P1-S0", path, "tls", 3, config, 0, str(tmp_path), reading=reading)
    cloud, _ = get_prepared(job)
    assert cloud.input_points <= 20_000 < read_header_info(path).point_count
    assert "thinned on reading" in capsys.readouterr().err


def test_a_ply_over_the_budget_streams_and_refuses_bad_coordinates(tmp_path):
    rng = np.random.default_rng(5)
    xyz = rng.uniform(0, 20, (30_000, 3))
    xyz[[10, 20_000, 29_999]] = np.nan
    vertex = np.empty(len(xyz), dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    vertex["x"], vertex["y"], vertex["z"] = xyz.T
    path = tmp_path / "bad.ply"
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(path))
    with pytest.raises(InputError, match="3 points have NaN or infinite coordinates"):
        read_thinned(path, 10_000, CELL)
    vertex["x"][[10, 20_000, 29_999]] = 1.0
    vertex["y"][[10, 20_000, 29_999]] = 1.0
    vertex["z"][[10, 20_000, 29_999]] = 1.0
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(path))
    assert 0 < len(read_thinned(path, 10_000, CELL).cloud) <= 10_000


def test_the_report_reads_an_uncached_scan_within_the_budget(big_scan, capsys):
    read = points_reader({}, ReadingConfig(max_points_in_memory=BUDGET))
    assert 0 < len(read(big_scan)) <= BUDGET
    assert "thinned on reading" in capsys.readouterr().err
