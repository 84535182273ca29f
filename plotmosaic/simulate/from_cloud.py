"""Virtual scans cut from a real point cloud: what a scanner at a given spot would have seen, with exact truth.

API (all coordinates float64; UTM clouds are processed in a local frame around an offset):

    cut_views(points, positions, seed=0, config=None, **settings) -> list[View]
        points     (N, 3) cloud in its file coordinates
        positions  [(x, y) or (x, y, z), ...] in the same coordinates; (x, y): the scanner stands
                   `height_above_ground` above the local ground (a low z percentile near (x, y))
        settings   any field of `CutConfig` (voxel, max_range, full_density_range, range_noise, ...)
        View.points  (n, 3) the points seen, in the view's own random scanner frame (scanner at 0)
        View.truth   4x4 view frame -> cloud file frame (apply_transform(truth, points) == points[index],
                     exactly up to float64 rounding when range_noise = 0)
        View.index   indices of the cloud points seen; View.position the scanner (file coordinates)
    grid_positions(points, n, spacing, angle_deg=0) -> [(x, y), ...]   n positions on a grid around the centre
    cut_cloud_to_folder(outdir, cloud_path, positions | n_views + spacing, seed, **settings) -> CutResult
        one LAZ per view (<plot>/<plot>-S<i>.laz, in its own frame), ground_truth.json (Poses: view -> cloud
        file frame, frame "crs" when the cloud has a CRS) and manifest.toml, as `simulate` writes them.

Physics (simulate/sightlines.py): a point is seen when it is within range, survives the range thinning (kept
with probability (r0/r)^2 beyond r0, seeded) and the ray from the scanner to it crosses no occupied voxel of
the cloud's occupancy grid before it. Near the point itself occupancy is ignored over a tolerance that grows
at grazing incidence (from the local surface normal), so a far patch of ground is not hidden by its own
neighbours.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import ValidationError
from scipy.spatial import cKDTree

from plotmosaic.config.cuts import CutConfig
from plotmosaic.config.simulate import TlsConfig
from plotmosaic.errors import InputError
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.frame import translation
from plotmosaic.io.las import STANDARD_ATTRIBUTES, PointCloud, read_cloud, write_cloud
from plotmosaic.manifest import Manifest, Plot, Scan, dump_manifest
from plotmosaic.poses import Poses, ScanPose
from plotmosaic.simulate.run import scan_path
from plotmosaic.simulate.scene import scan_id
from plotmosaic.simulate.sightlines import occupancy_grid, surface_normals, visible
from plotmosaic.simulate.tls import random_pose

# where a scanner standing in a trunk or a bush is moved to
RING_RADII = (0.25, 0.5, 0.75, 1.0, 1.25, 1.5)


@dataclass(frozen=True)
class View:
    points: np.ndarray  # (n, 3) in the view's own scanner frame
    truth: np.ndarray  # 4x4 view frame -> cloud file frame
    index: np.ndarray  # (n,) indices of the cloud points seen
    position: np.ndarray  # scanner position, cloud file coordinates
    stats: dict = field(default_factory=dict)


def make_cut_config(config: CutConfig | None = None, **settings) -> CutConfig:
    """A CutConfig from defaults (or `config`) and keyword settings; `None` values are ignored."""
    data = (config or CutConfig()).model_dump()
    for key, value in settings.items():
        if key not in data:
            raise InputError(f"unknown cut setting {key!r} (choose from {', '.join(data)})")
        if value is not None:
            data[key] = value
    try:
        return CutConfig.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        raise InputError(f"cut setting {'.'.join(map(str, err['loc']))}: {err['msg']}") from None


# ---------------------------------------------------------------- positions


def grid_positions(
    points: np.ndarray, n: int, spacing: float, angle_deg: float = 0.0
) -> list[tuple[float, float]]:
    """`n` scanner positions on a square grid `spacing` apart, centred on the cloud's xy bounding box."""
    if n < 1 or spacing <= 0:
        raise InputError(
            f"--views {n} --spacing {spacing}: need at least one view and a positive spacing"
        )
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    centre = (xy.min(axis=0) + xy.max(axis=0)) / 2.0
    cols = int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / cols))
    grid = [
        ((c - (cols - 1) / 2.0) * spacing, (r - (rows - 1) / 2.0) * spacing)
        for r in range(rows)
        for c in range(cols)
    ][:n]
    a = np.radians(angle_deg)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return [tuple(float(v) for v in centre + rot @ np.array(g)) for g in grid]


def parse_positions(text: str) -> list[tuple[float, ...]]:
    """'x,y;x,y' or 'x,y,z;...' -> list of tuples, one-line errors naming the entry."""
    out = []
    for k, entry in enumerate([e for e in text.split(";") if e.strip()], start=1):
        try:
            values = tuple(float(v) for v in entry.split(","))
        except ValueError:
            raise InputError(
                f"--positions: entry {k} ({entry.strip()!r}) is not x,y or x,y,z numbers"
            ) from None
        if len(values) not in (2, 3) or not np.isfinite(values).all():
            raise InputError(
                f"--positions: entry {k} ({entry.strip()!r}) is not x,y or x,y,z numbers"
            )
        out.append(values)
    if not out:
        raise InputError("--positions: no positions given (write 'x,y;x,y')")
    return out


