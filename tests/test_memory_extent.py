"""Memory follows the points, not the extent they span (issue 38.3).

A cloud the extent check accepts (up to 20 km) must not push a pair past 2 GB: the grids built over a
cloud are sparse (occupied cells only) or grow their cell to a fixed size. Sparse grids give the same
results as the dense ones they replace on forest inputs.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tracemalloc

import laspy
import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from plotmosaic.align.rasters import ground_model, height_above_ground
from plotmosaic.align.voxel import occupied_groups
from plotmosaic.config.coarse import CoarseConfig

PAIR_RSS_LIMIT = 2 * 2**30  # what any pair the extent check accepts may use
# a safety net for the shared machine, well above the address space a normal pair reserves
ADDRESS_SPACE_LIMIT = 4 * 2**30
# runs the command under the address-space limit; its children are the command's only children,
# so RUSAGE_CHILDREN's peak is the command's own
MEASURE = """
import json, resource, subprocess, sys
limit = int(sys.argv[1])
def cap():
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
p = subprocess.run(sys.argv[2:], preexec_fn=cap, capture_output=True, text=True)
peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024
print(json.dumps({"code": p.returncode, "stderr": p.stderr, "peak": peak}))
"""


# a lighter search (coarser headings, smaller FFTs): the grids under test do not depend on it
LIGHT_SEARCH = """[align.coarse]
max_fft = 128
yaw_step_deg = 10.0
refine_headings = 0
slice_max_fft = 128
slice_yaw_deg = 10.0
"""
SPAN_M = 19_500.0  # inside the 20 km extent align accepts


def write_cloud(path, xyz: np.ndarray) -> None:
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.offsets, header.scales = np.floor(xyz.min(axis=0)), [0.001] * 3
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    las.write(path)


def read_xyz(path) -> np.ndarray:
    las = laspy.read(path)
    return np.column_stack([las.x, las.y, las.z])


def spread_points(n: int, corner: np.ndarray, seed: int = 0) -> np.ndarray:
    """`n` uniform random points in a SPAN_M x SPAN_M x 50 m box from `corner`."""
    rng = np.random.default_rng(seed)
    return corner + rng.uniform([0, 0, 0], [SPAN_M, SPAN_M, 50.0], (n, 3))


def run_measured(command: list[str]) -> dict:
    """{code, stderr, peak (bytes of resident memory)} of `command` under ADDRESS_SPACE_LIMIT."""
    measured = subprocess.run(
        [sys.executable, "-c", MEASURE, str(ADDRESS_SPACE_LIMIT), *command],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(measured.stdout)


@pytest.mark.parametrize("scene", ["random", "scan with far scatter"])
@pytest.mark.slow
def test_cloud_spread_over_19_km_stays_under_2_gb(small_sim, tmp_path, scene):
    """200,000 random points over 19.5 km, or a forest scan with 20,000 points scattered over 19.5 km
    (too many to be stray), onto a forest scan: the pair's peak memory stays under 2 GB (a dense 1 m
    DTM over the extent alone was 17 GB); a refusal is one line."""
    if scene == "random":
        xyz = spread_points(200_000, np.array([470_000.0, 3_810_000.0, 2_100.0]))
    else:
        scan = read_xyz(small_sim.scan_paths["P1-S1"])
        xyz = np.vstack([scan, spread_points(20_000, scan.min(axis=0))])
    src = tmp_path / "spread.laz"
    write_cloud(src, xyz)
    config = tmp_path / "light.toml"
    config.write_text(LIGHT_SEARCH)
    target = small_sim.scan_paths["P1-S0"]
    run = run_measured(
        [sys.executable, "-m", "plotmosaic", "align", str(src), str(target)]
        + ["--out", str(tmp_path / "r.json"), "--config", str(config)]
    )
    lines = [line for line in run["stderr"].splitlines() if line.strip()]
    assert run["code"] in ((2, 3) if scene == "random" else (0, 2, 3)), run["stderr"][-2000:]
    if run["code"]:
        assert len(lines) == 1 and lines[0].startswith("error: "), run["stderr"][-2000:]
    assert run["peak"] < PAIR_RSS_LIMIT, f"peak RSS {run['peak'] / 2**30:.2f} GiB"


def local(path) -> np.ndarray:
    xyz = read_xyz(path)
    return xyz - xyz.min(axis=0)


def stem_band(small_sim) -> np.ndarray:
    """xy of the points 0.5-4 m above the rough DTM of a simulated scan (what trunk grouping sees)."""
    xyz = local(small_sim.scan_paths["P1-S0"])
    hag = height_above_ground(xyz, 1.0, CoarseConfig())
    return xyz[(hag > 0.5) & (hag < 4.0), :2]


def grid_groups(xy: np.ndarray, cell: float) -> list[np.ndarray]:
    """The dense reference: ndimage's 8-connected labelling of a `cell` occupancy image over `xy`."""
    ij = np.floor((xy - xy.min(axis=0)) / cell).astype(np.int64) + 1
    grid = np.zeros(tuple(ij.max(axis=0) + 2), bool)
    grid[ij[:, 0], ij[:, 1]] = True
    labels, n = ndimage.label(grid, structure=np.ones((3, 3)))
    lab = labels[ij[:, 0], ij[:, 1]] - 1
    order = np.argsort(lab, kind="stable")
    bounds = np.searchsorted(lab[order], np.arange(n + 1))
    return [order[bounds[k] : bounds[k + 1]] for k in range(n)]


