"""Every knob of the forest simulator, with defaults, and the named presets.

Distances in metres, angles in degrees. The scene is built in a local frame (plot P1 centre at
the origin) and `origin` (EPSG:26912, NAD83 / UTM 12N) is added in float64 when files are written.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

CRS_EPSG = 26912
# The paper's layout: a centre scan and four corner scans ~15 x 5 m away.
PAPER_LAYOUT = [(0.0, 0.0), (15.0, 5.0), (-15.0, 5.0), (-15.0, -5.0), (15.0, -5.0)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class TerrainConfig(_Model):
    cell: float = Field(0.25, gt=0.02, description="grid spacing of the terrain mesh")
    slope_deg: float = Field(8.0, ge=0, le=40)
    slope_azimuth_deg: float = 35.0
    undulation_m: float = Field(1.2, ge=0, description="amplitude of the smooth undulations")
    undulation_wavelength_m: tuple[float, float] = (12.0, 60.0)
    microrelief_m: float = Field(
        0.08, ge=0, description="hummocks, pits, litter mounds (std); they shadow grazing rays"
    )
    microrelief_scale_m: float = Field(1.2, gt=0)
    roughness_m: float = Field(0.015, ge=0, description="micro-roughness (per-vertex noise, std)")
    flat: bool = Field(
        False, description="near-flat terrain (hard case): no slope, 5 cm undulations"
    )


class ForestConfig(_Model):
    trees_per_ha: float = Field(250.0, ge=0)
    conifer_fraction: float = Field(0.75, ge=0, le=1)
    dbh_range_m: tuple[float, float] = (0.10, 0.80)
    dbh_median_m: float = 0.32
    conifer_height_m: tuple[float, float] = (15.0, 30.0)  # ponderosa
    broadleaf_height_m: tuple[float, float] = (10.0, 20.0)
    max_lean_deg: float = 8.0
    crowns: Literal["branches", "scattered", "none"] = Field(
        "branches",
        description="branches: foliage along branch whorls and scaffolds; scattered: the same foliage"
        " spread through the crown volume, no branches (forests shaped unlike ours, leafy crowns);"
        " none: bare stems (burnt, pruned or dead stands)",
    )
    stem_sides: int = Field(24, ge=8, description="facets around a stem: enough for smooth normals")
    foliage_per_m: float = Field(
        40.0, gt=0, description="foliage elements per metre of conifer branch"
    )
    broadleaf_leaves: int = Field(
        4000, ge=10, description="foliage elements of a full-size broadleaf crown"
    )
    leaf_size_m: tuple[float, float] = (0.06, 0.14)
    detail_radius_m: float = Field(
        70.0, description="trees farther from every plot centre get coarse foliage"
    )
    coarse_factor: int = Field(
        6, ge=1, description="coarse foliage: this many times fewer, larger elements"
    )
    shrubs_per_ha: float = Field(500.0, ge=0)
    shrub_elements: int = Field(300, ge=1)
    saplings_per_ha: float = Field(
        150.0, ge=0, description="young conifers 1.5-5 m tall (understory)"
    )
    # Bunchgrass: it hides the ground from grazing rays, so scans far apart see different ground.
    grass_tufts_per_m2: float = Field(3.0, ge=0)
    grass_blades: int = Field(20, ge=1)
    blade_width_m: tuple[float, float] = (0.01, 0.03)
    grass_height_m: tuple[float, float] = (0.15, 0.5)
    logs_per_ha: float = Field(25.0, ge=0)
    debris_per_ha: float = Field(400.0, ge=0, description="fallen branches on the ground (woody)")
    clearance_m: float = Field(
        1.5, ge=0, description="no stem or shrub this close to a scanner position"
    )


class TlsConfig(_Model):
    points_per_scan: int = Field(
        2_000_000, ge=1000, description="target points; sets the angular step"
    )
    angular_step_deg: float | None = Field(
        None, gt=0, description="fixed angular step (overrides points_per_scan)"
    )
    fov_horizontal_deg: float = 360.0
    fov_vertical_deg: float = 300.0  # BLK360: from 60 deg below the horizon to the zenith
    min_range_m: float = 0.6
    max_range_m: float = 60.0
    range_noise_m: float = 0.002  # sigma = range_noise_m + range_noise_per_m * range (4 mm at 10 m)
    range_noise_per_m: float = 0.00025
    height_m: float = 1.5
    max_tilt_deg: float = 2.0
    position_jitter_m: float = 0.5
    chunk_rays: int = 2_000_000
    intensity: bool = True
    seconds_per_scan: float = 180.0


class AlsConfig(_Model):
    density_per_m2: float = Field(15.0, gt=0, description="all returns per square metre")
    altitude_m: float = 900.0
    fov_deg: float = 40.0
    heading_deg: float = 0.0
    max_returns: int = Field(5, ge=1)
    transmission: float = Field(
        0.55, ge=0, le=1, description="chance a pulse goes on after a foliage/understory hit"
    )
    dead_zone_m: float = Field(1.0, ge=0, description="minimum separation of returns along a pulse")
    range_noise_m: float = 0.03
    margin_m: float = Field(
        15.0, description="tile edge beyond the plot(s) extent (scan positions)"
    )
    chunk_pulses: int = 1_000_000


class FireConfig(_Model):
    grass_removed: float = Field(0.8, ge=0, le=1)
    shrubs_removed: float = Field(0.7, ge=0, le=1)
    post_jitter_m: float = Field(
        0.8, ge=0, description="POST scans stand this far from the PRE positions"
    )


class SimulationConfig(_Model):
    name: str = "small"
    origin: tuple[float, float, float] = (470250.0, 3810150.0, 2100.0)
    plot_centres: list[tuple[float, float]] = Field(default_factory=lambda: [(0.0, 0.0)])
    scan_layout: list[tuple[float, float]] = Field(default_factory=lambda: list(PAPER_LAYOUT))
    scene_margin_m: float = Field(
        35.0, description="scene (terrain, trees) beyond the scan positions"
    )
    prepost: bool = False
    approx_positions: bool = False
    approx_sigma_m: float = Field(3.0, ge=0)
    terrain: TerrainConfig = Field(default_factory=TerrainConfig)
    forest: ForestConfig = Field(default_factory=ForestConfig)
    tls: TlsConfig = Field(default_factory=TlsConfig)
    als: AlsConfig = Field(default_factory=AlsConfig)
    fire: FireConfig = Field(default_factory=FireConfig)


def grid_layout(n_side: int, spacing: float, n: int | None = None) -> list[tuple[float, float]]:
    """Scan positions on an n_side x n_side grid `spacing` apart, centred on the plot centre (first `n` of them)."""
    half = (n_side - 1) / 2.0
    cells = [
        ((i - half) * spacing, (j - half) * spacing) for j in range(n_side) for i in range(n_side)
    ]
    return cells[: n if n is not None else len(cells)]


def grid_centres(n: int, spacing: float) -> list[tuple[float, float]]:
    """`n` plot centres on a near-square grid `spacing` apart, plot P1 at the origin."""
    cols = int(np.ceil(np.sqrt(n)))
    return [(float((k % cols) * spacing), float((k // cols) * spacing)) for k in range(n)]


def _preset(name: str, **changes) -> SimulationConfig:
    data = SimulationConfig(name=name).model_dump()
    for key, value in changes.items():
        node = data
        *parents, last = key.split(".")
        for p in parents:
            node = node[p]
        node[last] = value
    return SimulationConfig.model_validate(data)


PRESETS: dict[str, SimulationConfig] = {
    # Unit tests: a 70 x 50 m scene, coarse foliage, tens of thousands of points a scan.
    "small": _preset(
        "small",
        scene_margin_m=18.0,
        **{
            "terrain.cell": 0.4,
            "forest.foliage_per_m": 14.0,
            "forest.broadleaf_leaves": 1200,
            "forest.leaf_size_m": (0.12, 0.25),
            "forest.shrub_elements": 120,
            "forest.grass_tufts_per_m2": 0.5,  # 50k-point scans cannot resolve blades: keep grass light
            "forest.grass_blades": 8,
            "forest.blade_width_m": (0.02, 0.05),
            "forest.stem_sides": 16,
            "tls.points_per_scan": 50_000,
            "tls.max_range_m": 40.0,
            "als.margin_m": 8.0,
        },
    ),
    # One plot as in the paper: 5 BLK360-like scans, ALS over ~60 x 60 m.
    "paper": _preset("paper", **{"tls.points_per_scan": 4_000_000}),
    # Three plots a few hundred metres apart under one ALS region.
    "region": _preset(
        "region",
        plot_centres=[(0.0, 0.0), (280.0, 90.0), (110.0, 260.0)],
        **{
            "terrain.cell": 0.5,
            "forest.detail_radius_m": 45.0,
            "forest.coarse_factor": 10,
            "tls.points_per_scan": 1_000_000,
            "als.margin_m": 40.0,
        },
    ),
    # Open grassland: no trees or logs, dense grass, a few shrubs.
    "grassland": _preset(
        "grassland",
        **{
            "terrain.slope_deg": 3.0,
            "forest.trees_per_ha": 0.0,
            "forest.logs_per_ha": 0.0,
            "forest.debris_per_ha": 0.0,
            "forest.shrubs_per_ha": 60.0,
            "forest.saplings_per_ha": 0.0,
            "forest.grass_tufts_per_m2": 4.0,
            "tls.points_per_scan": 2_000_000,
        },
    ),
    # The same plot before and after a low-intensity fire that thinned grass and shrubs.
    "prepost": _preset("prepost", prepost=True, **{"tls.points_per_scan": 2_000_000}),
    # A 1-ha inventory plot scanned on a 6 x 6 grid 18 m apart (36 positions, none in the manifest).
    "large": _preset(
        "large",
        scan_layout=grid_layout(6, 18.0),
        scene_margin_m=30.0,
        **{"terrain.cell": 0.5, "forest.detail_radius_m": 75.0, "tls.points_per_scan": 1_000_000},
    ),
    # Ten plots of the paper layout 90 m apart under one ALS survey (a region of 50 scans).
    "region10": _preset(
        "region10",
        plot_centres=grid_centres(10, 90.0),
        scene_margin_m=30.0,
        **{
            "terrain.cell": 0.6,
            "forest.detail_radius_m": 35.0,
            "forest.coarse_factor": 10,
            "forest.grass_tufts_per_m2": 1.0,
            "tls.points_per_scan": 1_000_000,
            "als.margin_m": 25.0,
        },
    ),
    # Dense understorey: shrubs and saplings everywhere, so most returns come from within 5 m of the
    # scanner; three scans 7 m apart (the hard real-forest case of issue 15).
    "understorey": _preset(
        "understorey",
        scan_layout=[(0.0, 0.0), (7.0, 0.0), (3.5, 6.0)],
        scene_margin_m=25.0,
        **{
            "forest.trees_per_ha": 600.0,
            "forest.conifer_fraction": 0.4,
            # a low leafy subcanopy closes the sky within ~5 m
            "forest.broadleaf_height_m": (6.0, 12.0),
            "forest.shrubs_per_ha": 9000.0,
            "forest.saplings_per_ha": 6000.0,
            "forest.clearance_m": 1.0,
            "tls.points_per_scan": 500_000,
            "tls.max_range_m": 40.0,
        },
    ),
    # Another group's forest: leaning stems under crowns of scattered foliage (no branches),
    # understorey, undulating ground; 45 trees on the 40 m plot.
    "scattered": _preset(
        "scattered",
        scan_layout=grid_layout(3, 12.0, 6),
        scene_margin_m=8.0,
        **{
            "forest.crowns": "scattered",
            "forest.trees_per_ha": 280.0,
            "forest.conifer_fraction": 0.5,
            "forest.max_lean_deg": 15.0,
            "tls.points_per_scan": 500_000,
            "tls.max_range_m": 30.0,
            "als.margin_m": 8.0,
        },
    ),
    # An open stand of bare stems (burnt or pruned): no crowns, no shrubs or saplings, a little
    # grass and dead wood; --tree-density sets the stems a hectare (50-400 measured).
    "bare-stems": _preset(
        "bare-stems",
        scan_layout=grid_layout(3, 12.0, 6),
        scene_margin_m=8.0,
        **{
            "forest.crowns": "none",
            "forest.trees_per_ha": 150.0,
            "forest.shrubs_per_ha": 0.0,
            "forest.saplings_per_ha": 0.0,
            "forest.grass_tufts_per_m2": 0.5,
            "forest.logs_per_ha": 10.0,
            "forest.debris_per_ha": 100.0,
            "tls.points_per_scan": 500_000,
            "tls.max_range_m": 30.0,
            "als.margin_m": 8.0,
        },
    ),
}

# Short names for the knobs the CLI and `simulate(**overrides)` expose.
ALIASES = {
    "points_per_scan": "tls.points_per_scan",
    "angular_step": "tls.angular_step_deg",
    "max_range": "tls.max_range_m",
    "als_density": "als.density_per_m2",
    "tree_density": "forest.trees_per_ha",
    "crowns": "forest.crowns",
    "conifer_fraction": "forest.conifer_fraction",
    "shrub_density": "forest.shrubs_per_ha",
    "sapling_density": "forest.saplings_per_ha",
    "grass_density": "forest.grass_tufts_per_m2",
    "flat_terrain": "terrain.flat",
    "slope": "terrain.slope_deg",
}
