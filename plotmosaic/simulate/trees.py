"""Vegetation meshes: trees (tapered, leaning stems; branches; conifer or broadleaf crowns made of
many small randomly oriented foliage elements), shrubs, grass tufts and fallen logs.

Foliage is deliberately a cloud of small elements: normals there are random, while ground and
stems are smooth. That contrast is what the structural-complexity grouping lives on.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.config.simulate import ForestConfig
from plotmosaic.simulate.mesh import (
    FOLIAGE,
    UNDERSTORY,
    WOODY,
    Mesh,
    concat,
    random_elements,
    tubes,
    unit,
)
from plotmosaic.simulate.terrain import Terrain

SHRUB_IDS = 1_000_000  # owner ids: trees from 0, shrubs from here, grass tufts from GRASS_IDS
GRASS_IDS = 2_000_000
LOG_IDS = 3_000_000


@dataclass
class Tree:
    x: float
    y: float
    dbh: float
    height: float
    conifer: bool
    lean: np.ndarray  # unit stem axis
    crown_base: float  # height above the stem base where the live crown starts
    crown_radius: float
    detailed: bool


@dataclass
class Vegetation:
    mesh: Mesh
    trees: list[Tree] = field(default_factory=list)
    # owner ids of shrubs and saplings, and of grass tufts (what a surface fire can remove)
    shrub_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    grass_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))


def _place(
    n: int, extent, min_dist: np.ndarray, avoid: np.ndarray, clearance: float, rng
) -> np.ndarray:
    """Up to n positions, uniform with a minimum spacing (greedy dart throwing), away from `avoid`."""
    xmin, ymin, xmax, ymax = extent
    cand = np.column_stack(
        [rng.uniform(xmin, xmax, 3 * n + 10), rng.uniform(ymin, ymax, 3 * n + 10)]
    )
    if len(avoid) and clearance > 0:
        d, _ = cKDTree(avoid).query(cand)
        cand = cand[d > clearance]
    kept: list[int] = []
    tree = cKDTree(cand)
    blocked = np.zeros(len(cand), bool)
    for i in range(len(cand)):
        if len(kept) >= n:
            break
        if blocked[i]:
            continue
        kept.append(i)
        blocked[tree.query_ball_point(cand[i], min_dist[min(len(kept) - 1, len(min_dist) - 1)])] = (
            True
        )
    return cand[kept]


def _stem_paths(
    base: np.ndarray, axis: np.ndarray, length: float, ring_step: float, bow: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    rings = max(3, int(np.ceil(length / ring_step)) + 1)
    h = np.linspace(0.0, length, rings)
    centres = base + h[:, None] * axis + np.sin(np.pi * h / length)[:, None] * bow  # a slight sweep
    return centres, h


def _stem_radius(h: np.ndarray, dbh: float, total: float) -> np.ndarray:
    r = dbh / 2 * np.clip((total - h) / max(total - 1.3, 0.5 * total), 0.0, None) ** 0.8
    r *= 1 + 0.3 * np.clip(1.3 - h, 0, None) / 1.3  # butt swell
    return np.maximum(r, 0.01)


def _conifer(
    tree: Tree, z0: float, cfg: ForestConfig, rng, owner: int, stubs: bool = True
) -> list[Mesh]:
    sides = cfg.stem_sides if tree.detailed else 8
    base = np.array([tree.x, tree.y, z0 - 0.3])
    bow = unit(np.cross(tree.lean, rng.normal(size=3))) * rng.uniform(0, 0.01) * tree.height
    centres, h = _stem_paths(
        base, tree.lean, tree.height + 0.3, 0.75 if tree.detailed else 2.0, bow
    )
    meshes = [
        tubes(
            centres[None], _stem_radius(h - 0.3, tree.dbh, tree.height)[None], sides, WOODY, [owner]
        )
    ]
    # Whorls of branches through the crown; their length shrinks toward the top (a cone).
    whorl_h = np.arange(tree.crown_base, tree.height * 0.96, rng.uniform(0.5, 0.8))
    per = rng.integers(3, 7, len(whorl_h))
    hb = np.repeat(whorl_h, per)
    az = rng.uniform(0, 2 * np.pi, len(hb))
    frac = (tree.height - hb) / max(tree.height - tree.crown_base, 1e-3)
    length = tree.crown_radius * frac**0.9 * rng.uniform(0.75, 1.1, len(hb)) + 0.25
    pitch = np.radians(np.interp(frac, [0, 1], [25, -15]) + rng.normal(0, 6, len(hb)))
    # Dead stubs below the live crown: short woody branches without foliage.
    hs = rng.uniform(2.0, max(tree.crown_base, 2.1), int(rng.integers(3, 10)) if stubs else 0)
    az_s = rng.uniform(0, 2 * np.pi, len(hs))
    all_h = np.concatenate([hb, hs])
    all_az = np.concatenate([az, az_s])
    all_len = np.concatenate([length, rng.uniform(0.3, 1.0, len(hs))])
    all_pitch = np.concatenate([pitch, np.radians(rng.uniform(-20, 10, len(hs)))])
    start = base + (all_h[:, None] + 0.3) * tree.lean
    d = np.column_stack(
        [np.cos(all_az) * np.cos(all_pitch), np.sin(all_az) * np.cos(all_pitch), np.sin(all_pitch)]
    )
    droop = np.array([0.0, 0.0, -1.0]) * (0.15 * all_len**2 / 3)[:, None]
    mid = start + d * all_len[:, None] * 0.5 + droop * 0.35
    end = start + d * all_len[:, None] + droop
    r0 = 0.012 + 0.012 * all_len
    if tree.detailed:
        meshes.append(
            tubes(
                np.stack([start, mid, end], 1),
                np.column_stack([r0, r0 * 0.6, r0 * 0.25]),
                6,
                WOODY,
                np.full(len(start), owner),
                cap=False,
            )
        )
    else:  # far from every plot: straight three-sided branches are enough for ALS
        meshes.append(
            tubes(
                np.stack([start, end], 1),
                np.column_stack([r0, r0 * 0.25]),
                3,
                WOODY,
                np.full(len(start), owner),
                cap=False,
            )
        )
    # Needle clusters along the live branches (outer part), jittered around the branch line.
    factor = 1 if tree.detailed else cfg.coarse_factor
    counts = np.maximum(1, (cfg.foliage_per_m * length / factor).astype(int))
    b = np.repeat(np.arange(len(hb)), counts)
    t = rng.uniform(0.25, 1.0, len(b)) ** 0.7
    pts = (1 - t)[:, None] * start[b] + t[:, None] * end[b]
    pts += rng.normal(0, 1, (len(b), 3)) * (0.08 + 0.12 * t * length[b])[:, None]
    size = rng.uniform(*cfg.leaf_size_m, len(b)) * np.sqrt(factor)
    meshes.append(random_elements(pts, size, rng, FOLIAGE, owner))
    return meshes


def _broadleaf(tree: Tree, z0: float, cfg: ForestConfig, rng, owner: int) -> list[Mesh]:
    sides = cfg.stem_sides if tree.detailed else 8
    base = np.array([tree.x, tree.y, z0 - 0.3])
    bow = unit(np.cross(tree.lean, rng.normal(size=3))) * rng.uniform(0, 0.015) * tree.height
    leader = 0.8 * tree.height + 0.3
    centres, h = _stem_paths(base, tree.lean, leader, 0.75 if tree.detailed else 2.0, bow)
    meshes = [
        tubes(
            centres[None], _stem_radius(h - 0.3, tree.dbh, tree.height)[None], sides, WOODY, [owner]
        )
    ]
    crown_len = tree.height - tree.crown_base
    centre = base + (tree.crown_base + 0.3 + crown_len / 2) * tree.lean
    radii = np.array([tree.crown_radius, tree.crown_radius, crown_len / 2])
    # Scaffold branches from the stem out and up into the crown, each with two or three forks.
    n = int(rng.integers(5, 9))
    hb = rng.uniform(tree.crown_base, tree.crown_base + 0.6 * crown_len, n)
    start = base + (hb[:, None] + 0.3) * tree.lean
    az = rng.uniform(0, 2 * np.pi, n)
    target = centre + radii * np.column_stack(
        [np.cos(az) * 0.75, np.sin(az) * 0.75, rng.uniform(-0.1, 0.6, n)]
    )
    mid = (start + target) / 2 + rng.normal(0, 0.15, (n, 3))
    r0 = np.clip(tree.dbh * 0.18, 0.03, 0.12)
    meshes.append(
        tubes(
            np.stack([start, mid, target], 1),
            np.column_stack([np.full(n, r0), np.full(n, r0 * 0.65), np.full(n, r0 * 0.3)]),
            8 if tree.detailed else 4,
            WOODY,
            np.full(n, owner),
            cap=False,
        )
    )
    k = int(rng.integers(2, 4))
    fs = np.repeat(mid, k, 0) + rng.uniform(0, 1, (n * k, 1)) * (
        np.repeat(target, k, 0) - np.repeat(mid, k, 0)
    )
    fe = fs + unit(rng.normal(0, 1, (n * k, 3)) + [0, 0, 0.8]) * (
        0.25 * radii.mean() * rng.uniform(0.6, 1.2, (n * k, 1))
    )
    meshes.append(
        tubes(
            np.stack([fs, fe], 1),
            np.column_stack([np.full(n * k, r0 * 0.3), np.full(n * k, r0 * 0.12)]),
            5 if tree.detailed else 3,
            WOODY,
            np.full(n * k, owner),
            cap=False,
        )
    )
    # Leaves in clumps filling the outer shell of the crown ellipsoid.
    factor = 1 if tree.detailed else cfg.coarse_factor
    scale = (tree.crown_radius / 4.0) ** 2 * (
        crown_len / 10.0
    )  # leaf count grows with crown volume
    total = max(20, int(cfg.broadleaf_leaves * np.clip(scale, 0.2, 2.0) / factor))
    clumps = max(4, total // 40)
    dirs = unit(rng.normal(size=(clumps, 3)))
    cc = centre + dirs * radii * rng.uniform(0.45, 1.0, (clumps, 1))
    idx = rng.integers(0, clumps, total)
    pts = cc[idx] + rng.normal(0, 0.35, (total, 3))
    size = rng.uniform(*cfg.leaf_size_m, total) * np.sqrt(factor)
    meshes.append(random_elements(pts, size, rng, FOLIAGE, owner, quads=True))
    return meshes


def make_trees(
    terrain: Terrain, extent, plot_centres: np.ndarray, avoid: np.ndarray, cfg: ForestConfig, rng
) -> list[Tree]:
    area_ha = (extent[2] - extent[0]) * (extent[3] - extent[1]) / 1e4
    n = int(round(cfg.trees_per_ha * area_ha))
    if n == 0:
        return []
    lo, hi = cfg.dbh_range_m
    dbh = np.clip(np.exp(rng.normal(np.log(cfg.dbh_median_m), 0.45, n)), lo, hi)
    dbh = np.sort(dbh)[::-1]  # place big trees first so spacing follows crown size
    xy = _place(n, extent, 1.2 + 6.0 * dbh, avoid, cfg.clearance_m, rng)
    trees = []
    for k, (x, y) in enumerate(xy):
        d = dbh[k]
        conifer = rng.random() < cfg.conifer_fraction
        s = ((d - lo) / max(hi - lo, 1e-6)) ** 0.6
        hmin, hmax = cfg.conifer_height_m if conifer else cfg.broadleaf_height_m
        height = float(np.clip(hmin + (hmax - hmin) * s + rng.normal(0, 1.5), hmin, hmax))
        lean_deg = cfg.max_lean_deg * rng.random() ** 2  # most trees nearly upright, some lean
        la = rng.uniform(0, 2 * np.pi)
        lean = np.array(
            [
                np.sin(np.radians(lean_deg)) * np.cos(la),
                np.sin(np.radians(lean_deg)) * np.sin(la),
                np.cos(np.radians(lean_deg)),
            ]
        )
        crown_ratio = rng.uniform(0.4, 0.7) if conifer else rng.uniform(0.5, 0.7)
        crown_base = height * (1 - crown_ratio)
        crown_radius = (
            (0.12 * height * crown_ratio + 1.0 + 2.0 * d)
            if conifer
            else (0.22 * height + 1.0 + 2.0 * d)
        )
        near = not _far(np.array([[x, y]]), plot_centres, cfg)[0]
        trees.append(
            Tree(
                float(x),
                float(y),
                float(d),
                height,
                conifer,
                lean,
                crown_base,
                crown_radius,
                bool(near),
            )
        )
    return trees


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
        meshes.append(
            random_elements(
                pts,
                rng.uniform(*cfg.leaf_size_m, m) * np.sqrt(factor),
                rng,
                UNDERSTORY,
                SHRUB_IDS + k,
                quads=True,
            )
        )
        s = int(rng.integers(3, 6))  # a few thin stems
        base = np.column_stack(
            [x + rng.normal(0, 0.1, s), y + rng.normal(0, 0.1, s), np.full(s, z - 0.05)]
        )
        top = base + unit(rng.normal(0, 0.3, (s, 3)) + [0, 0, 1]) * h * 0.8
        meshes.append(
            tubes(
                np.stack([base, top], 1),
                np.tile([0.012, 0.005], (s, 1)),
                4,
                UNDERSTORY,
                np.full(s, SHRUB_IDS + k),
                cap=False,
            )
        )
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
        for m in _conifer(tree, z0, cfg, rng, first_id + k, stubs=False):
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


def _far(xy: np.ndarray, plot_centres: np.ndarray, cfg: ForestConfig) -> np.ndarray:
    """Objects beyond `detail_radius_m` of every plot centre get coarse geometry (only ALS sees them)."""
    if len(xy) == 0:
        return np.zeros(0, bool)
    return cKDTree(plot_centres).query(xy)[0] > cfg.detail_radius_m


def make_vegetation(
    terrain: Terrain, extent, plot_centres: np.ndarray, scan_xy: np.ndarray, cfg: ForestConfig, rng
) -> Vegetation:
    """Every plant and log of the scene as one labelled mesh."""
    trees = make_trees(terrain, extent, plot_centres, scan_xy, cfg, rng)
    meshes = []
    for k, tree in enumerate(trees):
        z0 = terrain.height(np.array([tree.x]), np.array([tree.y]))[0]
        meshes += (_conifer if tree.conifer else _broadleaf)(tree, z0, cfg, rng, k)
    area = (extent[2] - extent[0]) * (extent[3] - extent[1])
    n_shrubs = int(round(cfg.shrubs_per_ha * area / 1e4))
    shrub_xy = (
        _place(n_shrubs, extent, np.full(1, 1.0), scan_xy, cfg.clearance_m, rng)
        if n_shrubs
        else np.zeros((0, 2))
    )
    meshes.append(_shrubs(terrain, shrub_xy, _far(shrub_xy, plot_centres, cfg), cfg, rng))
    n_sap = int(round(cfg.saplings_per_ha * area / 1e4))
    sap_xy = (
        _place(n_sap, extent, np.full(1, 1.5), scan_xy, cfg.clearance_m, rng)
        if n_sap
        else np.zeros((0, 2))
    )
    meshes.append(
        _saplings(
            terrain, sap_xy, _far(sap_xy, plot_centres, cfg), cfg, rng, SHRUB_IDS + len(shrub_xy)
        )
    )
    shrub_ids = SHRUB_IDS + np.arange(len(shrub_xy) + len(sap_xy), dtype=np.int32)
    # Grass grows in patches: tuft centres cluster around random patch centres.
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
        tuft_xy = tuft_xy[
            cKDTree(scan_xy).query(tuft_xy)[0] > 0.5
        ]  # the tripod stands on bare ground
    meshes.append(_grass(terrain, tuft_xy, _far(tuft_xy, plot_centres, cfg), cfg, rng))
    n_logs = int(round(cfg.logs_per_ha * area / 1e4))
    log_xy = np.column_stack(
        [rng.uniform(extent[0], extent[2], n_logs), rng.uniform(extent[1], extent[3], n_logs)]
    )
    meshes.append(_logs(terrain, log_xy, scan_xy, rng))
    n_debris = int(round(cfg.debris_per_ha * area / 1e4))  # fallen branches
    debris_xy = np.column_stack(
        [rng.uniform(extent[0], extent[2], n_debris), rng.uniform(extent[1], extent[3], n_debris)]
    )
    meshes.append(
        _logs(terrain, debris_xy, scan_xy, rng, (0.5, 3.0), (0.02, 0.06), 6, LOG_IDS + n_logs)
    )
    return Vegetation(
        concat(meshes), trees, shrub_ids, GRASS_IDS + np.arange(len(tuft_xy), dtype=np.int32)
    )
