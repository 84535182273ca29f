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
        description="linearity from which a level point lies on a line (a stem, a branch, a twig)",
    )
    # heights are taken above the cloud's own rough ground, levelled by its own up: any pose, any slope
    ground_cell: float = Field(
        1.0, gt=0, le=20, description="cell (m) of the rough ground model heights are measured from"
    )
    above_ground_m: float = Field(
        0.3,
        ge=0,
        le=10,
        description="a level point this high above the ground stands on it (below: ground, litter, scan rings)",
    )
    stem_band_m: tuple[float, float] = Field(
        (0.5, 3.5),
        description="heights (m above the ground) trunks are looked for in: above litter, below most crowns",
    )
    stem_max_normal_cos: float = Field(
        0.35,
        gt=0,
        lt=1,
        description="|normal . up| below this: an upright surface or line (a trunk's side)",
    )
    stem_cell: float = Field(
        0.3,
        gt=0,
        le=5,
        description="squares (m) upright points are grouped in: stems apart, one stem whole",
    )
    # a random cloud's chance columns hold a few points; a trunk's side one a level cube up its length
    stem_min_points: int = Field(
        10,
        ge=3,
        le=10_000,
        description="least level points of a stem (2 m of one side at 0.2 m cubes)",
    )
    stem_min_span_m: float = Field(
        1.5,
        gt=0,
        le=10,
        description="least length (m) a stem stands through the band: a trunk, not a stub",
    )
    # a random cloud's chance columns are as wide as the grouping lets them grow; trunks narrower
    stem_max_width_m: float = Field(
        0.8, gt=0, le=5, description="widest (m, 4 sigma across its axis) a stem group may be"
    )
    stem_max_lean_deg: float = Field(
        35.0,
        gt=0,
        le=90,
        description="most a stem's axis leans from the cloud's up (leaning trunks, up taken on a slope)",
    )
    # ground-based forest scans show several, open stands too; random clouds and built scenes none
    min_stems: int = Field(
        3,
        ge=1,
        le=1000,
        description="stems that make a scene a forest by themselves: trunks standing on a ground",
    )
    # a random cloud's lowest points lie on no surface; an airborne cloud's or a grassland's ground
    min_ground_share: float = Field(
        0.1,
        ge=0,
        le=1,
        description="least share on a ground (low, on a plane facing up) for lines above it to count",
    )
    # a level point every 0.2 m cube: a branch's next points lie within 0.3 m
    branch_radius_m: float = Field(
        0.3, gt=0, le=5, description="line points this near each other are one branch or stem"
    )
    branch_neighbours: int = Field(
        2, ge=1, le=100, description="line neighbours a line point needs to be part of a branch"
    )
    # a clip without its ground (an MLS clip) has branches; a random cloud's chance lines stand alone
    min_branch_share: float = Field(
        0.05,
        ge=0,
        le=1,
        description="or least share of the above-ground points in branches for lines above it to count",
    )
    # airborne clouds, grassland and short views see few trunks (figures: benchmarks/results/judge.md)
    min_above_linear_share: float = Field(
        0.01,
        ge=0,
        le=1,
        description="else, least share of what stands above the ground on lines: branches, twigs, blades",
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

    @model_validator(mode="after")
    def _band(self) -> SceneConfig:
        lo, hi = self.stem_band_m
        if not 0 <= lo < hi:
            raise ValueError(f"stem_band_m must be 0 <= low < high, got {self.stem_band_m}")
        return self


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
    # a low-overlap pair's truth often ranks low on the wide scales among many starts, but many
    # starts agree on it (docs/method.md#judge-settings): a refused pose gets one more look among them
    second_look_rivals: int = Field(
        24,
        ge=0,
        le=64,
        description="distinct candidates a pose that would be refused is looked for again from"
        " (0: none); the first that holds replaces it",
    )
    # many looks are many chances for a chance alignment to pass; the truths the looks find stand
    # clear of their rivals (docs/method.md#judge-settings)
    second_look_min_confidence: float = Field(
        0.5,
        ge=0,
        le=1,
        description="least confidence of a pose a second look finds (the first pose needs"
        " min_confidence)",
    )
    # a near miss's truth can stand well inside the distinct radius (docs/method.md#judge-settings):
    # only a pose the final ICP returns to is one already weighed
    weighed_radius: float = Field(
        0.15,
        gt=0,
        le=1,
        description="share of the distinct radius within which a second look's pose is a pose"
        " already weighed (the look stops)",
    )
    global_rivals: bool = Field(
        True, description="after --no-coarse / --init also search the whole pair for rivals"
    )
    # a score is a share of all points, so a thin pair's truth scores little; sharpness and the
    # margin tell chance from fit (docs/method.md#judge-settings)
    min_score: float = Field(
        0.08,
        ge=0,
        le=1,
        description="least judge score of a searched pose: a floor, the margin decides",
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
    stored_min_score: float = Field(
        0.12,
        ge=0,
        le=1,
        description="least judge score of a stored pose or placement verified without a search",
    )
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
