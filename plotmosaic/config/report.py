"""Settings of the registration report (breast-height slice, cloud-to-cloud distances, page)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class SliceConfig(BaseModel):
    """Breast-height slice: where it is cut and how stems are found in it."""

    model_config = ConfigDict(extra="forbid")

    height: float = Field(
        1.3,
        gt=0,
        le=5,
        description="breast height above the local ground (m), the forester's DBH height",
    )
    half_width: float = Field(
        0.05,
        gt=0,
        le=0.5,
        description="half thickness of the slice (m): thin enough for sharp rings",
    )
    dtm_cell: float = Field(
        1.0, gt=0.1, le=10, description="cell of the coarse ground model (m): lowest point per cell"
    )
    dtm_spike: float = Field(
        0.3,
        gt=0,
        le=5,
        description="a cell this much above the opened ground saw no ground (stem base, log)",
    )
    keep_low: float = Field(
        0.5,
        ge=0,
        le=1.2,
        description="per scan, points this close above its own cell minimum are ground, not kept",
    )
    keep_high: float = Field(
        2.5,
        ge=1.4,
        le=10,
        description="per scan, points this far above its own cell minimum cannot be in the slice",
    )
    stratum_voxel: float = Field(
        0.005,
        gt=0,
        le=0.05,
        description="one point per cube (m) of the kept low stratum: bounds memory, keeps mm rings",
    )
    stem_cell: float = Field(
        0.1,
        gt=0.005,
        le=0.5,
        description="raster cell that joins a stem's ring points into one cluster (m)",
    )
    stem_min_points: int = Field(
        8,
        ge=4,
        le=10_000,
        description="fewest slice points of one scan for a circle fit on its arc",
    )
    stem_max_radius: float = Field(
        0.6,
        gt=0.02,
        le=3,
        description="largest stem radius (m): bigger clusters are shrubs or logs",
    )
    stem_min_radius: float = Field(
        0.03, gt=0, le=0.5, description="smallest stem radius (m): smaller are saplings and twigs"
    )
    stem_arc_rmse: float = Field(
        0.015,
        gt=0,
        le=0.2,
        description="one scan's arc must fit a circle this well (m) to be a stem",
    )
    insets: int = Field(4, ge=0, le=12, description="zoomed stems drawn beside the slice")


class DistanceConfig(BaseModel):
    """Cloud-to-cloud distances of registered scans (point to the other scan's local plane)."""

    model_config = ConfigDict(extra="forbid")

    voxel: float = Field(
        0.02,
        gt=0.001,
        le=0.5,
        description="one point per cube of this size (m): evens TLS density, keeps cm detail",
    )
    max_points: int = Field(
        200_000,
        ge=1000,
        le=10_000_000,
        description="cap per scan after thinning: bounds memory and KD-tree time",
    )
    sample: int = Field(
        50_000,
        ge=1000,
        le=10_000_000,
        description="source points measured an edge, a seeded subset: thousands stay in the overlap",
    )
    neighbourhood: float = Field(
        0.15,
        gt=0,
        le=2,
        description="the other scan must be dense within this radius (m): the overlap",
    )
    neighbours: int = Field(
        6, ge=3, le=64, description="points of the other scan that define its local plane"
    )
    spacing_factor: float = Field(
        1.5,
        ge=0,
        le=10,
        description="a sparse target's local plane reaches this many times its median spacing",
    )
    colour_max: float = Field(
        0.05, gt=0, le=1, description="top of the distance colour scale (m): 5 cm shows cm errors"
    )
    edge_figures: int = Field(
        4,
        ge=0,
        le=200,
        description="edges drawn (the worst by median distance); all are in the table",
    )


class AlsFitConfig(BaseModel):
    """The georeferenced page's comparison of the placed scans with the ALS."""

    model_config = ConfigDict(extra="forbid")

    margin: float = Field(
        5.0, ge=0, le=100, description="ALS kept this far (m) around the plot's ground model"
    )
    min_als_points: int = Field(
        100, ge=1, le=1_000_000, description="fewer ALS returns over the plot: no comparison drawn"
    )
    ground_reach: float = Field(
        20.0,
        gt=0,
        le=500,
        description="ground compared within this distance (m) of a scanner: farther, TLS sees understorey",
    )
    canopy_cell: float = Field(
        2.0, gt=0.2, le=20, description="cell of the canopy-top comparison (m): a crown's size"
    )
    canopy_min_height: float = Field(
        2.0,
        ge=0,
        le=50,
        description="a cell is canopy where both tops are this high above ground (m)",
    )
    top_band: float = Field(
        1.0,
        gt=0,
        le=10,
        description="the TLS sees a cell's top when it has points this close below it (m)",
    )
    top_points: int = Field(
        5, ge=1, le=10_000, description="fewest TLS points in that band for the TLS top to count"
    )
    colour_max: float = Field(
        0.3, gt=0, le=5, description="ends of the ground-difference colour scale (+- m)"
    )


class ReportConfig(BaseModel):
    """Pictures and pages of the registration report."""

    model_config = ConfigDict(extra="forbid")

    slice: SliceConfig = Field(default_factory=SliceConfig, description="breast-height slice")
    distance: DistanceConfig = Field(
        default_factory=DistanceConfig, description="cloud-to-cloud distances"
    )
    als_fit: AlsFitConfig = Field(
        default_factory=AlsFitConfig, description="fit of the placed scans to the ALS"
    )
    picture_points: int = Field(
        20_000, ge=1000, le=1_000_000, description="points per scan in the overview pictures"
    )
    view3d_points: int = Field(
        20_000,
        ge=0,
        le=1_000_000,
        description="points per scan in the interactive 3D view (0: none)",
    )
    view3d_total: int = Field(
        300_000,
        ge=1000,
        le=5_000_000,
        description="points over all scans in the 3D view: keeps the page under view3d_max_mb",
    )
    view3d_max_mb: float = Field(
        20.0,
        gt=0,
        le=200,
        description="the 3D page is skipped above this size: it must open quickly",
    )
    weak_ring_spread: float = Field(
        0.02,
        gt=0,
        le=1,
        description="a median ring spread above this (m) is flagged as doubled stems",
    )
    rigid_translation: float = Field(
        0.0005,
        ge=0,
        le=0.1,
        description="a plot whose within-plot poses a later solve moved less than this (m) is judged in the earlier report",
    )
    rigid_rotation_deg: float = Field(
        0.001,
        ge=0,
        le=1,
        description="the same in rotation (deg): its slice and distances would be the earlier ones, moved",
    )
    weak_distance: float = Field(
        0.03,
        gt=0,
        le=1,
        description="a scan's median distance to neighbours above this (m) is flagged",
    )
    als_margin: float = Field(
        40.0,
        ge=0,
        le=1000,
        description="ALS kept this far (m) around the scanners: map background, fit, 3D layer",
    )
    weak_ground_offset: float = Field(
        0.15,
        gt=0,
        le=5,
        description="a plot's median ground offset from the ALS above this (m) is flagged",
    )
