"""Terrain: a height grid (slope + smooth undulations + micro-roughness) and its mesh.

`Terrain.height(x, y)` interpolates exactly like the mesh triangles, so points on the ground
can be checked against it and objects can be set on it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import zoom

from plotmosaic.config.simulate import TerrainConfig
from plotmosaic.simulate.mesh import GROUND, Mesh


@dataclass(frozen=True)
class Terrain:
    x0: float
    y0: float
    cell: float
    z: np.ndarray  # (ny, nx) heights on the grid

    @property
    def extent(self) -> tuple[float, float, float, float]:
        ny, nx = self.z.shape
        return self.x0, self.y0, self.x0 + (nx - 1) * self.cell, self.y0 + (ny - 1) * self.cell

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height of the mesh surface at (x, y) (clamped to the grid)."""
        ny, nx = self.z.shape
        fx = np.clip((np.asarray(x, float) - self.x0) / self.cell, 0, nx - 1 - 1e-9)
        fy = np.clip((np.asarray(y, float) - self.y0) / self.cell, 0, ny - 1 - 1e-9)
        i, j = fx.astype(int), fy.astype(int)
        u, v = fx - i, fy - j
        z00, z10, z01, z11 = self.z[j, i], self.z[j, i + 1], self.z[j + 1, i], self.z[j + 1, i + 1]
        lower = u + v <= 1  # the mesh splits each cell along the (1,0)-(0,1) diagonal
        return np.where(
            lower,
            z00 + u * (z10 - z00) + v * (z01 - z00),
            z11 + (1 - u) * (z01 - z11) + (1 - v) * (z10 - z11),
        )

    def mesh(self) -> Mesh:
        ny, nx = self.z.shape
        xs = self.x0 + np.arange(nx) * self.cell
        ys = self.y0 + np.arange(ny) * self.cell
        X, Y = np.meshgrid(xs, ys)
        verts = np.column_stack([X.ravel(), Y.ravel(), self.z.ravel()])
        idx = np.arange(nx * ny).reshape(ny, nx)
        a, b, c, d = (
            idx[:-1, :-1].ravel(),
            idx[:-1, 1:].ravel(),
            idx[1:, :-1].ravel(),
            idx[1:, 1:].ravel(),
        )
        tris = np.concatenate([np.stack([a, b, c], 1), np.stack([d, c, b], 1)])
        return Mesh(
            verts,
            tris.astype(np.int64),
            np.full(len(tris), GROUND, np.uint8),
            np.full(len(tris), -1, np.int32),
        )


def make_terrain(
    extent: tuple[float, float, float, float], cfg: TerrainConfig, rng: np.random.Generator
) -> Terrain:
    """Heights over extent (xmin, ymin, xmax, ymax), zero mean near the origin."""
    xmin, ymin, xmax, ymax = extent
    nx = int(np.ceil((xmax - xmin) / cfg.cell)) + 1
    ny = int(np.ceil((ymax - ymin) / cfg.cell)) + 1
    X, Y = np.meshgrid(xmin + np.arange(nx) * cfg.cell, ymin + np.arange(ny) * cfg.cell)
    slope = 0.0 if cfg.flat else np.tan(np.radians(cfg.slope_deg))
    az = np.radians(cfg.slope_azimuth_deg)
    z = slope * (X * np.sin(az) + Y * np.cos(az))
    # Smooth undulations: a sum of random plane waves, wavelengths in the configured band.
    amp = 0.05 if cfg.flat else cfg.undulation_m
    waves = 12
    lo, hi = cfg.undulation_wavelength_m
    lam = np.exp(rng.uniform(np.log(lo), np.log(hi), waves))
    theta = rng.uniform(0, 2 * np.pi, waves)
    phase = rng.uniform(0, 2 * np.pi, waves)
    weights = lam / lam.sum() * amp * 2.0  # long waves carry more relief
    for k in range(waves):
        kx, ky = 2 * np.pi / lam[k] * np.cos(theta[k]), 2 * np.pi / lam[k] * np.sin(theta[k])
        z += weights[k] * np.cos(kx * X + ky * Y + phase[k])
    if cfg.microrelief_m > 0:  # smooth bumps a metre or so across: white noise, upsampled
        coarse = rng.normal(
            0.0,
            1.0,
            (
                int(ny * cfg.cell / cfg.microrelief_scale_m) + 3,
                int(nx * cfg.cell / cfg.microrelief_scale_m) + 3,
            ),
        )
        fine = zoom(coarse, (cfg.microrelief_scale_m / cfg.cell,) * 2, order=3, mode="nearest")[
            :ny, :nx
        ]
        z += fine / max(fine.std(), 1e-9) * cfg.microrelief_m
    z += rng.normal(0.0, cfg.roughness_m, z.shape)
    # heights relative to the plot centre's ground
    z -= Terrain(xmin, ymin, cfg.cell, z).height(np.array([0.0]), np.array([0.0]))[0]
    return Terrain(xmin, ymin, cfg.cell, z)