# ---------------------------------------------------------------- geometry helpers


def _ground_z(xy_tree: cKDTree, z: np.ndarray, xy: np.ndarray, cfg: CutConfig) -> float:
    near = xy_tree.query_ball_point(xy, cfg.ground_radius)
    if len(near) < 10:  # sparse spot: the nearest points still say where the ground is
        dist, near = xy_tree.query(xy, k=min(50, len(z)))
        if float(np.min(dist)) > 5.0:
            raise InputError(
                f"scanner position ({xy[0]:.2f}, {xy[1]:.2f}) is {float(np.min(dist)):.1f} m from the nearest point of the cloud"
            )
    return float(np.percentile(z[np.atleast_1d(near)], cfg.ground_percentile))


def _place(
    tree: cKDTree, xy_tree: cKDTree, local: np.ndarray, pos: tuple, cfg: CutConfig, k: int
) -> np.ndarray:
    """Scanner position (local frame) for a user position, moved off a trunk or bush if it stands in one."""
    if len(pos) == 3:
        return np.asarray(pos, dtype=np.float64)
    xy0 = np.asarray(pos[:2], dtype=np.float64)
    candidates = [xy0] + [
        xy0 + r * np.array([np.cos(a), np.sin(a)])
        for r in RING_RADII
        for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)
    ]
    for xy in candidates:
        s = np.array(
            [xy[0], xy[1], _ground_z(xy_tree, local[:, 2], xy, cfg) + cfg.height_above_ground]
        )
        if cfg.clearance == 0 or not (
            tree.query_ball_point(s, cfg.clearance) or _enclosed(tree, local, s, cfg.clearance)
        ):
            return s
    raise InputError(
        f"position {k + 1}: no free space for a scanner within {RING_RADII[-1]} m (clearance {cfg.clearance} m)"
    )


def _enclosed(tree: cKDTree, local: np.ndarray, s: np.ndarray, clearance: float) -> bool:
    """Inside a (hollow, surface-only) trunk: points within 2 x clearance in every one of 8 horizontal sectors."""
    near = np.asarray(tree.query_ball_point(s, 2 * clearance + 1.0), dtype=np.int64)
    if len(near) == 0:
        return False
    d = local[near] - s
    ring = (np.hypot(d[:, 0], d[:, 1]) < 2 * clearance) & (np.abs(d[:, 2]) < 1.0)
    sectors = np.floor((np.arctan2(d[ring, 1], d[ring, 0]) + np.pi) / (np.pi / 4)).astype(int) % 8
    return len(np.unique(sectors)) == 8


def _frame_rotation(rng: np.random.Generator, max_tilt_deg: float) -> np.ndarray:
    """A random heading in [0, 360) and a tilt up to `max_tilt_deg` (the simulator's tripod model)."""
    return random_pose(np.zeros(3), TlsConfig(max_tilt_deg=max_tilt_deg), rng)[:3, :3]


# ---------------------------------------------------------------- the cut


def cut_views(
    points: np.ndarray, positions: list, seed: int = 0, config: CutConfig | None = None, **settings
) -> list[View]:
    """One virtual scan per position (see the module docstring); same inputs + seed = same views."""
    cfg = make_cut_config(config, **settings)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) < cfg.min_points:
        raise InputError(f"cloud has {len(pts)} points, at least {cfg.min_points} needed")
    if not np.isfinite(pts).all():
        raise InputError("cloud has NaN or infinite coordinates")
    # local frame: UTM keeps its millimetres
    offset = np.floor((pts.min(axis=0) + pts.max(axis=0)) / 2.0)
    local = pts - offset
    tree = cKDTree(local)
    xy_tree = cKDTree(local[:, :2])
    views = []
    for k, pos in enumerate(positions):
        if len(pos) not in (2, 3):
            raise InputError(f"position {k + 1}: give (x, y) or (x, y, z)")
        rel = np.asarray(pos, dtype=np.float64) - offset[: len(pos)]
        scanner = _place(tree, xy_tree, local, tuple(rel), cfg, k)
        rng = np.random.default_rng(np.random.SeedSequence([seed, k]))
        views.append(_cut_one(local, tree, scanner, cfg, rng, offset, k))
    return views


