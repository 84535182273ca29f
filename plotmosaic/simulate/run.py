"""`simulate`: build a world, scan it, write LAZ files, ground truth and a manifest.

Layout of OUTDIR:
    manifest.toml           region form, [[als]] + [[plots]] with crs EPSG:26912
    ground_truth.json       Poses(frame="crs"): scanner frame -> UTM for every TLS scan
    <plot>/<plot>-S<i>.laz  TLS scans in their scanner frames (extra dim `label`)
    als/als.laz             the ALS tile in UTM (CRS written)
    figures/*.png           pictures (optional)
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import ValidationError
from pyproj import CRS

from plotmosaic.config.simulate import ALIASES, CRS_EPSG, PRESETS, SimulationConfig
from plotmosaic.errors import InputError
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.frame import translation
from plotmosaic.io.las import PointCloud, write_cloud
from plotmosaic.manifest import AlsTile, Manifest, Plot, Scan, dump_manifest
from plotmosaic.poses import Poses, ScanPose
from plotmosaic.simulate.als import scan_als
from plotmosaic.simulate.figures import make_figures
from plotmosaic.simulate.scene import Scene, World, build_world, square_extent
from plotmosaic.simulate.tls import random_pose, scan_tls

FIGURE_SAMPLE = 400_000  # points per scan kept in memory for the pictures


def make_config(preset: str = "small", **overrides) -> SimulationConfig:
    """A preset with overrides (`points_per_scan=...`, dotted `tls.max_range_m=...` via a dict, or top-level fields).

    `None` values are ignored so a CLI can pass every option through.
    """
    if preset not in PRESETS:
        raise InputError(f"unknown preset {preset!r} (choose from {', '.join(PRESETS)})")
    data = PRESETS[preset].model_dump()
    for key, value in overrides.items():
        if value is None:
            continue
        *tables, name = ALIASES.get(key, key).split(".")
        node = data
        for table in tables:
            node = node.get(table) if isinstance(node, dict) else None
        if not isinstance(node, dict) or name not in node:
            raise InputError(f"unknown simulation setting {key!r}")
        node[name] = value
    try:
        return SimulationConfig.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        raise InputError(
            f"simulation setting {'.'.join(map(str, err['loc']))}: {err['msg']}"
        ) from None


@dataclass(frozen=True)
class SimulationResult:
    outdir: Path
    manifest_path: Path
    ground_truth_path: Path
    scan_paths: dict[str, Path]
    als_paths: list[Path]
    figures: list[Path]
    config: SimulationConfig
    seed: int
    points: dict[str, int] = field(default_factory=dict)  # per scan id, and "als"
    als_density: float = 0.0  # achieved returns per m2 over the tile
    als_extent: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  # local frame
    seconds: dict[str, float] = field(default_factory=dict)


Progress = Callable[[str, int, int], None]  # (what, done, total)


def scan_path(plot_id: str, scan_id: str) -> Path:
    """Where a TLS scan goes, relative to OUTDIR (and to the manifest)."""
    return Path(plot_id) / f"{scan_id}.laz"


ALS_PATH = Path("als") / "als.laz"


def crs_wkt() -> str:
    return CRS.from_epsg(CRS_EPSG).to_wkt()


def scanner_pose(world: World, xy: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Scanner frame -> local frame for a tripod standing at xy."""
    z = world.terrain.height(np.array([xy[0]]), np.array([xy[1]]))[0] + world.config.tls.height_m
    return random_pose(np.array([xy[0], xy[1], z]), world.config.tls, rng)


def als_extent(world: World) -> tuple[float, float, float, float]:
    xy = np.array([s.xy for s in world.sites])
    ext = square_extent(xy, world.config.als.margin_m)
    e = world.extent  # never beyond the scene
    return (
        max(ext[0], e[0] + 1),
        max(ext[1], e[1] + 1),
        min(ext[2], e[2] - 1),
        min(ext[3], e[3] - 1),
    )


@dataclass(frozen=True, kw_only=True)
class _Streams:
    """The run's random streams, one per use, all from the seed."""

    pose: np.random.Generator
    tls: np.random.Generator
    als: np.random.Generator
    approx: np.random.Generator
    figures: np.random.Generator


@dataclass(frozen=True, kw_only=True)
class _TlsScans:
    """What scanning every site gave: files, true poses, manifest entries and picture samples."""

    scan_paths: dict[str, Path]
    poses: dict[str, ScanPose]
    points: dict[str, int]
    samples: dict[str, PointCloud]
    plots: dict[str, list[Scan]]
    scenes: dict[bool, Scene]  # ray casters built so far, by "after the fire"


@dataclass(frozen=True, kw_only=True)
class _AlsTile:
    cloud: PointCloud  # UTM
    path: Path
    extent: tuple[float, float, float, float]  # local frame


