"""Settings of the coarse stage's clouds and their vertical hypotheses (levelling, trunk axes).

A leaf module: imports nothing of the project.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class CoarseLevelling(BaseModel):
    """The coarse stage's switch, the clouds it works on and their vertical hypotheses."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(True, description="run the global coarse stage before ForestAlign")
    # --- clouds used by the coarse stage
    feature_voxel: float = Field(
        0.1, gt=0, le=2.0, description="voxel (m) of the cloud used for levelling and rasters"
    )
    max_points: int = Field(
        150_000, gt=1000, le=5_000_000, description="cap on points used for the rasters"
    )
    normal_radius: float = Field(
        0.75,
        gt=0,
        le=5.0,
        description="largest neighbourhood (m) of the coarse stage's own normals",
    )
    normal_neighbours: int = Field(
        16,
        ge=5,
        le=200,
        description="nearest neighbours per normal: the neighbourhood adapts to density",
    )
    # --- levelling (levelling.py)
    levelling_normals: int = Field(
        10_000,
        ge=500,
        le=1_000_000,
        description="seeded sample of normals the vertical is estimated from",
    )
    max_tilt_deg: float = Field(
        75.0, gt=0, le=90, description="largest roll/pitch the levelling searches"
    )
    up_candidates: int = Field(
        1000, ge=100, le=100_000, description="directions over the hemisphere tried as the vertical"
    )
    flat_deg: float = Field(
        15.0, gt=0, le=45, description="a normal within this of a candidate counts as ground-like"
    )
    upright_deg: float = Field(
        8.0,
        gt=0,
        le=45,
        description="a normal within this of the horizontal plane counts as stem-like",
    )
    upright_weight: float = Field(
        0.5,
        ge=0,
        le=10,
        description="weight of stem-like normals beside ground-like ones in the first vote",
    )
    refine_bands_deg: tuple[float, ...] = Field(
        (20.0, 12.0, 8.0), description="shrinking bands (deg) of the vertical's refinement"
    )
    min_stem_share: float = Field(
        0.04,
        ge=0,
        le=1,
        description="least share of stem-like normals to refine the vertical on stems",
    )
    min_stem_normals: int = Field(
        200, ge=10, description="least stem-like normals to refine the vertical on stems"
    )
    min_ground_normals: int = Field(
        50, ge=10, description="least ground-like normals to refine the vertical on the ground"
    )
    # --- trunk axes (levelling.trunk_axes_up)
    trunk_hag: tuple[float, float] = Field(
        (0.5, 4.0),
        description="band (m above the rough DTM) trunk axes are fitted in: below the crowns",
    )
    trunk_normal_deg: float = Field(
        30.0,
        gt=0,
        le=60,
        description="a normal within this of the rough horizontal may be a trunk's (the rough level may be off)",
    )
    trunk_min_points: int = Field(
        12,
        ge=5,
        description="least points of a trunk group (an 8M scan: 166 trunks at 12, 52 at 30)",
    )
    trunk_min_span: float = Field(
        1.5, gt=0, le=10, description="least height (m) a trunk group spans: an axis needs a lever"
    )
    trunk_elongation: float = Field(
        8.0, ge=1, le=1000, description="least ratio of a trunk group's main to second variance"
    )
    trunk_max_lean_deg: float = Field(
        30.0,
        gt=0,
        le=60,
        description="groups leaning more than this from the rough level are no trunks",
    )
    trunk_min_count: int = Field(
        4,
        ge=1,
        le=100,
        description="least trunks for the median axis (fewer: one leaning stem decides)",
    )
    trunk_passes: int = Field(
        2, ge=1, le=5, description="level, fit the axes, level again: the band follows the estimate"
    )
    # --- vertical hypotheses (several, verification decides)
    vertical_duplicate_deg: float = Field(
        2.0, gt=0, le=20, description="vertical hypotheses closer than this are one"
    )
    max_vertical_spread_deg: float = Field(
        35.0,
        gt=0,
        le=90,
        description="estimates further than this from the joint (ground + stem) one are dropped",
    )
    max_verticals: int = Field(
        3, ge=1, le=6, description="vertical hypotheses of the source carried into the search"
    )
    max_target_verticals: int = Field(
        5,
        ge=1,
        le=6,
        description="vertical hypotheses kept for the target: every kind, so each source kind finds its like "
        "(kept ones cost nothing until a pair uses them)",
    )
    max_vertical_pairs: int = Field(
        3, ge=1, le=36, description="(source, target) vertical pairs searched"
    )
    settle_early: bool = Field(
        True,
        description="search the other vertical pairs only when the first pair's best pose is not settled",
    )
    settled_confidence: float = Field(
        0.5,
        ge=0,
        le=1,
        description="settled: its margin over the best distinct refined rival is at least this ...",
    )
    settled_score: float = Field(
        0.2,
        ge=0,
        le=1,
        description="... its refined score (share of non-flat points with a partner) at least this ...",
    )
    settled_generators: int = Field(
        2, ge=1, le=3, description="... and this many generators reached it on their own"
    )
    z_up_max_deg: float = Field(
        8.0, ge=0, le=45, description="z-up is a candidate when an estimate lies within this of it"
    )
    ground_fit_cell: float = Field(
        2.0, gt=0, le=20, description="cell (m) of the lowest-point-per-cell ground fit"
    )
    ground_fit_min_cells: int = Field(
        12, ge=3, description="least cells for the robust ground-plane fit"
    )
    ground_fit_max_deg: float = Field(
        30.0,
        gt=0,
        le=90,
        description="a ground fit tilted more than this from the rough level is rejected",
    )
    ground_fit_inlier_m: float = Field(
        0.5,
        gt=0,
        le=5,
        description="residual (m) of a lowest point still on the fitted ground plane",
    )
