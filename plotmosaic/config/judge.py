"""Settings of the pose judge (align/judge/): residual-profile scales, rivals, calibrated thresholds."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator


class SceneConfig(BaseModel):
    """Is each cloud a forest scene (align/scene.py)? Refused before any pose is weighed (exit 3).
    Calibration: see docs/method.md#judge-settings."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(
        True, description="refuse a pair whose source or target is no forest scene"
    )
    # a plot's scan holds several trees, stems metres apart; an object or a machine is smaller
    min_extent_m: float = Field(
        6.0,
        ge=0,
        le=1000,
        description="least span (m, along the cloud's widest principal axis) of a forest scene",
    )
    linearity: float = Field(
        0.6,
        gt=0,
        le=1,
        description="linearity from which a level point lies on a line (a stem, a branch)",
    )
    # the sparsest forest clouds on lines are ALS tiles; random clouds have none at all
    min_linear_share: float = Field(
        0.02,
        ge=0,
        le=1,
        description="least share of a forest scene on lines: stems and branches are in every forest cloud",
    )
    crossing_max_cos: float = Field(
        0.3,
        gt=0,
        lt=1,
        description="a plane whose normal is within this cosine of perpendicular to the main planes'"
        " crosses them (a wall on a floor)",
    )
    # forests' planes are their ground (stems' broad sides cross it a little); rooms, streets are walls
    max_crossing_share: float = Field(
        0.2,
        ge=0,
        le=1,
        description="most share of a forest scene on planes across its main planes: built scenes are walls",
    )


class JudgeConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(True, description="verify every pairwise result against distinct rivals")
    scales: list[float] = Field(
        [0.02, 0.05, 0.10, 0.25],
        min_length=1,
        description="residual-profile distances (m) at the delta0 spacing",
    )
    reference_spacing: float = Field(
        0.05, gt=0, description="point spacing (m) the scales are given for (delta0)"
    )
    max_scale_factor: float = Field(
        8.0, ge=1, description="cap on how far a sparse cloud stretches the scales"
    )
    profile_points: int = Field(
        4_000, ge=200, le=100_000, description="sample points per direction of a profile"
    )
    structure_max_planarity: float = Field(
        0.4, ge=0, le=1, description="structure (stems, crowns) below this planarity: planes slide"
    )
    distinct_m: float = Field(
        1.0, gt=0, description="a rival this far (m, at the source centroid) is another pose"
    )
    distinct_deg: float = Field(
        3.0, gt=0, description="a rival this far in rotation (deg) is another pose"
    )
    max_rivals: int = Field(
        6, ge=0, le=64, description="distinct candidate poses refined and scored as rivals"
    )
    rival_points: int = Field(
        2_000, ge=200, le=50_000, description="source points of a rival's refinement ICP"
    )
    # a last stage as tight as the finest scale: a rival that is the truth must end on it, or its
    # fine share falls to chance (see docs/method.md#judge-settings)
    rival_schedule: list[tuple[float, int]] = Field(
        [(0.6, 8), (0.25, 8), (0.1, 6), (0.04, 8)],
        description="(distance m, iterations) stages of a rival's refinement; distances x the scale factor",
    )
    rival_kernel: float = Field(
        0.1,
        gt=0,
        le=1,
        description="widest Tukey floor (m, x the scale factor) of a rival's stages",
    )
    # a narrow strip holds its roll weakly: a near rival may still be sliding into the pose, and a
    # far one cannot be the pose, so only near ones pay for more passes (docs/method.md#judge-settings)
    near_rival_radii: float = Field(
        2.0,
        ge=1,
        le=10,
        description="a rival within this many distinct radii of the pose is refined again: it may be"
        " sliding into the pose",
    )
    near_rival_passes: int = Field(
        2, ge=0, le=8, description="extra refinement passes of a near rival at most (0: none)"
    )
    # a near miss the final ICP left inside the distinct radius has the sharper truth beside it;
    # a right pose's starts return to it (docs/method.md#judge-settings)
    basin_neighbours: int = Field(
        2,
        ge=0,
        le=8,
        description="starts around the pose (turned and shifted), refined like rivals: a near miss's"
        " neighbours find the sharper pose beside it (0: off)",
    )
    basin_deg: float = Field(
        2.0, gt=0, le=10, description="turn of a basin start (deg, about the source centre)"
    )
    basin_m: float = Field(
        0.2, gt=0, le=2, description="shift of a basin start (m, x the scale factor)"
    )
    # above refinement noise, far below what a near miss's starts gain (docs/method.md#judge-settings)
    basin_tolerance: float = Field(
        0.25,
        ge=0,
        le=1,
        description="how much more share within the smallest scale a basin start may end with before"
        " it is a rival (a sharper pose beside this one: a near miss)",
    )
    scene: SceneConfig = Field(
        default_factory=SceneConfig,
        description="each cloud must be a forest scene (extent, stems, not all planes)",
    )
    # a low-overlap pair's truth often ranks low on the wide scales among many starts
    # (docs/method.md#judge-settings): a refused pose gets one more look among them
    second_look_rivals: int = Field(
        12,
        ge=0,
        le=64,
        description="distinct candidates beyond the rivals refined when the pose would be refused"
        " (0: none); the sharpest one is tried as the pose",
    )
    second_look_below: float = Field(
        0.25,
        ge=0,
        le=1,
        description="confidence below which a pose gets that second look (also: blunt, beaten, or"
        " below min_score)",
    )
    global_rivals: bool = Field(
        True, description="after --no-coarse / --init also search the whole pair for rivals"
    )
    min_score: float = Field(
        0.12,
        ge=0,
        le=1,
        description="least judge score of an accepted pose: a floor, the margin decides",
    )
    # wider scales rank a boxed-in view's rivals level with the truth; the finest does not
    fine_scales: int = Field(
        1, ge=1, le=8, description="smallest profile scales whose share makes the fine margin"
    )
    # between the wrong poses' highest fine margin and the right poses' lowest
    # (docs/method.md#judge-settings)
    chance_margin: float = Field(
        0.5,
        ge=0,
        lt=1,
        description="fine margin counting as confidence 0: above what wrong poses reach by chance",
    )
    full_margin: float = Field(
        0.9,
        gt=0,
        le=1,
        description="fine margin (1 - best rival's fine share / the pose's) counting as confidence 1",
    )
    # a wrong pose among wrong rivals can win on confidence, never on sharpness
    # (docs/method.md#judge-settings)
    min_sharpness: float = Field(
        0.04,
        ge=0,
        le=1,
        description="least sharpness (see stored_min_sharpness) of a pose accepted on its confidence alone",
    )
    # two noisy sensors together spread the finest share: a right pose may be blunter, but then only
    # as a clear winner (docs/method.md#judge-settings)
    blunt_min_sharpness: float = Field(
        0.03,
        ge=0,
        le=1,
        description="least sharpness of any accepted pose (and of a rival that may outscore it); below min_sharpness only with blunt_min_confidence",
    )
    blunt_min_confidence: float = Field(
        0.9,
        ge=0,
        le=1,
        description="confidence a pose between blunt_min_sharpness and min_sharpness needs: a clear winner",
    )
    # a stored pose (E57 `use_pose = true`) that verifies skips the global search; these decide it
    stored_max_correction_deg: float = Field(
        0.5,
        gt=0,
        le=10,
        description="a right stored pose barely turns under ICP: most it may (deg)",
    )
    stored_max_correction_m: float = Field(
        0.10,
        gt=0,
        le=2,
        description="most a verified stored pose may move under ICP (m, at the source centroid)",
    )
    # right stored poses are sharp; a pose that fails falls back to the search
    # (docs/method.md#judge-settings)
    stored_min_sharpness: float = Field(
        0.075,
        gt=0,
        le=1,
        description="least share within the smallest scale over share within the largest (structure"
        " points, both directions): chance alignments are blunt",
    )

    @model_validator(mode="after")
    def _margins_ordered(self) -> JudgeConfig:
        if self.blunt_min_sharpness > self.min_sharpness:
            raise ValueError(
                f"judge.blunt_min_sharpness {self.blunt_min_sharpness} must not exceed"
                f" min_sharpness {self.min_sharpness}"
            )
        if self.chance_margin >= self.full_margin:
            raise ValueError(
                f"judge.chance_margin {self.chance_margin} must be below full_margin {self.full_margin}"
            )
        return self