def simulate(
    outdir: str | Path,
    preset: str = "small",
    seed: int = 0,
    figures: bool = False,
    progress: Progress | None = None,
    config: SimulationConfig | None = None,
    **overrides,
) -> SimulationResult:
    """Simulate a forest plot (or region) with TLS scans, an ALS tile and ground truth into `outdir`."""
    t_start = time.perf_counter()
    outdir = Path(outdir)
    cfg = config if config is not None else make_config(preset, **overrides)
    world = build_world(cfg, seed)
    seconds = {"world": time.perf_counter() - t_start}
    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence([seed, 1]).spawn(5)]
    streams = _Streams(pose=rngs[0], tls=rngs[1], als=rngs[2], approx=rngs[3], figures=rngs[4])
    total = len(world.sites) + 1
    t0 = time.perf_counter()
    tls = _scan_sites(world, outdir, streams, figures, progress)
    seconds["tls"] = time.perf_counter() - t0
    if progress:
        progress("ALS", total - 1, total)
    t0 = time.perf_counter()
    als = _scan_als_tile(world, tls.scenes, outdir, streams.als)
    seconds["als"] = time.perf_counter() - t0
    if progress:
        progress("done", total, total)
    manifest_path, truth_path = _write_manifest_and_truth(outdir, world, tls)
    figure_paths = []
    if figures:
        t0 = time.perf_counter()
        als_sample = _sample(als.cloud, streams.figures)
        figure_paths = make_figures(outdir / "figures", world, tls.samples, tls.poses, als_sample)
        seconds["figures"] = time.perf_counter() - t0
    extent = als.extent
    area = (extent[2] - extent[0]) * (extent[3] - extent[1])
    seconds["total"] = time.perf_counter() - t_start
    return SimulationResult(
        outdir=outdir,
        manifest_path=manifest_path,
        ground_truth_path=truth_path,
        scan_paths=tls.scan_paths,
        als_paths=[als.path],
        figures=figure_paths,
        config=cfg,
        seed=seed,
        points={**tls.points, "als": len(als.cloud)},
        als_density=len(als.cloud) / area,
        als_extent=extent,
        seconds=seconds,
    )


def _scan_sites(
    world: World, outdir: Path, streams: _Streams, figures: bool, progress: Progress | None
) -> _TlsScans:
    """Scan every site in turn and write its LAZ (scanner frame); poses in UTM."""
    cfg = world.config
    to_world = translation(world.origin)
    scenes: dict[bool, Scene] = {}
    scan_paths: dict[str, Path] = {}
    poses: dict[str, ScanPose] = {}
    points: dict[str, int] = {}
    samples: dict[str, PointCloud] = {}
    plots: dict[str, list[Scan]] = {}
    total = len(world.sites) + 1
    for k, site in enumerate(world.sites):
        if progress:
            progress(f"scan {site.scan_id}", k, total)
        post = site.post and world.post_mesh is not None
        if post not in scenes:
            scenes[post] = Scene(world.mesh_for(site))
        pose_local = scanner_pose(world, site.xy, streams.pose)
        cloud = scan_tls(scenes[post], pose_local, cfg.tls, streams.tls, t0=1000.0 + 600.0 * k)
        rel = scan_path(site.plot_id, site.scan_id)
        scan_paths[site.scan_id] = write_cloud(outdir / rel, cloud)
        T = to_world @ pose_local  # scanner frame -> UTM, float64
        poses[site.scan_id] = ScanPose(T, plot=site.plot_id)
        points[site.scan_id] = len(cloud)
        if figures:
            samples[site.scan_id] = _sample(cloud, streams.figures)
        approx = None
        if cfg.approx_positions:
            noise = streams.approx.normal(0, cfg.approx_sigma_m, 3)
            approx = tuple(float(v) for v in T[:3, 3] + noise)
        scan = Scan(
            id=site.scan_id,
            path=rel,
            kind="tls",
            reference=not plots.get(site.plot_id),
            approx_position=approx,
            approx_position_frame="crs",
        )
        plots.setdefault(site.plot_id, []).append(scan)
    return _TlsScans(
        scan_paths=scan_paths,
        poses=poses,
        points=points,
        samples=samples,
        plots=plots,
        scenes=scenes,
    )


def _scan_als_tile(
    world: World, scenes: dict[bool, Scene], outdir: Path, rng: np.random.Generator
) -> _AlsTile:
    """The ALS tile over the sites (the scene before any fire), written in UTM with its CRS."""
    scene = scenes[False] if False in scenes else Scene(world.mesh)
    extent = als_extent(world)
    als = scan_als(scene, world.terrain, extent, world.config.als, rng)
    als_world = PointCloud(als.xyz + world.origin, als.attrs)
    path = write_cloud(outdir / ALS_PATH, als_world, crs=CRS.from_epsg(CRS_EPSG))
    return _AlsTile(cloud=als_world, path=path, extent=extent)


def _write_manifest_and_truth(outdir: Path, world: World, tls: _TlsScans) -> tuple[Path, Path]:
    """manifest.toml (plots + the ALS tile) and ground_truth.json (every TLS pose, UTM)."""
    cfg, seed, origin = world.config, world.seed, world.origin
    crs = f"EPSG:{CRS_EPSG}"
    manifest = Manifest(
        name=f"simulated {cfg.name} (seed {seed})",
        plots=[Plot(id=pid, crs=crs, scans=scans) for pid, scans in tls.plots.items()],
        als=[AlsTile(path=ALS_PATH)],
    )
    manifest_path = write_text_atomic(outdir / "manifest.toml", dump_manifest(manifest))
    truth = Poses(
        scans=tls.poses,
        frame="crs",
        crs=crs_wkt(),
        extra={
            "simulation": {"preset": cfg.name, "seed": seed, "origin": [float(v) for v in origin]}
        },
    )
    return manifest_path, truth.save(outdir / "ground_truth.json")


def _sample(cloud: PointCloud, rng: np.random.Generator) -> PointCloud:
    if len(cloud) <= FIGURE_SAMPLE:
        return cloud
    return cloud.select(np.sort(rng.choice(len(cloud), FIGURE_SAMPLE, replace=False)))
