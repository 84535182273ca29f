"""Settings of the virtual scans cut out of a real cloud (`simulate --from-cloud`) and of the
forest drawn as points (`simulate --drawn`). Distances in metres, angles in degrees."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from plotmosaic.config.simulate import grid_layout


class CutConfig(BaseModel):
    """How virtual scans are cut out of a real cloud (metres, degrees)."""

    model_config = ConfigDict(extra="forbid")

    voxel: float = Field(
        0.1,
        gt=0.005,
        le=2.0,
        description="occupancy voxel edge: finer than stems, coarser than the point spacing",
    )
    height_above_ground: float = Field(
        1.5, ge=0, le=100, description="tripod height over the local ground for (x, y) positions"
    )
    ground_radius: float = Field(
        2.0,
        gt=0,
        le=50,
        description="horizontal radius around a position where the local ground is read",
    )
    ground_percentile: float = Field(
        2.0,
        ge=0,
        le=50,
        description="low z percentile near the position taken as ground (robust to a few low outliers)",
    )
    min_range: float = Field(
        0.5,
        ge=0,
        le=10,
        description="nothing nearer is seen (the tripod) and occupancy nearer does not block",
    )
    max_range: float | None = Field(
        None, gt=0, description="nothing farther is seen (None: no limit)"
    )
    full_density_range: float = Field(
        5.0,
        gt=0,
        description="r0: beyond it a point is kept with probability (r0/r)^2, as a fixed angular step gives",
    )
    tolerance: float = Field(
        0.05,
        ge=0,
        le=5,
        description="occupied voxels this much (+ a voxel / cos incidence) in front of a point never hide it",
    )
    max_tolerance: float = Field(
        1.5,
        ge=0,
        le=10,
        description="cap of the grazing-incidence tolerance (a far ground patch is not hidden by itself)",
    )
    normal_neighbours: int = Field(
        12, ge=4, le=100, description="neighbours of the local plane that gives the incidence angle"
    )
    range_noise: float = Field(
        0.0,
        ge=0,
        le=0.5,
        description="std of the noise added along each ray (0: points exactly as in the cloud)",
    )
    max_tilt_deg: float = Field(
        2.0,
        ge=0,
        le=90,
        description="tilt of each view's random frame (a levelled tripod), heading uniform",
    )
    clearance: float = Field(
        0.3,
        ge=0,
        le=5,
        description="a scanner needs this much free space (and no trunk around it); otherwise it is moved up to 1.5 m",
    )
    max_grid_cells: int = Field(
        200_000_000,
        ge=1_000_000,
        description="bytes of the dense occupancy grid of one view: the voxel grows to fit",
    )
    chunk_samples: int = Field(
        4_000_000, ge=10_000, description="ray samples tested at once (memory ~ 30 bytes each)"
    )
    min_points: int = Field(
        100, ge=1, description="a view with fewer points is an error (a position outside the cloud)"
    )


class DrawnConfig(BaseModel):
    """A forest drawn as points instead of ray cast (simulate/drawn.py): as a simulator that places
    points on surfaces and in crown volumes would give it (metres)."""

    model_config = ConfigDict(extra="forbid")

    plot_m: float = Field(
        40.0, gt=5, le=500, description="side of the square plot the trees stand on"
    )
    trees: int = Field(45, ge=0, le=5000, description="trees on the plot (the issue-53 plot: 45)")
    tree_height_m: tuple[float, float] = (12.0, 25.0)
    dbh_m: tuple[float, float] = (0.15, 0.6)
    max_lean_deg: float = Field(15.0, ge=0, le=45, description="leaning stems, some strongly")
    shrubs: int = Field(60, ge=0, le=100_000, description="shrubs of scattered points")
    scan_layout: list[tuple[float, float]] = Field(
        default_factory=lambda: grid_layout(3, 12.0, 6),
        description="scanner positions (plot centre at the origin): six on a 3 x 2 grid 12 m apart",
    )
    points_per_scan: int = Field(1_500_000, ge=1000, description="points drawn for each scan")
    max_range_m: float = Field(30.0, gt=1, description="nothing farther from a scanner is drawn")
    height_m: float = Field(1.5, ge=0, description="scanner above the ground")
    # shares of a scan's points: ground, stems (their scanner side), crowns, shrubs
    shares: tuple[float, float, float, float] = Field(
        (0.45, 0.03, 0.42, 0.10), description="points on ground, stems, crowns, shrubs"
    )
    range_noise_m: float = Field(0.003, ge=0, le=0.1, description="noise of every point (std)")
