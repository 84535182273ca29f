"""The FPFH generator: mutually matched FPFH features, a 4-DoF vote per vertical pair and one
6-DoF RANSAC (features3d.py)."""

from __future__ import annotations

import numpy as np

from plotmosaic.align import features3d
from plotmosaic.align.coarse.clouds import Levels, homogeneous
from plotmosaic.align.coarse.hypothesis import Start
from plotmosaic.align.levelling import rotate
from plotmosaic.config.coarse import CoarseConfig


def fpfh_matches(src: Levels, tgt: Levels, config: CoarseConfig) -> tuple[np.ndarray, np.ndarray]:
    """Mutually matched FPFH points (source, target), local frames."""
    voxel = features3d.shared_voxel([src.voxels, tgt.voxels], config)
    fs, ft = src.fpfh(config, voxel), tgt.fpfh(config, voxel)
    i, j = features3d.mutual_matches(fs, ft)
    return fs.points[i], ft.points[j]


def fpfh_starts(
    matches: tuple[np.ndarray, np.ndarray],
    pairs,
    config: CoarseConfig,
    rng: np.random.Generator,
    six_dof: bool,
) -> list[Start]:
    """Starts from FPFH matches: a 4-DoF vote per vertical pair, and (`six_dof`) one 6-DoF RANSAC."""
    p, q = matches
    out = []
    for vs, vt in pairs:
        Rs, Rt = vs.R, vt.R
        for A, n in features3d.vote_4dof(rotate(p, Rs), rotate(q, Rt), config):
            T = homogeneous(Rt.T) @ A @ homogeneous(Rs)
            out.append(Start(T=T, generator="fpfh", vertical=f"{vs.name}/{vt.name}", votes=n))
    if six_dof and config.fpfh_six_dof:
        for T, n in features3d.ransac_6dof(p, q, config, rng):
            out.append(Start(T=T, generator="fpfh", vertical="none (6-DoF)", votes=n))
    return out
