"""Settings of sensor-kind detection (align/kinds.py): which of tls / mls / uls / als a cloud looks like.

Calibration on the real clips and the simulator's presets: benchmarks/results/kinds.md.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator


class KindConfig(BaseModel):
    """A cloud's sensor kind from its points, when no kind is given."""

    model_config = ConfigDict(extra="forbid")

    sample_points: int = Field(
        200_000, ge=1000, le=100_000_000, description="seeded sample the figures are counted on"
    )
    cell: float = Field(
        1.0, gt=0, le=100, description="horizontal cell (m) of the coverage, density and columns"
    )
    # an object, a machine part or a handful of points says nothing about the sensor
    min_points: int = Field(
        1000, ge=10, le=10_000_000, description="fewer points: too few to tell, the default kind"
    )
    min_extent_m: float = Field(
        3.0, gt=0, le=1000, description="narrower (m, widest horizontal side): too small to tell"
    )
    # seen from above, every cell of the footprint gets returns; a ground-based scan's far range and
    # shadows leave holes between its rays
    min_airborne_coverage: float = Field(
        0.9,
        ge=0,
        le=1,
        description="occupied share of the cells within each row's extent, at least: airborne "
        "(with an even density or a hidden understorey)",
    )
    # a scan line spreads points evenly; a station packs them around itself (1/r^2), and a
    # ground-based cloud piles points on stems and crowns it sees from close by
    max_airborne_dense_share: float = Field(
        0.15,
        ge=0,
        le=1,
        description="share of the points in the densest 5 % of cells, at most: an even, airborne density",
    )
    # a canopy hides what lies below it from above (overlapping UAV strips are less even than one
    # scan line); a ground-based sensor sees stems and shrubs best, at close range
    max_airborne_understorey: float = Field(
        0.06,
        ge=0,
        le=1,
        description="share of points in the understorey band under a canopy, at most: seen from above",
    )
    understorey_from_m: float = Field(
        0.5, ge=0, le=100, description="understorey band from (m above a column's lowest point)"
    )
    understorey_to_m: float = Field(
        3.0, gt=0, le=100, description="understorey band up to (m above a column's lowest point)"
    )
    min_canopy_m: float = Field(
        3.0,
        gt=0,
        le=100,
        description="a column this tall (lowest to highest point, m) has a canopy",
    )
    # airborne surveys deliver up to a few tens of points per m2, UAV lidar hundreds and more
    min_uls_density: float = Field(
        100.0,
        gt=0,
        le=1e6,
        description="points per occupied m2 from which an airborne cloud is uls",
    )
    # a tripod scanner sees the ground all around it at steep angles; a mobile scanner's narrow
    # vertical field grazes it, so little ground comes back where shrubs stand
    ground_band_m: float = Field(
        0.3, gt=0, le=10, description="height (m) above a column's lowest point counted as ground"
    )
    max_mls_ground_share: float = Field(
        0.06,
        ge=0,
        le=1,
        description="share of a ground-based cloud on the ground, at most: mls (else tls)",
    )

    @model_validator(mode="after")
    def _band(self) -> KindConfig:
        if self.understorey_from_m >= self.understorey_to_m:
            raise ValueError("understorey_from_m must be below understorey_to_m")
        return self
