"""A forest drawn as points, not ray cast: what a simulator that places points on surfaces and in
crown volumes gives (another group's forests, issue 53).

One world: undulating ground, leaning tapering stems, crown ellipsoids, shrubs (DrawnConfig). Each
scan draws its own points, density falling as 1/r^2 from its levelled scanner within its range:
ground and stem surfaces (the scanner's side of each stem: no other occlusion), and foliage
scattered through the crowns and shrubs, drawn anew for every scan (no surface two scans share).
Written as `simulate` writes a plot: one LAZ a scan in its scanner frame (random heading, levelled),
ground_truth.json (scanner frame -> UTM) and manifest.toml.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plotmosaic.config.cuts import DrawnConfig
from plotmosaic.config.simulate import CRS_EPSG, PRESETS
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.las import PointCloud, write_cloud
from plotmosaic.manifest import Manifest, Plot, Scan, dump_manifest
from plotmosaic.poses import Poses, ScanPose
from plotmosaic.simulate.run import crs_wkt, scan_path
from plotmosaic.simulate.scene import scan_id


@dataclass(frozen=True)
class _Tree:
    base: np.ndarray  # stem base on the ground
    axis: np.ndarray  # unit stem axis (leaning)
    height: float
    dbh: float
    crown_base: float  # along the axis
    crown_radius: float


@dataclass(frozen=True)
class DrawnWorld:
    config: DrawnConfig
    trees: tuple[_Tree, ...]
    shrubs: np.ndarray  # (S, 4) centre x, y, z and radius


def ground_z(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The undulating, gently sloping ground."""
    return (
        0.9 * np.sin(x / 7.0 + 1.0) * np.cos(y / 9.0)
        + 0.4 * np.sin(x / 3.1) * np.sin(y / 4.3)
        + 0.06 * x
    )


def drawn_world(config: DrawnConfig, rng: np.random.Generator) -> DrawnWorld:
    """Trees at least 2.5 m apart on the plot, and shrubs."""
    half = config.plot_m / 2
    kept: list[np.ndarray] = []
    for p in rng.uniform(-half, half, (max(1, 5 * config.trees), 2)):
        if len(kept) < config.trees and all(np.linalg.norm(p - q) > 2.5 for q in kept):
            kept.append(p)
    trees = []
    for x, y in kept:
        height, dbh = rng.uniform(*config.tree_height_m), rng.uniform(*config.dbh_m)
        lean, azimuth = np.radians(rng.uniform(0, config.max_lean_deg)), rng.uniform(0, 2 * np.pi)
        axis = np.array(
            [np.sin(lean) * np.cos(azimuth), np.sin(lean) * np.sin(azimuth), np.cos(lean)]
        )
        base = np.array([x, y, float(ground_z(np.array(x), np.array(y)))])
        trees.append(
            _Tree(base, axis, height, dbh, rng.uniform(0.35, 0.6) * height, rng.uniform(2.0, 4.0))
        )
    sx, sy = rng.uniform(-half, half, (2, config.shrubs))
    radius = rng.uniform(0.4, 1.2, config.shrubs)
    shrubs = np.column_stack([sx, sy, ground_z(sx, sy) + radius, radius])
    return DrawnWorld(config, tuple(trees), shrubs)


