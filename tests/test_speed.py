"""Issue 16's speed work: the faster report primitives give the same results as the plain numpy
ones, the plot cloud registered in memory is exactly what its written file holds, and the process
pool of a run serves its stages with one spawn."""

import os
from types import SimpleNamespace

import numpy as np
import pytest

from plotmosaic.align import prepare
from plotmosaic.align.pipeline import AlignRequest, align_clouds
from plotmosaic.config.report import ReportConfig, SliceConfig
from plotmosaic.graph.executor import _POOL, Workers, close_pool, run_pairs
from plotmosaic.io.frame import column_bounds, translation
from plotmosaic.io.las import PointCloud, read_cloud, write_cloud
from plotmosaic.parallel import threads
from plotmosaic.poses import Poses, ScanPose
from plotmosaic.report.distance import thin
from plotmosaic.report.runs import rigid_plots
from plotmosaic.report.slice import cell_minima, fit_circle, low_stratum, merge_minima
from plotmosaic.stages.tie_to_als import Anchor, as_stored


def _clouds():
    rng = np.random.default_rng(7)
    for n, offset in ((1, 0.0), (50, 0.0), (20_000, 0.0), (20_000, 5e5)):
        yield rng.normal(size=(n, 3)) * [15, 15, 3] + [offset, 8 * offset, 1200]


