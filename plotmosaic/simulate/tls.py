"""BLK360-like terrestrial scans: a regular azimuth x elevation grid of rays from the scanner,
first hit only, range noise growing with range, fewer returns near the maximum range.

Points come out in the scanner's own frame (scanner at the origin); `pose` maps that frame to
the scene's local frame. Density falls with range by itself because the angular step is fixed.
"""

from __future__ import annotations

import numpy as np

from plotmosaic.config.simulate import TlsConfig
from plotmosaic.io.las import PointCloud
from plotmosaic.simulate.scene import Scene

# Reflectance at 830 nm by label: ground, bark, needles/leaves, grass/shrubs.
REFLECTANCE = np.array([0.30, 0.40, 0.55, 0.50] + [0.0] * 252)
PILOT_STEP_DEG = 1.5


def random_pose(position: np.ndarray, cfg: TlsConfig, rng: np.random.Generator) -> np.ndarray:
    """Scanner frame -> local frame: random heading in [0, 360), tilt up to `max_tilt_deg`."""
    heading = rng.uniform(0, 2 * np.pi)
    tilt = np.radians(cfg.max_tilt_deg) * np.sqrt(rng.random())
    axis_az = rng.uniform(0, 2 * np.pi)
    axis = np.array([np.cos(axis_az), np.sin(axis_az), 0.0])
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R_tilt = np.eye(3) + np.sin(tilt) * K + (1 - np.cos(tilt)) * K @ K
    c, s = np.cos(heading), np.sin(heading)
    R_head = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = R_tilt @ R_head
    T[:3, 3] = position
    return T


def _grid(step: float, cfg: TlsConfig) -> tuple[np.ndarray, np.ndarray]:
    el_min = 90.0 - cfg.fov_vertical_deg / 2  # -60 deg for 300 deg: the tripod blocks the rest
    n_az = max(4, int(round(cfg.fov_horizontal_deg / step)))
    n_el = max(2, int(round((90.0 - el_min) / step)))
    az = np.radians((np.arange(n_az) + 0.5) * cfg.fov_horizontal_deg / n_az)
    el = np.radians(el_min + (np.arange(n_el) + 0.5) * (90.0 - el_min) / n_el)
    return az, el


def _directions(az: np.ndarray, el: np.ndarray) -> np.ndarray:
    """Unit rays column by column (as the head turns), float32."""
    ce, se = np.cos(el).astype(np.float32), np.sin(el).astype(np.float32)
    d = np.empty((len(az), len(el), 3), dtype=np.float32)
    d[:, :, 0] = np.multiply.outer(np.cos(az).astype(np.float32), ce)
    d[:, :, 1] = np.multiply.outer(np.sin(az).astype(np.float32), ce)
    d[:, :, 2] = se
    return d.reshape(-1, 3)


def _detect(r: np.ndarray, cfg: TlsConfig, rng) -> np.ndarray:
    """Returns fade beyond half the maximum range (weak echoes from far, oblique targets)."""
    x = np.clip((r / cfg.max_range_m - 0.5) / 0.5, 0, 1)
    keep = (r >= cfg.min_range_m) & (r <= cfg.max_range_m)
    return keep & (rng.random(len(r)) < 1 - 0.7 * x**2)


def angular_step(scene: Scene, pose: np.ndarray, cfg: TlsConfig, rng: np.random.Generator) -> float:
    """The grid step giving about `points_per_scan` points from this position (a coarse pilot scan)."""
    if cfg.angular_step_deg:
        return cfg.angular_step_deg
    az, el = _grid(PILOT_STEP_DEG, cfg)
    d = _directions(az, el)
    _, t, _, _ = scene.cast(pose[:3, 3], np.einsum("ij,kj->ik", d, pose[:3, :3].astype(np.float32)))
    frac = max(_detect(t, cfg, rng).sum() / len(d), 1e-3)
    span = cfg.fov_horizontal_deg * cfg.fov_vertical_deg / 2
    return float(np.sqrt(span * frac / cfg.points_per_scan))


def scan_tls(
    scene: Scene, pose: np.ndarray, cfg: TlsConfig, rng: np.random.Generator, t0: float = 0.0
) -> PointCloud:
    """One scan from `pose` (scanner -> scene local frame), points in the scanner frame."""
    step = angular_step(scene, pose, cfg, rng)
    az, el = _grid(step, cfg)
    cols = max(1, cfg.chunk_rays // len(el))
    parts: list[tuple] = []
    R, origin = pose[:3, :3].astype(np.float32), pose[:3, 3]
    for start in range(0, len(az), cols):
        d = _directions(az[start : start + cols], el)
        dw = np.einsum("ij,kj->ik", d, R)  # d @ R.T; einsum: BLAS is slow on tall, 3-wide arrays
        hit, t, label, normal = scene.cast(origin, dw)
        ok = _detect(t, cfg, rng)
        hit, t, label, normal = hit[ok], t[ok], label[ok], normal[ok]
        r = t + rng.standard_normal(len(t)) * (cfg.range_noise_m + cfg.range_noise_per_m * t)
        xyz = d[hit] * r[:, None]  # float64: the scanner frame, exactly as the ray was cast
        gps = t0 + (start + hit // len(el)) * (cfg.seconds_per_scan / len(az))
        attrs = {"label": label, "gps_time": gps}
        if cfg.intensity:
            cos = np.abs(np.einsum("ij,ij->i", normal, dw[hit]))
            val = (
                REFLECTANCE[label]
                * (0.35 + 0.65 * cos)
                * np.exp(-r / 80.0)
                * rng.normal(1.0, 0.05, len(r))
            )
            attrs["intensity"] = np.clip(val * 60000, 0, 65535).astype(np.uint16)
        parts.append((xyz, attrs))
    xyz = np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, 3))
    attrs = {k: np.concatenate([p[1][k] for p in parts]) for k in parts[0][1]} if parts else {}
    n = len(xyz)
    attrs["return_number"] = np.ones(n, np.uint8)
    attrs["number_of_returns"] = np.ones(n, np.uint8)
    return PointCloud(xyz, attrs)