def _in_balls(centres: np.ndarray, radii: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    d = rng.normal(size=centres.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return centres + d * rng.random((len(centres), 1)) ** (1 / 3) * radii


def draw_scan(world: DrawnWorld, scanner: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The points one scanner at `scanner` (local frame) draws, in the local frame."""
    c = world.config
    n, half = c.points_per_scan, c.plot_m / 2
    ground, stems, crowns, shrubs = c.shares
    r = rng.uniform(0.8, c.max_range_m, int(ground * n))  # r uniform: areal density 1/r^2
    a = rng.uniform(0, 2 * np.pi, len(r))
    x, y = scanner[0] + r * np.cos(a), scanner[1] + r * np.sin(a)
    inside = (np.abs(x) < half) & (np.abs(y) < half)
    parts = [np.column_stack([x[inside], y[inside], ground_z(x[inside], y[inside])])]
    if world.trees:
        d = np.array([np.linalg.norm(t.base[:2] - scanner[:2]) for t in world.trees])
        w = (d < c.max_range_m) / np.maximum(d, 3.0) ** 2
        w = w / w.sum() if w.sum() > 0 else np.full(len(d), 1.0 / len(d))
        for t, k, m in zip(
            world.trees, rng.multinomial(int(stems * n), w), rng.multinomial(int(crowns * n), w)
        ):
            h = rng.uniform(0, 0.85 * t.height, k)
            radius = t.dbh / 2 * (1 - h / t.height) * (1 + 0.2 * np.clip(1.3 - h, 0, None))
            face = np.arctan2(scanner[1] - t.base[1], scanner[0] - t.base[0])
            ang = face + rng.uniform(-np.pi / 2, np.pi / 2, k)
            ring = np.column_stack([np.cos(ang), np.sin(ang), np.zeros(k)])
            parts.append(t.base + h[:, None] * t.axis + radius[:, None] * ring)
            half_len = (t.height - t.crown_base) / 2
            centre = t.base + (t.crown_base + half_len) * t.axis
            radii = np.array([t.crown_radius, t.crown_radius, half_len])
            parts.append(_in_balls(np.repeat(centre[None], m, axis=0), radii, rng))
    if len(world.shrubs):
        d = np.linalg.norm(world.shrubs[:, :2] - scanner[:2], axis=1)
        w = (d < c.max_range_m) / np.maximum(d, 2.0) ** 2
        if w.sum() > 0:
            which = rng.choice(len(w), int(shrubs * n), p=w / w.sum())
            parts.append(_in_balls(world.shrubs[which, :3], world.shrubs[which, 3:4], rng))
    pts = np.vstack(parts)
    pts = pts[np.linalg.norm(pts - scanner, axis=1) <= c.max_range_m]
    return pts + rng.normal(0, c.range_noise_m, pts.shape)


def drawn_plot(outdir: str | Path, seed: int = 0, config: DrawnConfig | None = None) -> Path:
    """Draw every scan of the plot into `outdir` (LAZ per scan, ground_truth.json, manifest.toml);
    returns the manifest's path. The same (config, seed) always gives the same files."""
    config = config or DrawnConfig()
    outdir = Path(outdir)
    rng_world, rng_scans = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))
    world = drawn_world(config, rng_world)
    origin = np.asarray(PRESETS["small"].origin, dtype=float)
    scans, poses = [], {}
    for k, (x, y) in enumerate(config.scan_layout):
        xy = np.array([x, y]) + rng_scans.normal(0, 0.3, 2)
        scanner = np.array([*xy, float(ground_z(xy[:1], xy[1:])[0]) + config.height_m])
        pts = draw_scan(world, scanner, rng_scans)
        heading = rng_scans.uniform(0, 2 * np.pi)
        c, s = np.cos(heading), np.sin(heading)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, scanner + origin  # levelled scanner frame -> UTM
        sid = scan_id("P1", k)
        write_cloud(outdir / scan_path("P1", sid), PointCloud((pts - scanner) @ R))
        poses[sid] = ScanPose(T, plot="P1")
        scans.append(Scan(id=sid, path=scan_path("P1", sid), kind="tls", reference=k == 0))
    crs = f"EPSG:{CRS_EPSG}"
    manifest = Manifest(
        name=f"forest drawn as points (seed {seed})", plots=[Plot(id="P1", crs=crs, scans=scans)]
    )
    path = write_text_atomic(outdir / "manifest.toml", dump_manifest(manifest))
    extra = {"drawn": {"seed": seed, "config": config.model_dump()}}
    Poses(scans=poses, frame="crs", crs=crs_wkt(), extra=extra).save(outdir / "ground_truth.json")
    return path


def drawn_scan(seed: int = 0, config: DrawnConfig | None = None) -> np.ndarray:
    """One scan's points from the plot centre, in its levelled scanner frame (the scanner at 0)."""
    config = config or DrawnConfig()
    rng_world, rng_scan = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))
    world = drawn_world(config, rng_world)
    scanner = np.array([0.0, 0.0, float(ground_z(np.zeros(1), np.zeros(1))[0]) + config.height_m])
    return draw_scan(world, scanner, rng_scan) - scanner