def _thin_reference(xyz, voxel, cap, rng):
    """One random point per cube the plain way: permuted points, np.unique on their cube rows."""
    perm = rng.permutation(len(xyz))
    keys = np.floor((xyz[perm] - xyz.min(axis=0)) / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    idx = np.sort(perm[first])
    if len(idx) > cap:
        idx = np.sort(rng.choice(idx, cap, replace=False))
    return xyz[idx]


@pytest.mark.parametrize("voxel", [0.005, 0.05, 1.0])
def test_thin_is_one_random_point_per_cube_as_before(voxel):
    for xyz in _clouds():
        a, b = np.random.default_rng(3), np.random.default_rng(3)
        got = thin(xyz, voxel, max(1, len(xyz) // 3), a)
        assert np.array_equal(got, _thin_reference(xyz, voxel, max(1, len(xyz) // 3), b))
        assert a.random() == b.random()  # the same draws consumed: later pictures unchanged


def test_cell_minima_and_low_stratum_as_with_np_unique():
    cfg = SliceConfig()
    for xyz in _clouds():
        keys = np.floor(xyz[:, :2] / cfg.dtm_cell).astype(np.int64)
        cells, inv = np.unique(keys, axis=0, return_inverse=True)
        inv = inv.ravel()
        zmin = np.full(len(cells), np.inf)
        np.minimum.at(zmin, inv, xyz[:, 2])
        got_cells, got_z = cell_minima(xyz, cfg.dtm_cell)
        assert np.array_equal(got_cells, cells) and np.array_equal(got_z, zmin)
        dz = xyz[:, 2] - zmin[inv]
        expected = xyz[(dz >= cfg.keep_low) & (dz <= cfg.keep_high)]
        assert np.array_equal(low_stratum(xyz, cfg), expected)
        half = (got_cells[::2], got_z[::2] - 1.0)
        m_cells, m_z = merge_minima((got_cells, got_z), half)
        assert np.array_equal(m_cells, cells)
        assert np.array_equal(
            m_z, np.minimum(zmin, np.where(np.arange(len(zmin)) % 2, np.inf, zmin - 1.0))
        )


def test_fit_circle_recovers_stems_and_survives_a_line():
    rng = np.random.default_rng(0)
    for arc in (2 * np.pi, np.pi, np.pi / 3):  # a whole ring, the half a scan sees, a narrow arc
        t = rng.uniform(0, arc, 400)
        xy = np.column_stack([3.0 + 0.2 * np.cos(t), -4.0 + 0.2 * np.sin(t)])
        xy += rng.normal(scale=0.002, size=xy.shape)
        c, r, rmse = fit_circle(xy)
        assert np.linalg.norm(c - [3.0, -4.0]) < 0.01 and abs(r - 0.2) < 0.01 and rmse < 0.004
    line = np.column_stack([np.linspace(0, 1, 20), np.zeros(20)])
    c, r, rmse = fit_circle(line)  # collinear: no exception, a finite answer
    assert np.all(np.isfinite(c)) and np.isfinite(r) and np.isfinite(rmse)


@pytest.mark.parametrize("offset", [0.0, 4.5e6])
def test_plot_cloud_in_memory_is_the_written_file(tmp_path, offset):
    rng = np.random.default_rng(1)
    cloud = PointCloud(rng.normal(size=(30_000, 3)) * [40, 40, 8] + [offset / 9, offset, 1500])
    path = write_cloud(tmp_path / "plot.laz", cloud)
    back = read_cloud(path, attributes=False).xyz
    held = as_stored(cloud).xyz
    assert np.array_equal(held, back)  # bit for bit: registering one is registering the other
    assert np.abs(held - cloud.xyz).max() <= 0.0005 + 1e-9


def worker_pid(job) -> dict:
    return {"key": job, "pid": os.getpid()}


def test_one_pool_serves_the_stages_of_a_run():
    try:
        first = run_pairs(list("abcd"), Workers(jobs=2, progress=False), worker=worker_pid)
        second = run_pairs(list("efgh"), Workers(jobs=2, progress=False), worker=worker_pid)
        assert len(_POOL) == 1
        pids = {r["pid"] for r in first} | {r["pid"] for r in second}
        assert len(pids) <= 2 and os.getpid() not in pids  # the same two workers both times
        assert sorted(r["key"] for r in first + second) == list("abcdefgh")
    finally:
        close_pool()
    assert not _POOL


def _rigid_case(tmp_path, nudge):
    """register-plot's poses of a 3-scan plot, the same moved as one piece into a CRS, one scan nudged."""
    rot = np.array([[0.0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    plot = {"S0": np.eye(4), "S1": translation([10.0, 2, 0]), "S2": rot @ translation([-5.0, 8, 1])}
    earlier = Poses({k: ScanPose(T, "P1") for k, T in plot.items()}, frame="plot")
    M = translation([470000.0, 3810000, 2100]) @ rot
    moved = {k: M @ T for k, T in plot.items()}
    moved["S2"] = moved["S2"] @ translation([nudge, 0, 0])
    (tmp_path / "reg").mkdir(parents=True)
    (tmp_path / "reg" / "report.html").write_text("<html></html>")
    result = SimpleNamespace(
        out=tmp_path / "geo",
        poses=Poses({k: ScanPose(T, "P1") for k, T in moved.items()}, frame="crs"),
        anchors=[Anchor("P1", "S0", "ok")],
    )
    return result, earlier, tmp_path / "reg" / "report.html"


def test_a_plot_moved_as_one_piece_is_judged_in_register_plots_report(tmp_path):
    cfg = ReportConfig()
    result, earlier, page = _rigid_case(tmp_path, 0.0)
    judged = rigid_plots(result, earlier, page, cfg)
    assert judged["P1"][0] == "../reg/report.html" and "one piece" in judged["P1"][1]
    result, earlier, page = _rigid_case(tmp_path / "b", 2 * cfg.rigid_translation)
    assert rigid_plots(result, earlier, page, cfg) == {}  # moved within the plot: judged anew
    assert rigid_plots(result, earlier, tmp_path / "missing.html", cfg) == {}


@pytest.mark.parametrize("n", [1, 7, 32_768, 32_769, 100_003])
def test_column_bounds_by_blocks_are_the_columns_min_and_max(n):
    xyz = np.random.default_rng(n).normal(size=(n, 3)) * [30, 30, 5] + [5e5, 4.2e6, 1200]
    plain = np.array([[xyz[:, i].min(), xyz[:, i].max()] for i in range(3)])
    assert np.array_equal(column_bounds(xyz), plain)
    xyz[n // 2, 1] = np.nan  # a NaN still shows, as numpy's min and max show it
    assert np.isnan(column_bounds(xyz)[1]).all() and np.array_equal(column_bounds(xyz)[0], plain[0])


def test_align_drops_each_clouds_stray_points_once(small_sim, monkeypatch):
    """The kinds and the preparation share one robust_points per cloud (each a pass over every point)."""
    calls = []
    real = prepare.stray_mask
    monkeypatch.setattr(
        prepare, "stray_mask", lambda xyz, *a: calls.append(len(xyz)) or real(xyz, *a)
    )
    src, tgt = (read_cloud(small_sim.scan_paths[f"P1-S{i}"]) for i in (1, 0))
    align_clouds(src, tgt, AlignRequest())
    assert calls == [len(src), len(tgt)]


def worker_threads(job) -> dict:
    return {"key": job, "threads": threads()}


@pytest.mark.parametrize("cores", [2, 4])
def test_a_stages_last_jobs_get_the_whole_thread_budget(cores, monkeypatch):
    """Two workers of one thread each; where -j is the whole machine, the last two jobs (the stage's
    tail, which may run alone) may use both threads, so no core idles while they finish. A smaller
    -j leaves the other cores alone."""
    monkeypatch.setattr("plotmosaic.graph.executor.os.cpu_count", lambda: cores)
    try:
        records = run_pairs(list("abcde"), Workers(jobs=2, progress=False), worker=worker_threads)
    finally:
        close_pool()
    tail = 2 if cores == 2 else 1
    assert {r["key"]: r["threads"] for r in records} == dict(zip("abcde", [1, 1, 1, tail, tail]))
