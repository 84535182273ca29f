"""The simulated world: terrain + vegetation meshes in a local frame, scanner sites, and an Open3D
RaycastingScene with a label per triangle.

The local frame has plot P1's centre at the origin (float32 inside Embree is then good to well
under a millimetre); `World.origin` (UTM, float64) is added when points and poses are written.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from plotmosaic.config.simulate import SimulationConfig
from plotmosaic.simulate.mesh import Mesh, concat
from plotmosaic.simulate.terrain import Terrain, make_terrain
from plotmosaic.simulate.vegetation import Vegetation, make_vegetation


@dataclass(frozen=True)
class Site:
    scan_id: str
    plot_id: str
    xy: np.ndarray  # local scanner position on the ground (the tripod stands here)
    post: bool = False  # scanned after the fire (prepost)


@dataclass(frozen=True)
class World:
    config: SimulationConfig
    seed: int
    origin: np.ndarray
    extent: tuple[float, float, float, float]
    terrain: Terrain
    vegetation: Vegetation
    sites: list[Site]
    mesh: Mesh  # the scene as first scanned
    post_mesh: Mesh | None = None  # after the fire (prepost only)

    @property
    def plot_ids(self) -> list[str]:
        return list(dict.fromkeys(s.plot_id for s in self.sites))

    def mesh_for(self, site: Site) -> Mesh:
        return self.post_mesh if site.post and self.post_mesh is not None else self.mesh


class Scene:
    """Embree ray casting on a labelled mesh (local frame)."""

    def __init__(self, mesh: Mesh):
        self.mesh = mesh
        self.labels = mesh.labels
        self.raycaster = o3d.t.geometry.RaycastingScene()
        self.raycaster.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(mesh.triangles, dtype=np.uint32)),
        )

    def cast(
        self, origins: np.ndarray, directions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Indices of the rays that hit, their distance, the label and unit face normal of the hit."""
        rays = np.empty((len(directions), 6), dtype=np.float32)
        rays[:, :3] = origins
        rays[:, 3:] = directions
        out = self.raycaster.cast_rays(o3d.core.Tensor(rays))
        t = out["t_hit"].numpy()
        hit = np.flatnonzero(np.isfinite(t))
        prim = out["primitive_ids"].numpy()[hit]
        return (
            hit,
            t[hit].astype(np.float64),
            self.labels[prim],
            out["primitive_normals"].numpy()[hit],
        )

    def distance(self, points_local: np.ndarray) -> np.ndarray:
        """Unsigned distance from each point to the nearest triangle."""
        q = o3d.core.Tensor(np.ascontiguousarray(points_local, dtype=np.float32))
        return self.raycaster.compute_distance(q).numpy().astype(np.float64)


def scan_id(plot_id: str, index: int) -> str:
    return f"{plot_id}-S{index}"


def plot_ids(config: SimulationConfig) -> list[str]:
    if config.prepost:
        return ["PRE", "POST"]
    return [f"P{i + 1}" for i in range(len(config.plot_centres))]


def _sites(config: SimulationConfig, rng: np.random.Generator) -> list[Site]:
    layout = np.asarray(config.scan_layout, dtype=float)
    sites = []
    centres = [config.plot_centres[0]] * 2 if config.prepost else config.plot_centres
    pre_xy = None
    for pid, centre in zip(plot_ids(config), centres):
        ang = rng.uniform(0, 2 * np.pi, len(layout))
        rad = config.tls.position_jitter_m * np.sqrt(rng.random(len(layout)))
        xy = (
            np.asarray(centre) + layout + np.column_stack([np.cos(ang), np.sin(ang)]) * rad[:, None]
        )
        post = config.prepost and pid == "POST"
        if post:  # the crew comes back and sets the tripod near, not on, the old spots
            ang = rng.uniform(0, 2 * np.pi, len(layout))
            xy = pre_xy + np.column_stack([np.cos(ang), np.sin(ang)]) * config.fire.post_jitter_m
        pre_xy = xy
        sites += [Site(scan_id(pid, i), pid, xy[i], post) for i in range(len(layout))]
    return sites


def square_extent(xy: np.ndarray, margin: float) -> tuple[float, float, float, float]:
    """A square around the points' bounding box, `margin` beyond its longer side."""
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    c, half = (lo + hi) / 2, (hi - lo).max() / 2 + margin
    return float(c[0] - half), float(c[1] - half), float(c[0] + half), float(c[1] + half)


def build_world(config: SimulationConfig, seed: int = 0) -> World:
    """Everything the scans are taken of; the same (config, seed) always gives the same world."""
    rng_terrain, rng_sites, rng_veg, rng_fire = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4)
    )
    sites = _sites(config, rng_sites)
    scan_xy = np.array([s.xy for s in sites])
    extent = square_extent(scan_xy, config.scene_margin_m)
    terrain = make_terrain(extent, config.terrain, rng_terrain)
    centres = np.asarray(config.plot_centres, dtype=float)
    vegetation = make_vegetation(terrain, extent, centres, scan_xy, config.forest, rng_veg)
    mesh = concat([terrain.mesh(), vegetation.mesh])
    post_mesh = None
    if config.prepost:
        post_mesh = burn(mesh, vegetation, config, rng_fire)
    return World(
        config,
        seed,
        np.asarray(config.origin, dtype=np.float64),
        extent,
        terrain,
        vegetation,
        sites,
        mesh,
        post_mesh,
    )


def burn(
    mesh: Mesh, vegetation: Vegetation, config: SimulationConfig, rng: np.random.Generator
) -> Mesh:
    """A low-intensity surface fire: most grass tufts and many shrubs are gone, trees untouched."""
    gone = np.concatenate(
        [
            vegetation.grass_ids[rng.random(len(vegetation.grass_ids)) < config.fire.grass_removed],
            vegetation.shrub_ids[
                rng.random(len(vegetation.shrub_ids)) < config.fire.shrubs_removed
            ],
        ]
    )
    return mesh.select(~np.isin(mesh.owners, gone))
