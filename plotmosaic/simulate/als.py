"""Airborne scan of a tile: pulses from parallel flight lines, multiple returns through canopy gaps.

A pulse that hits foliage or understory goes on with probability `transmission` (the footprint is
only partly intercepted); the receiver is blind for `dead_zone_m` after each return. Ground, stems
and logs stop the pulse. Pulses are drawn until the tile holds `density_per_m2` returns per m2.
"""

from __future__ import annotations

import numpy as np

from plotmosaic.config.simulate import AlsConfig
from plotmosaic.io.las import PointCloud
from plotmosaic.simulate.mesh import FOLIAGE, GROUND, UNDERSTORY
from plotmosaic.simulate.scene import Scene
from plotmosaic.simulate.terrain import Terrain

SPEED_MS = 60.0  # aircraft ground speed, for gps_time


def _pulses(
    n: int, extent, terrain: Terrain, cfg: AlsConfig, rng
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Origins, unit directions and times of n pulses aimed at uniform ground points of the tile."""
    xmin, ymin, xmax, ymax = extent
    x, y = rng.uniform(xmin, xmax, n), rng.uniform(ymin, ymax, n)
    target = np.column_stack([x, y, terrain.height(x, y)])
    h = np.radians(cfg.heading_deg)
    along, across = np.array([np.sin(h), np.cos(h)]), np.array([np.cos(h), -np.sin(h)])
    spacing = 2 * cfg.altitude_m * np.tan(np.radians(cfg.fov_deg / 2)) * 0.7  # 30 % side overlap
    c = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2])
    u = (target[:, :2] - c) @ across
    line = np.round(u / spacing)
    # nearest line, abeam of the target
    plane_xy = target[:, :2] + ((line * spacing - u)[:, None] * across)
    origin = np.column_stack([plane_xy, np.full(n, cfg.altitude_m + float(np.median(terrain.z)))])
    d = target - origin
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    s = (target[:, :2] - c) @ along
    time = (line - line.min()) * 900.0 + (s - s.min()) / SPEED_MS
    return origin, d, time


def _returns(scene: Scene, origin: np.ndarray, d: np.ndarray, cfg: AlsConfig, rng):
    """Multiple returns of each pulse: (pulse index, xyz, label) in order along the pulse."""
    idx = np.arange(len(d))
    o = origin.copy()
    out_i, out_p, out_l = [], [], []
    for _ in range(cfg.max_returns):
        if len(idx) == 0:
            break
        hit, t, label, _ = scene.cast(o[idx], d[idx])
        idx = idx[hit]
        r = t + rng.normal(0, cfg.range_noise_m, len(t))
        out_i.append(idx)
        out_p.append(o[idx] + d[idx] * r[:, None])
        out_l.append(label)
        soft = (label == FOLIAGE) | (label == UNDERSTORY)
        go = soft & (rng.random(len(idx)) < cfg.transmission)
        o[idx[go]] += d[idx[go]] * (t[go] + cfg.dead_zone_m)[:, None]
        idx = idx[go]
    return np.concatenate(out_i), np.concatenate(out_p), np.concatenate(out_l)


def classify(xyz: np.ndarray, label: np.ndarray, terrain: Terrain) -> np.ndarray:
    """ASPRS classes: 2 ground, 3/4/5 low/medium/high vegetation by height above ground."""
    hag = xyz[:, 2] - terrain.height(xyz[:, 0], xyz[:, 1])
    cls = np.where(hag < 0.5, 3, np.where(hag < 2.0, 4, 5)).astype(np.uint8)
    cls[label == GROUND] = 2
    return cls


def scan_als(
    scene: Scene, terrain: Terrain, extent, cfg: AlsConfig, rng: np.random.Generator
) -> PointCloud:
    """Returns over `extent` (xmin, ymin, xmax, ymax) in the scene's local frame."""
    area = (extent[2] - extent[0]) * (extent[3] - extent[1])
    wanted = int(round(cfg.density_per_m2 * area))
    per_pulse = 1.5  # first guess, refined from what the pulses return
    parts, total = [], 0
    while total < wanted:
        n = int(min(cfg.chunk_pulses, max(1000, (wanted - total) / per_pulse * 1.05)))
        origin, d, time = _pulses(n, extent, terrain, cfg, rng)
        i, p, lab = _returns(scene, origin, d, cfg, rng)
        order = np.lexsort((np.arange(len(i)), i))  # by pulse, then along the pulse
        i, p, lab = i[order], p[order], lab[order]
        counts = np.bincount(i, minlength=n)
        per_pulse = max(counts.mean(), 0.2)
        cum = np.cumsum(counts)
        take = int(np.searchsorted(cum, wanted - total, side="right"))  # whole pulses only
        take = n if cum[-1] <= wanted - total else max(take, 1)
        keep = i < take
        i, p, lab = i[keep], p[keep], lab[keep]
        first = np.r_[0, np.cumsum(counts[:take])[:-1]]
        ret = (np.arange(len(i)) - first[i] + 1).astype(np.uint8)
        parts.append((p, lab, ret, counts[i].astype(np.uint8), time[i]))
        total += len(i)
        if take < n:
            break
    xyz = np.concatenate([q[0] for q in parts])
    label = np.concatenate([q[1] for q in parts])
    attrs = {
        "label": label,
        "return_number": np.concatenate([q[2] for q in parts]),
        "number_of_returns": np.concatenate([q[3] for q in parts]),
        "gps_time": np.concatenate([q[4] for q in parts]),
        "classification": classify(xyz, label, terrain),
    }
    attrs["intensity"] = np.clip(
        (np.array([0.35, 0.4, 0.5, 0.45] + [0.0] * 252)[label] / attrs["number_of_returns"])
        * 60000,
        0,
        65535,
    ).astype(np.uint16)
    return PointCloud(xyz, attrs)
