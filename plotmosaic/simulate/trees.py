"""Trees: tapered, leaning stems with branches, and conifer or broadleaf crowns made of many small
randomly oriented foliage elements; where they stand, and how detailed each is. `crowns` scatters
the same foliage through the crown volume without branches, or leaves bare stems.

Foliage is deliberately a cloud of small elements: normals there are random, while ground and
stems are smooth. That contrast is what the structural-complexity grouping lives on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.config.simulate import ForestConfig
from plotmosaic.simulate.mesh import (
    FOLIAGE,
    WOODY,
    Mesh,
    orthonormal_frame,
    random_elements,
    tubes,
    unit,
)
from plotmosaic.simulate.terrain import Terrain


@dataclass(frozen=True)
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


def place(
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


def _stem(
    tree: Tree, z0: float, cfg: ForestConfig, rng, owner: int, sweep: float, length: float
) -> tuple[np.ndarray, list[Mesh]]:
    """The stem's base (0.3 m into the ground) and its tube, `length` m along its lean, bowed by up
    to `sweep` of the tree's height."""
    base = np.array([tree.x, tree.y, z0 - 0.3])
    bow = unit(np.cross(tree.lean, rng.normal(size=3))) * rng.uniform(0, sweep) * tree.height
    centres, h = _stem_paths(base, tree.lean, length, 0.75 if tree.detailed else 2.0, bow)
    radius = _stem_radius(h - 0.3, tree.dbh, tree.height)
    sides = cfg.stem_sides if tree.detailed else 8
    return base, [tubes(centres[None], radius[None], sides, WOODY, [owner])]


def conifer_meshes(
    tree: Tree, z0: float, cfg: ForestConfig, rng, owner: int, stubs: bool = True
) -> list[Mesh]:
    base, meshes = _stem(tree, z0, cfg, rng, owner, 0.01, tree.height + 0.3)
    if cfg.crowns == "none":
        return meshes
    # Whorls of branches through the crown; their length shrinks toward the top (a cone).
    whorl_h = np.arange(tree.crown_base, tree.height * 0.96, rng.uniform(0.5, 0.8))
    per = rng.integers(3, 7, len(whorl_h))
    hb = np.repeat(whorl_h, per)
    az = rng.uniform(0, 2 * np.pi, len(hb))
    frac = (tree.height - hb) / max(tree.height - tree.crown_base, 1e-3)
    length = tree.crown_radius * frac**0.9 * rng.uniform(0.75, 1.1, len(hb)) + 0.25
    if cfg.crowns == "scattered":
        # the foliage the whorls would carry, spread through the crown cone instead
        factor = 1 if tree.detailed else cfg.coarse_factor
        n = int(np.maximum(1, (cfg.foliage_per_m * length / factor).astype(int)).sum())
        pts = _in_cone(base, tree, n, rng)
        size = rng.uniform(*cfg.leaf_size_m, n) * np.sqrt(factor)
        meshes.append(random_elements(pts, size, rng, FOLIAGE, owner))
        return meshes
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
    # far from every plot: straight three-sided branches are enough for ALS
    path = [start, mid, end] if tree.detailed else [start, end]
    radii = [r0, r0 * 0.6, r0 * 0.25] if tree.detailed else [r0, r0 * 0.25]
    sides = 6 if tree.detailed else 3
    owners = np.full(len(start), owner)
    meshes.append(tubes(np.stack(path, 1), np.column_stack(radii), sides, WOODY, owners, cap=False))
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


def _in_cone(base: np.ndarray, tree: Tree, n: int, rng) -> np.ndarray:
    """`n` points uniform in a conifer's crown cone (crown base to top, around the leaning stem)."""
    depth = rng.random(n) ** (1 / 3)  # volume below the apex grows as depth cubed
    h = tree.height - (tree.height - tree.crown_base) * depth
    r = tree.crown_radius * depth * np.sqrt(rng.random(n))
    a = rng.uniform(0, 2 * np.pi, n)
    u, v = orthonormal_frame(tree.lean)
    return (
        base
        + (h + 0.3)[:, None] * tree.lean
        + (r * np.cos(a))[:, None] * u
        + (r * np.sin(a))[:, None] * v
    )


def broadleaf_meshes(tree: Tree, z0: float, cfg: ForestConfig, rng, owner: int) -> list[Mesh]:
    base, meshes = _stem(tree, z0, cfg, rng, owner, 0.015, 0.8 * tree.height + 0.3)
    if cfg.crowns == "none":
        return meshes
    crown_len = tree.height - tree.crown_base
    centre = base + (tree.crown_base + 0.3 + crown_len / 2) * tree.lean
    radii = np.array([tree.crown_radius, tree.crown_radius, crown_len / 2])
    factor = 1 if tree.detailed else cfg.coarse_factor
    # leaf count grows with crown volume
    scale = (tree.crown_radius / 4.0) ** 2 * (crown_len / 10.0)
    total = max(20, int(cfg.broadleaf_leaves * np.clip(scale, 0.2, 2.0) / factor))
    if cfg.crowns == "scattered":  # the same leaves through the whole crown ellipsoid, no scaffold
        pts = centre + unit(rng.normal(size=(total, 3))) * radii * rng.random((total, 1)) ** (1 / 3)
        size = rng.uniform(*cfg.leaf_size_m, total) * np.sqrt(factor)
        meshes.append(random_elements(pts, size, rng, FOLIAGE, owner, quads=True))
        return meshes
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
    widths = np.column_stack([np.full(n, r0), np.full(n, r0 * 0.65), np.full(n, r0 * 0.3)])
    sides = 8 if tree.detailed else 4
    path = np.stack([start, mid, target], 1)
    meshes.append(tubes(path, widths, sides, WOODY, np.full(n, owner), cap=False))
    k = int(rng.integers(2, 4))
    fs = np.repeat(mid, k, 0) + rng.uniform(0, 1, (n * k, 1)) * (
        np.repeat(target, k, 0) - np.repeat(mid, k, 0)
    )
    fe = fs + unit(rng.normal(0, 1, (n * k, 3)) + [0, 0, 0.8]) * (
        0.25 * radii.mean() * rng.uniform(0.6, 1.2, (n * k, 1))
    )
    widths = np.column_stack([np.full(n * k, r0 * 0.3), np.full(n * k, r0 * 0.12)])
    sides = 5 if tree.detailed else 3
    meshes.append(
        tubes(np.stack([fs, fe], 1), widths, sides, WOODY, np.full(n * k, owner), cap=False)
    )
    # Leaves in clumps filling the outer shell of the crown ellipsoid.
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
    xy = place(n, extent, 1.2 + 6.0 * dbh, avoid, cfg.clearance_m, rng)
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
        near = not far(np.array([[x, y]]), plot_centres, cfg)[0]
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


def far(xy: np.ndarray, plot_centres: np.ndarray, cfg: ForestConfig) -> np.ndarray:
    """Objects beyond `detail_radius_m` of every plot centre get coarse geometry (only ALS sees them)."""
    if len(xy) == 0:
        return np.zeros(0, bool)
    return cKDTree(plot_centres).query(xy)[0] > cfg.detail_radius_m
