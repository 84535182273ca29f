"""The plot -> ALS anchor's fit: ALS returns on the TLS planes, offset and jackknife covariance,
carried to each scan of the plot."""

import gtsam
import numpy as np

from plotmosaic.poses import Poses, ScanPose
from plotmosaic.stages.tie_to_als.anchor_fit import AnchorFit, anchor_fit
from plotmosaic.stages.tie_to_als.solve import Tied, georeferenced_sigmas


def _ground(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 0.05 * x + 0.6 * np.sin(x / 5.0) * np.cos(y / 7.0)


def _scene(rng: np.random.Generator, als_noise: float, als_shift: float = 0.0):
    """(plot cloud in the plot frame, ALS in a UTM-like CRS, plot -> CRS): a rolling terrain, TLS
    dense, the ALS sparse and noisy."""
    g = np.arange(-20.0, 20.0, 0.1)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    plot = np.column_stack([x, y, _ground(x, y)])
    T = gtsam.Pose3(gtsam.Rot3.Yaw(0.7), np.array([512_000.0, 5_400_000.0, 830.0])).matrix()
    ax, ay = rng.uniform(-20, 20, (2, 8000))
    als = np.column_stack([ax, ay, _ground(ax, ay) + als_shift + rng.normal(0, als_noise, ax.size)])
    return plot, als @ T[:3, :3].T + T[:3, 3], T


def test_offset_and_spread_measure_the_als_against_the_plot():
    rng = np.random.default_rng(0)
    plot, als, T = _scene(rng, 0.01)
    fit = anchor_fit(plot, als, T, block=10.0, max_distance=0.3)
    assert fit is not None and fit.blocks >= 16 and fit.points > 7000
    assert abs(fit.offset_median) < 0.003 and 0.007 < fit.offset_nmad < 0.013
    assert np.all(np.isfinite(fit.sigma)) and fit.sigma[5] < 0.002

    raised = anchor_fit(*_scene(np.random.default_rng(0), 0.01, als_shift=0.05), 10.0, 0.3)
    assert abs(raised.offset_median - 0.05) < 0.005  # the ALS 5 cm above the TLS ground

    noisy = anchor_fit(*_scene(np.random.default_rng(0), 0.05), 10.0, 0.3)
    assert noisy.sigma[5] > 3 * fit.sigma[5]  # height known five times less well


def test_too_few_als_points_give_no_fit():
    plot, als, T = _scene(np.random.default_rng(1), 0.01)
    assert anchor_fit(plot, als[:2000], T, block=10.0, max_distance=0.3) is not None
    assert anchor_fit(plot, als[:60], T, block=10.0, max_distance=0.3) is None  # < 4 blocks of 20


def test_an_anchor_off_the_als_disagrees_by_its_error():
    plot, als, T = _scene(np.random.default_rng(2), 0.01)
    error = np.array([np.radians(0.05), 0.0, np.radians(-0.03), 0.02, -0.01, 0.015])
    fit = anchor_fit(plot, als, T @ gtsam.Pose3.Expmap(error).matrix(), 10.0, 0.3)
    assert np.allclose(fit.disagreement, -error, atol=0.15 * np.abs(error).max())
    assert np.all(fit.sigma >= 0.7 * np.abs(error))  # the disagreement is part of the covariance


def test_georeferenced_sigmas_carry_the_anchor_to_each_scan():
    fit = AnchorFit(
        points=1000,
        blocks=16,
        covariance=np.diag([1e-8, 1e-8, 4e-8, 1e-6, 1e-6, 1e-6]),  # 0.1 mrad tilt, 1 mm
        disagreement=np.zeros(6),
        offset_median=0.0,
        offset_nmad=0.03,
    )
    far = np.eye(4)
    far[:3, 3] = [100.0, 0.0, 0.0]
    about = [1e-5] * 3 + [1e-3] * 3
    poses = Poses(
        {
            "S0": ScanPose(np.eye(4), "P1", np.zeros(6), {"sigma_about_plot": about}),
            "S1": ScanPose(far, "P1", np.ones(6), {"sigma_about_plot": about}),
        }
    )
    tied = Tied(jobs=[], records={}, computed=0, anchors={}, refs={"P1": "S0"}, fits={"P1": fit})
    sig = georeferenced_sigmas(poses, tied)
    assert np.allclose(sig["S0"][3:], np.sqrt(1e-6 + 1e-6))
    # 100 m from the plot's origin a 0.2 mrad yaw sigma is 2 cm across
    assert 0.019 < sig["S1"][4] < 0.021 and sig["S1"][3] < 0.002