def test_occupied_groups_number_groups_as_the_dense_labelling(small_sim):
    """The sparse grouping returns the dense one's groups, members and order, on a forest's stem band
    and on random points (some on cell faces)."""
    xy = stem_band(small_sim)
    dense, sparse = grid_groups(xy, 0.25), occupied_groups(xy, 0.25)
    assert len(dense) > 10
    assert len(sparse) == len(dense)
    assert all(np.array_equal(a, b) for a, b in zip(dense, sparse))
    rng = np.random.default_rng(1)
    for trial in range(40):
        pts = rng.uniform(0, rng.uniform(1, 30), (int(rng.integers(1, 2000)), 2))
        pts = np.round(pts * 4) / 4 if trial % 2 else pts
        dense, sparse = grid_groups(pts, 0.5), occupied_groups(pts, 0.5)
        assert len(sparse) == len(dense)
        assert all(np.array_equal(a, b) for a, b in zip(dense, sparse))


def test_sparse_ground_model_matches_the_dense_one(small_sim):
    """Forced onto its occupied cells, the DTM keeps every valid cell's height and fills each hole
    from a valid cell at the dense fill's (nearest) distance."""
    xyz = local(small_sim.scan_paths["P1-S0"])
    c = CoarseConfig()
    sparse = xyz[:, 2] - height_above_ground(xyz, 1.0, c.model_copy(update={"dtm_dense_cells": 0}))
    dtm, origin, ok = ground_model(xyz[:, :2], xyz[:, 2], 1.0, c)
    ij = np.floor((xyz[:, :2] - origin) / 1.0).astype(np.int64)
    valid = ok[ij[:, 0], ij[:, 1]]
    assert valid.mean() > 0.5 and (~valid).any()
    assert np.array_equal(sparse[valid], dtm[ij[valid, 0], ij[valid, 1]])
    # a hole: the sparse height is the low of a valid cell exactly as near as the dense fill's
    dist = ndimage.distance_transform_edt(~ok)
    good = np.argwhere(ok)
    tree = cKDTree(good)
    for k in np.flatnonzero(~valid)[:: max(1, (~valid).sum() // 300)]:
        d = dist[ij[k, 0], ij[k, 1]]
        near = good[tree.query_ball_point(ij[k], d + 1e-9)]
        near = near[np.isclose(np.linalg.norm(near - ij[k], axis=1), d)]
        assert sparse[k] in dtm[near[:, 0], near[:, 1]]


def test_grids_of_two_plots_19_km_apart_follow_the_points(small_sim):
    """Two copies of a scan 19 km apart (13.5 km along x and y): the DTM and the stem grouping use a few MB, as for one plot
    (dense grids over that extent were 3 GB and 23 GB)."""
    xyz = local(small_sim.scan_paths["P1-S0"])
    two = np.vstack([xyz, xyz + [13_500.0, 13_500.0, 0.0]])
    tracemalloc.start()
    try:
        hag = height_above_ground(two, 1.0, CoarseConfig())
        groups = occupied_groups(two[(hag > 0.5) & (hag < 4.0), :2], 0.25)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 100 * 2**20, f"{peak / 2**20:.0f} MB"
    # nothing links the copies: the groups are those of each copy on its own
    band = two[(hag > 0.5) & (hag < 4.0), :2]
    first = band[:, 0] < 6_000.0
    alone = len(occupied_groups(band[first], 0.25)) + len(occupied_groups(band[~first], 0.25))
    assert len(groups) == alone > 20