def _cut_one(
    local: np.ndarray,
    tree: cKDTree,
    scanner: np.ndarray,
    cfg: CutConfig,
    rng: np.random.Generator,
    offset: np.ndarray,
    k: int,
) -> View:
    t0 = time.perf_counter()
    R = _frame_rotation(rng, cfg.max_tilt_deg)
    r = np.linalg.norm(local - scanner, axis=1)
    keep_p = np.minimum(1.0, (cfg.full_density_range / np.maximum(r, 1e-9)) ** 2)
    cand = (r >= cfg.min_range) & (rng.random(len(r)) < keep_p)
    if cfg.max_range is not None:
        cand &= r <= cfg.max_range
    idx = np.flatnonzero(cand)
    if len(idx) < cfg.min_points:
        raise InputError(
            f"position {k + 1}: only {len(idx)} points within range (need {cfg.min_points})"
        )
    reach = cfg.max_range if cfg.max_range is not None else float(r.max())
    lo = np.maximum(local.min(axis=0), scanner - reach)
    hi = np.minimum(local.max(axis=0), scanner + reach)
    grid = occupancy_grid(local, lo, hi, cfg)
    cand_pts = local[idx]
    normals = surface_normals(tree, local, cand_pts, cfg.normal_neighbours)
    ray = cand_pts - scanner
    cos = np.abs(np.einsum("ij,ij->i", normals, ray)) / np.maximum(
        np.linalg.norm(ray, axis=1), 1e-9
    )
    # the ray runs within a voxel of the point's own surface over ~voxel / cos(incidence) before it
    tol = np.minimum(
        cfg.tolerance + grid.voxel / np.maximum(cos, 1e-3), max(cfg.max_tolerance, cfg.tolerance)
    )
    seen = visible(grid, scanner, cand_pts, tol, cfg)
    idx = idx[seen]
    if len(idx) < cfg.min_points:
        raise InputError(
            f"position {k + 1}: only {len(idx)} points visible (need {cfg.min_points})"
        )
    rel = local[idx] - scanner
    if cfg.range_noise > 0:
        dist = np.linalg.norm(rel, axis=1)
        rel = rel * ((dist + rng.normal(0.0, cfg.range_noise, len(dist))) / dist)[:, None]
    view_pts = rel @ R  # R.T @ rel per row: cloud axes -> view axes
    truth = translation(offset) @ translation(scanner)
    truth[:3, :3] = R
    stats = {
        "candidates": int(cand.sum()),
        "seen": len(idx),
        "voxel": grid.voxel,
        "seconds": time.perf_counter() - t0,
        "within_5m": float(np.mean(np.linalg.norm(rel, axis=1) <= 5.0)),
    }
    return View(view_pts, truth, idx, scanner + offset, stats)


# ---------------------------------------------------------------- files


@dataclass(frozen=True)
class CutResult:
    outdir: Path
    manifest_path: Path
    ground_truth_path: Path
    scan_paths: dict[str, Path]
    points: dict[str, int]
    positions: dict[str, list[float]]
    seconds: dict[str, float]


def cut_cloud_to_folder(
    outdir: str | Path,
    cloud_path: str | Path,
    positions: list | None = None,
    n_views: int | None = None,
    spacing: float | None = None,
    seed: int = 0,
    plot_id: str = "P1",
    **settings,
) -> CutResult:
    """Read a LAS/LAZ cloud, cut views, write one LAZ per view + ground_truth.json + manifest.toml into `outdir`."""
    cfg = make_cut_config(None, **settings)
    t0 = time.perf_counter()
    cloud = read_cloud(cloud_path, attributes=[n for n in STANDARD_ATTRIBUTES if n != "gps_time"])
    t_read = time.perf_counter() - t0
    if positions is None:
        if n_views is None or spacing is None:
            raise InputError("--from-cloud needs --positions 'x,y;x,y' or --views N --spacing M")
        positions = grid_positions(cloud.xyz, n_views, spacing)
    views = cut_views(cloud.xyz, positions, seed, cfg)
    outdir = Path(outdir)
    crs = cloud.crs
    crs_text = None
    if crs is not None:
        auth = crs.to_authority()
        crs_text = f"{auth[0]}:{auth[1]}" if auth else crs.to_wkt()
    scans, poses, paths, points, where = [], {}, {}, {}, {}
    for k, view in enumerate(views):
        sid = scan_id(plot_id, k)
        rel = scan_path(plot_id, sid)
        attrs = {n: v[view.index] for n, v in cloud.attrs.items()}
        paths[sid] = write_cloud(outdir / rel, PointCloud(view.points, attrs))
        poses[sid] = ScanPose(view.truth, plot=plot_id, extra={"cut": view.stats})
        points[sid] = len(view.points)
        where[sid] = [float(v) for v in view.position]
        scans.append(Scan(id=sid, path=rel, kind="tls", reference=k == 0))
    manifest = Manifest(
        name=f"virtual scans of {Path(cloud_path).name} (seed {seed})",
        plots=[Plot(id=plot_id, crs=crs_text, scans=scans)],
    )
    manifest_path = write_text_atomic(outdir / "manifest.toml", dump_manifest(manifest))
    extra = {
        "from_cloud": {
            "source": str(cloud_path),
            "seed": seed,
            "positions": where,
            "settings": cfg.model_dump(),
        }
    }
    truth = Poses(
        scans=poses,
        frame="crs" if crs is not None else "plot",
        crs=crs.to_wkt() if crs is not None else None,
        extra=extra,
    )
    truth_path = truth.save(outdir / "ground_truth.json")
    return CutResult(
        outdir,
        manifest_path,
        truth_path,
        paths,
        points,
        where,
        {"read": t_read, "total": time.perf_counter() - t0},
    )
