"""The crowding about the file origin, against its plain definition."""

from __future__ import annotations

from collections import Counter

import numpy as np

from plotmosaic.align.sampling import sample
from plotmosaic.align.viewpoint import crowding
from plotmosaic.config.align import ViewpointConfig


def _plain(xyz: np.ndarray, cfg: ViewpointConfig, rng: np.random.Generator) -> float:
    xy = xyz[sample(len(xyz), cfg.probe_points, rng), :2]
    cells = Counter(map(tuple, np.floor(xy / cfg.cell).astype(np.int64).tolist()))
    near = [n for (i, j), n in cells.items() if np.hypot(i + 0.5, j + 0.5) * cfg.cell <= cfg.radius]
    return float(np.mean(near) / np.mean(list(cells.values()))) if near else 0.0


def test_crowding_is_the_mean_count_near_the_origin_over_the_mean_count():
    rng = np.random.default_rng(2)
    r = rng.exponential(6.0, 80_000)  # a scan's density falling off from the origin
    a = rng.uniform(0, 2 * np.pi, len(r))
    xyz = np.column_stack([r * np.cos(a), r * np.sin(a), rng.uniform(0, 20, len(r))])
    cfg = ViewpointConfig()
    for cloud in (xyz, xyz - (3.3, -7.1, 0.0), xyz + (40.0, 0.0, 0.0)):
        got = crowding(cloud, cfg, np.random.default_rng(5))
        assert got == _plain(cloud, cfg, np.random.default_rng(5))
    assert crowding(xyz, cfg, np.random.default_rng(5)) > cfg.min_crowding
    assert crowding(xyz + (40.0, 0.0, 0.0), cfg, np.random.default_rng(5)) < cfg.min_crowding
