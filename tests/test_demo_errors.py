"""The demo's error table: the plot frame's own scan is not listed with an error of zero."""

import numpy as np

from plotmosaic.demo import georeferenced_errors, plot_frame_errors
from plotmosaic.poses import Poses, ScanPose


def pose(yaw_deg: float, xyz) -> np.ndarray:
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = xyz
    return T


def test_plot_frame_errors_leave_out_the_reference_and_measure_the_rest():
    world = {"S0": pose(30, [500_000, 4_000_000, 900]), "S1": pose(75, [500_010, 4_000_004, 901])}
    truth = Poses({k: ScanPose(T, "P1") for k, T in world.items()})
    relative = np.linalg.inv(world["S0"]) @ world["S1"]
    off = pose(0.01, [0.02, 0, 0])  # the estimate 2 cm / 0.01 deg off in the plot frame
    estimated = Poses({"S0": ScanPose(np.eye(4), "P1"), "S1": ScanPose(relative @ off, "P1")})
    errors = plot_frame_errors(estimated, truth)
    assert set(errors) == {"S1"}  # S0 is the frame: its error is zero by construction
    deg, m = errors["S1"]
    assert abs(deg - 0.01) < 1e-6 and abs(m - 0.02) < 1e-4
    geo = georeferenced_errors(truth, truth)
    assert set(geo) == {"S0", "S1"} and max(e[1] for e in geo.values()) < 1e-9
