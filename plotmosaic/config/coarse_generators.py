"""Settings of the coarse stage's generators: forest rasters and their search, 3D features, height
slices, stem maps.

A leaf module: imports nothing of the project.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class CoarseGenerators(BaseModel):
    """The generators of coarse hypotheses."""

    model_config = ConfigDict(extra="forbid")

    # --- forest rasters (rasters.py)
    cell: float = Field(1.0, gt=0, le=20, description="raster cell (m); grown for large extents")
    feature_cell: float = Field(
        1.0,
        gt=0,
        le=10,
        description="cell (m) of the rough DTM that gives each point its height above ground",
    )
    dtm_percentile: float = Field(
        25.0,
        ge=0,
        le=100,
        description="low quantile of a DTM cell's neighbourhood it is compared with",
    )
    dtm_window: int = Field(5, ge=3, le=25, description="neighbourhood (cells) of that comparison")
    dtm_dense_cells: int = Field(
        4_000_000,
        ge=0,
        le=100_000_000,
        description="largest dense rough DTM (cells); a larger one is built on its occupied cells only, so memory follows the points",
    )
    dtm_max_step: float = Field(
        1.0,
        gt=0,
        le=10,
        description="a lowest return this far (m) above its neighbourhood is not ground",
    )
    vertical_normal_z: float = Field(
        0.35, gt=0, lt=1, description="|normal z| below this: a vertical surface (stem, trunk)"
    )
    stem_min_hag: float = Field(
        0.5, ge=0, le=10, description="lowest height above ground (m) of the stem channel"
    )
    stem_max_hag: float = Field(
        4.0, gt=0, le=30, description="highest height above ground (m) of the stem channel"
    )
    canopy_min_hag: float = Field(
        3.0, ge=0, le=50, description="vegetation above this height (m) is canopy"
    )
    ground_max_hag: float = Field(
        0.25, gt=0, le=5, description="points within this (m) of the DTM may be ground"
    )
    ground_normal_z: float = Field(
        0.7, gt=0, lt=1, description="|normal z| above this: a ground-like surface"
    )
    # --- raster search
    small_scene_cells: int = Field(
        20,
        ge=4,
        le=1000,
        description="a source narrower than this many cells also gets a finer-cell search",
    )
    min_cell: float = Field(
        0.25, gt=0, le=20, description="finest raster cell (m) of that extra search"
    )
    max_fft: int = Field(
        512, ge=64, le=8192, description="largest padded FFT side; the cell grows to respect it"
    )
    cell_growth: float = Field(
        1.5, gt=1, le=4, description="factor the cell grows by until the FFT fits"
    )
    yaw_step_deg: float = Field(
        4.0, gt=0, le=10, description="heading step of the full-circle search"
    )
    refine_headings: int = Field(
        8, ge=0, le=64, description="best headings searched again at half a step either side"
    )
    # a heading's shifts on cells k times larger cost ~1/k^2 of its FFTs; canopy and terrain (what
    # an airborne cloud shows best) are smooth at that scale, stems (what ground pairs weigh most)
    # are a cell wide
    heading_pyramid: int = Field(
        2,
        ge=1,
        le=4,
        description="where a cloud is airborne, the full circle of headings runs first on cells this "
        "many times larger and only its best headings on the raster cell (1: every heading on the "
        "raster cell); pairs of ground-based scans always search every heading on it",
    )
    pyramid_headings: int = Field(
        12,
        ge=1,
        le=90,
        description="distinct headings of the coarser search searched again on the raster cell",
    )
    blur_cells: float = Field(
        1.0, ge=0, le=10, description="Gaussian blur (cells) of the occupancy rasters"
    )
    min_overlap: float = Field(
        0.08, ge=0, le=1, description="least overlap, as a fraction of the smaller footprint"
    )
    terrain_min_share: float = Field(
        0.25, ge=0, le=1, description="terrain NCC counts only over this share of the least overlap"
    )
    terrain_min_cells: int = Field(
        4, ge=1, description="terrain NCC counts only over at least this many shared ground cells"
    )
    overlap_exponent: float = Field(
        0.25,
        ge=0,
        le=2,
        description="raster score x overlap share ** this: small overlaps score lower",
    )
    peak_suppression_m: float = Field(
        3.0, gt=0, le=50, description="radius (m) cleared around a peak before the next one"
    )
    hypotheses: int = Field(
        6, ge=1, le=64, description="raster hypotheses verified under the first vertical pair"
    )
    secondary_hypotheses: int = Field(
        3, ge=1, le=64, description="raster hypotheses verified under each other vertical pair"
    )
    peaks_per_yaw: int = Field(2, ge=1, le=10, description="correlation peaks kept per heading")
    distinct_yaw_deg: float = Field(
        6.0, gt=0, le=90, description="hypotheses closer than this in heading and ..."
    )
    distinct_shift_m: float = Field(
        3.0, gt=0, le=50, description="... closer than this in shift are one"
    )
    weights_ground: dict[str, float] = Field(
        {"stems": 1.0, "canopy": 0.5, "terrain": 0.5},
        description="channel weights between ground-based scans (stems seen best)",
    )
    weights_airborne: dict[str, float] = Field(
        {"stems": 0.25, "canopy": 1.0, "terrain": 1.0},
        description="channel weights when a cloud is airborne (canopy, terrain seen best)",
    )
    tz_ground_radius: float = Field(
        0.75,
        gt=0,
        le=10,
        description="xy radius (m) pairing source and target ground for the height",
    )
    tz_min_ground: int = Field(
        20, ge=3, description="least paired ground points for the height from the ground"
    )
    # --- 3D features generator (features3d.py)
    fpfh: bool = Field(True, description="generate hypotheses from FPFH feature matches")
    fpfh_voxel: float = Field(
        0.3, gt=0.05, le=3, description="voxel (m) of the clouds FPFH is computed on (forest scale)"
    )
    fpfh_max_points: int = Field(
        8_000,
        ge=500,
        le=200_000,
        description="cap on the smaller cloud's FPFH points (the shared voxel grows to respect it)",
    )
    fpfh_max_points_larger: int = Field(
        16_000,
        ge=500,
        le=200_000,
        description="cap on the larger cloud's FPFH points at the shared voxel",
    )
    fpfh_normal_radius: float = Field(0.75, gt=0, le=10, description="normal radius (m) for FPFH")
    fpfh_radius: float = Field(1.5, gt=0, le=20, description="FPFH feature radius (m)")
    fpfh_max_nn: int = Field(60, ge=10, le=500, description="neighbours per FPFH descriptor")
    fpfh_inlier_m: float = Field(
        0.6, gt=0, le=10, description="correspondence inlier distance (m) of the robust estimator"
    )
    fpfh_draws: int = Field(
        200_000,
        ge=1000,
        le=5_000_000,
        description="random match triples drawn x 1/2 for the 6-DoF RANSAC, cheaply pre-filtered",
    )
    fpfh_iterations: int = Field(
        3000, ge=100, le=200_000, description="consistent 6-DoF samples scored"
    )
    fpfh_vote_yaw_deg: float = Field(
        1.5,
        gt=0,
        le=10,
        description="heading step of the 4-DoF vote: 0.75 deg off at most, 0.4 m at 30 m from the centre",
    )
    fpfh_vote_cells: int = Field(
        2, ge=1, le=20, description="fullest translation bins per heading (and grid) kept as poses"
    )
    fpfh_min_inliers: int = Field(
        8, ge=3, le=10_000, description="least inlier matches of an FPFH pose (fewer: chance)"
    )
    fpfh_hypotheses: int = Field(
        3, ge=1, le=20, description="distinct FPFH poses handed to verification"
    )
    fpfh_vertical_pairs: int = Field(
        2, ge=0, le=36, description="vertical pairs the 4-DoF RANSAC runs under (the first ones)"
    )
    fpfh_six_dof: bool = Field(
        True, description="also a 6-DoF RANSAC that trusts no vertical hypothesis"
    )
    # --- height-slice occupancy generator (slices.py): sparse ground views the 1 m rasters miss
    slices: bool = Field(
        True,
        description="generate hypotheses by correlating fine height-slice occupancy (when not settled)",
    )
    # see docs/method.md#coarse-stage-settings
    slice_cell: float = Field(
        0.3,
        gt=0.05,
        le=5,
        description="occupancy cell (m): a stem is one or two cells (coarser cells merge stems)",
    )
    slice_edges: tuple[float, ...] = Field(
        (0.3, 1.0, 2.0, 4.0, 8.0, 30.0),
        min_length=2,
        description="slice edges (m above the rough DTM): understorey, stems, crown base, crowns; ground left out",
    )
    slice_yaw_deg: float = Field(
        2.0, gt=0, le=10, description="heading step: 1 m at the edge of a 30 m view"
    )
    slice_max_fft: int = Field(
        512, ge=64, le=8192, description="largest padded FFT side; the cell grows to respect it"
    )
    slice_min_cells: int = Field(
        20, ge=1, description="least shared slice cells for a pose to score (fewer: chance)"
    )
    slice_peaks_per_yaw: int = Field(2, ge=1, le=10, description="peaks kept per heading")
    slice_suppression_m: float = Field(
        2.0, gt=0, le=50, description="radius (m) cleared around a peak before the next one"
    )
    # enough to hold the truth's rank on sparse views (docs/method.md#coarse-stage-settings)
    slice_hypotheses: int = Field(
        6,
        ge=1,
        le=64,
        description="distinct poses handed to verification",
    )
    slice_distinct_yaw_deg: float = Field(
        3.0, gt=0, le=90, description="poses closer than this in heading and ..."
    )
    slice_distinct_m: float = Field(
        1.5,
        gt=0,
        le=50,
        description="... closer than this in shift are one (the screening ICP's basin)",
    )
    slice_vertical_pairs: int = Field(
        1, ge=0, le=36, description="vertical pairs the slice search runs under (the first ones)"
    )
    # --- stem map generator (stemmap.py)
    stems: bool = Field(True, description="generate hypotheses by matching stem maps")
    stem_slab: tuple[float, float] = Field(
        (1.0, 2.0), description="breast-height slab (m above ground) stems are cut at"
    )
    stem_cluster_m: float = Field(
        0.25, gt=0, le=2, description="xy link distance (m) of points of one stem"
    )
    stem_min_points: int = Field(8, ge=3, description="least points of a stem cluster")
    stem_max_diameter: float = Field(
        1.5, gt=0, le=5, description="largest fitted stem diameter (m)"
    )
    stem_max_count: int = Field(
        300, ge=3, le=5000, description="stems kept per cloud (the best supported)"
    )
    stem_inlier_m: float = Field(
        0.5, gt=0, le=5, description="a stem within this (m) of a moved stem matches it"
    )
    stem_min_matches: int = Field(
        3, ge=2, description="least matched stems for a stem-map hypothesis"
    )
    stem_pair_min_m: float = Field(
        2.0, gt=0, description="stem pairs shorter than this do not fix a heading"
    )
    stem_max_pairs: int = Field(
        3000, ge=10, le=1_000_000, description="cap on source stem pairs voted with"
    )
    stem_hypotheses: int = Field(
        3, ge=1, le=20, description="distinct stem-map poses handed to verification"
    )
    stem_vote_yaw_deg: float = Field(
        3.0, gt=0, le=30, description="heading bin (deg) of the stem-pair vote accumulator"
    )
