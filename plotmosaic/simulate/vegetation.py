"""The scene's vegetation as one labelled mesh: trees (simulate/trees.py), shrubs and saplings,
grass tufts, fallen logs and branches, with the owner ids a surface fire removes (prepost).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.config.simulate import ForestConfig
from plotmosaic.simulate.mesh import UNDERSTORY, WOODY, Mesh, concat, random_elements, tubes, unit
from plotmosaic.simulate.terrain import Terrain
from plotmosaic.simulate.trees import Tree, broadleaf_meshes, conifer_meshes, far, make_trees, place

SHRUB_IDS = 1_000_000  # owner ids: trees from 0, shrubs from here, grass tufts from GRASS_IDS
GRASS_IDS = 2_000_000
LOG_IDS = 3_000_000


@dataclass(frozen=True)
class Vegetation:
    mesh: Mesh
    trees: list[Tree] = field(default_factory=list)
    # owner ids of shrubs and saplings, and of grass tufts (what a surface fire can remove)
    shrub_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    grass_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))


def _shrubs(terrain: Terrain, xy: np.ndarray, coarse: np.ndarray, cfg: ForestConfig, rng) -> Mesh:
    meshes = []
    for k, (x, y) in enumerate(xy):
        h = rng.uniform(0.5, 2.0)
        r = rng.uniform(0.4, 1.2)
        z = terrain.height(np.array([x]), np.array([y]))[0]
        factor = cfg.coarse_factor if coarse[k] else 1
        m = max(4, cfg.shrub_elements // factor)
        d = unit(rng.normal(size=(m, 3))) * rng.random((m, 1)) ** (1 / 3)
        pts = np.array([x, y, z + h / 2]) + d * [r, r, h / 2]
        size = rng.uniform(*cfg.leaf_size_m, m) * np.sqrt(factor)
        meshes.append(random_elements(pts, size, rng, UNDERSTORY, SHRUB_IDS + k, quads=True))
        s = int(rng.integers(3, 6))  # a few thin stems
        base = np.column_stack(
            [x + rng.normal(0, 0.1, s), y + rng.normal(0, 0.1, s), np.full(s, z - 0.05)]
        )
        top = base + unit(rng.normal(0, 0.3, (s, 3)) + [0, 0, 1]) * h * 0.8
        widths, owners = np.tile([0.012, 0.005], (s, 1)), np.full(s, SHRUB_IDS + k)
        meshes.append(tubes(np.stack([base, top], 1), widths, 4, UNDERSTORY, owners, cap=False))
    return concat(meshes)


def _grass(terrain: Terrain, xy: np.ndarray, coarse: np.ndarray, cfg: ForestConfig, rng) -> Mesh:
    """Bunchgrass tufts of thin upright blades; far from the plots fewer, wider blades (same cover)."""
    n = len(xy)
    if n == 0:
        return Mesh.empty()
    blades = np.where(coarse, max(1, cfg.grass_blades // cfg.coarse_factor), cfg.grass_blades)
    widen = np.where(coarse, cfg.grass_blades / blades, 1.0)
    tuft = np.repeat(np.arange(n), blades)
    m = len(tuft)
    base_xy = xy[tuft] + rng.normal(0, 0.06, (m, 2))
    base = np.column_stack([base_xy, terrain.height(base_xy[:, 0], base_xy[:, 1]) - 0.02])
    tip = base + unit(rng.normal(0, 0.35, (m, 3)) + [0, 0, 1]) * rng.uniform(
        *cfg.grass_height_m, (m, 1)
    )
    half = rng.uniform(*cfg.blade_width_m, (m, 1)) / 2 * widen[tuft, None]
    side = unit(np.column_stack([rng.normal(size=(m, 2)), np.zeros(m)])) * half
    return Mesh.soup(np.stack([base - side, base + side, tip], 1), UNDERSTORY, GRASS_IDS + tuft)


def _saplings(
    terrain: Terrain, xy: np.ndarray, coarse: np.ndarray, cfg: ForestConfig, rng, first_id: int
) -> Mesh:
    """Young conifers (understory): a thin stem with a narrow cone of branches and needles."""
    meshes = []
    for k, (x, y) in enumerate(xy):
        height = rng.uniform(1.5, 5.0)
        tree = Tree(
            float(x),
            float(y),
            rng.uniform(0.02, 0.06),
            height,
            True,
            np.array([0.0, 0.0, 1.0]),
            rng.uniform(0.2, 0.8),
            rng.uniform(0.4, 1.2),
            not coarse[k],
        )
        z0 = terrain.height(np.array([x]), np.array([y]))[0]
        for m in conifer_meshes(tree, z0, cfg, rng, first_id + k, stubs=False):
            m.labels[:] = UNDERSTORY
            meshes.append(m)
    return concat(meshes)


def _logs(
    terrain: Terrain,
    xy: np.ndarray,
    avoid: np.ndarray,
    rng,
    length_m=(2.5, 10.0),
    radius_m=(0.08, 0.3),
    sides=12,
    first_id=LOG_IDS,
) -> Mesh:
    meshes = []
    for k, (x, y) in enumerate(xy):
        length, r, a = rng.uniform(*length_m), rng.uniform(*radius_m), rng.uniform(0, np.pi)
        t = np.linspace(0, 1, 7)
        px = x + t * length * np.cos(a)
        py = y + t * length * np.sin(a)
        if len(avoid) and cKDTree(avoid).query(np.column_stack([px, py]))[0].min() < 1.2:
            continue  # the surveyor would not set the tripod on a log
        path = np.column_stack([px, py, terrain.height(px, py) + r * 0.8])
        meshes.append(tubes(path[None], np.full((1, 7), r), sides, WOODY, [first_id + k]))
    return concat(meshes)


def _tuft_positions(extent, area: float, scan_xy: np.ndarray, cfg: ForestConfig, rng) -> np.ndarray:
    """Grass grows in patches: tuft centres cluster around random patch centres."""
    n_tufts = int(round(cfg.grass_tufts_per_m2 * area))
    patches = max(1, n_tufts // 30)
    pc = np.column_stack(
        [rng.uniform(extent[0], extent[2], patches), rng.uniform(extent[1], extent[3], patches)]
    )
    tuft_xy = pc[rng.integers(0, patches, n_tufts)] + rng.normal(0, 1.5, (n_tufts, 2))
    inside = (
        (tuft_xy[:, 0] > extent[0])
        & (tuft_xy[:, 0] < extent[2])
        & (tuft_xy[:, 1] > extent[1])
        & (tuft_xy[:, 1] < extent[3])
    )
    tuft_xy = tuft_xy[inside]
    if len(scan_xy) and len(tuft_xy):
        # the tripod stands on bare ground
        tuft_xy = tuft_xy[cKDTree(scan_xy).query(tuft_xy)[0] > 0.5]
    return tuft_xy


def make_vegetation(
    terrain: Terrain, extent, plot_centres: np.ndarray, scan_xy: np.ndarray, cfg: ForestConfig, rng
) -> Vegetation:
    """Every plant and log of the scene as one labelled mesh."""
    trees = make_trees(terrain, extent, plot_centres, scan_xy, cfg, rng)
    meshes = []
    for k, tree in enumerate(trees):
        z0 = terrain.height(np.array([tree.x]), np.array([tree.y]))[0]
        meshes += (conifer_meshes if tree.conifer else broadleaf_meshes)(tree, z0, cfg, rng, k)
    area = (extent[2] - extent[0]) * (extent[3] - extent[1])

    def spaced(per_ha: float, min_dist: float) -> np.ndarray:
        n = int(round(per_ha * area / 1e4))
        if not n:
            return np.zeros((0, 2))
        return place(n, extent, np.full(1, min_dist), scan_xy, cfg.clearance_m, rng)

    def scattered(per_ha: float) -> np.ndarray:
        n = int(round(per_ha * area / 1e4))
        return np.column_stack(
            [rng.uniform(extent[0], extent[2], n), rng.uniform(extent[1], extent[3], n)]
        )

    shrub_xy = spaced(cfg.shrubs_per_ha, 1.0)
    meshes.append(_shrubs(terrain, shrub_xy, far(shrub_xy, plot_centres, cfg), cfg, rng))
    sap_xy = spaced(cfg.saplings_per_ha, 1.5)
    meshes.append(
        _saplings(
            terrain, sap_xy, far(sap_xy, plot_centres, cfg), cfg, rng, SHRUB_IDS + len(shrub_xy)
        )
    )
    shrub_ids = SHRUB_IDS + np.arange(len(shrub_xy) + len(sap_xy), dtype=np.int32)
    tuft_xy = _tuft_positions(extent, area, scan_xy, cfg, rng)
    meshes.append(_grass(terrain, tuft_xy, far(tuft_xy, plot_centres, cfg), cfg, rng))
    log_xy = scattered(cfg.logs_per_ha)
    meshes.append(_logs(terrain, log_xy, scan_xy, rng))
    debris_xy = scattered(cfg.debris_per_ha)  # fallen branches
    meshes.append(
        _logs(terrain, debris_xy, scan_xy, rng, (0.5, 3.0), (0.02, 0.06), 6, LOG_IDS + len(log_xy))
    )
    return Vegetation(
        concat(meshes), trees, shrub_ids, GRASS_IDS + np.arange(len(tuft_xy), dtype=np.int32)
    )
