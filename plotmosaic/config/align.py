"""Typed settings for ForestAlign pairwise registration (defaults = the paper's Algorithm 1)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from plotmosaic.config.coarse import CoarseConfig
from plotmosaic.config.freespace import FreeSpaceConfig
from plotmosaic.config.judge import JudgeConfig
from plotmosaic.config.kinds import KindConfig

KINDS = ("tls", "mls", "uls", "als")  # sensor kinds: terrestrial, mobile, UAV, airborne
# complexity levels K of one cloud: the level schedule repeats its last entry beyond 3, and more
# than 6 groups of a forest scan are no longer distinct structures
MAX_LEVELS = 6

# Levels per sensor kind (paper, Algorithm 1): ground-based scans see ground, stems and foliage;
# airborne scans mostly ground and canopy. Grassland plots (no trees) should use 1-2 via the flag.
DEFAULT_LEVELS = {"tls": 3, "mls": 3, "uls": 2, "als": 2}


def default_levels(kind: str) -> int:
    return DEFAULT_LEVELS[kind.lower()]


class StrayConfig(BaseModel):
    """Stray points dropped before any grid is built (align/outliers.py)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    enabled: bool = Field(
        True, description="drop points detached from the cloud before any grid is built"
    )
    core_quantile: float = Field(
        0.02,
        gt=0,
        lt=0.25,
        description="the bulk: quantiles q..1-q per axis (a "
        "cluster of NaN-written points below q cannot move them)",
    )
    core_margin: float = Field(
        1.0,
        ge=0,
        le=10,
        description="the bulk widened by this multiple of its width: "
        "a scan's sparse far range stays untouched",
    )
    min_margin_m: float = Field(
        50.0, ge=0, description="and by at least this much: thin clouds (a flat z range)"
    )
    max_gap_m: float = Field(
        20.0, gt=0, description="an empty gap this wide along an axis detaches what lies beyond"
    )
    detached_max_fraction: float = Field(
        0.01,
        ge=0,
        lt=0.5,
        description="a detached part holding at most this "
        "share of the points is stray; more is real data",
    )
    sample_points: int = Field(
        200_000, ge=1000, description="strided sample for the quantiles (stable to <1 %)"
    )


class VmfConfig(BaseModel):
    """EM of the von Mises-Fisher mixture that groups points into complexity levels."""

    model_config = ConfigDict(extra="forbid")

    # EM runs on a seeded subsample (drawn at delta0 density); every point is then labelled
    sample_size: int = Field(
        10_000, ge=100, le=10_000_000, description="points of the seeded EM subsample"
    )
    max_iter: int = Field(60, ge=1, le=10_000, description="EM iterations at most")
    tol: float = Field(
        1e-4, gt=0, le=1, description="EM stops below this relative change of the log-likelihood"
    )
    n_init: int = Field(2, ge=1, le=100, description="EM restarts; the best log-likelihood wins")
    kappa_max: float = Field(
        500.0, gt=0, le=1e6, description="cap on a component's concentration kappa"
    )


class IcpStage(BaseModel):
    """One stage of an ICP schedule."""

    model_config = ConfigDict(extra="forbid")

    max_distance: float = Field(gt=0, le=1000, description="correspondence distance (m)")
    iterations: int = Field(ge=1, le=10_000, description="ICP iterations at most")


def _level_schedule() -> list[list[IcpStage]]:
    # for level step j (0 = least complex), a coarse-to-fine schedule of stages
    return [
        [IcpStage(max_distance=3.0, iterations=30), IcpStage(max_distance=1.0, iterations=30)],
        # the second level brings the first x/y/yaw constraints: start wide again
        [
            IcpStage(max_distance=3.0, iterations=30),
            IcpStage(max_distance=1.0, iterations=30),
            IcpStage(max_distance=0.4, iterations=20),
        ],
        [IcpStage(max_distance=0.4, iterations=30), IcpStage(max_distance=0.2, iterations=30)],
    ]


def _final_schedule() -> list[IcpStage]:
    return [IcpStage(max_distance=0.25, iterations=30), IcpStage(max_distance=0.1, iterations=20)]


class ViewpointConfig(BaseModel):
    """Scanner positions of single-station scans (align/viewpoint.py), for the final ICP's side test."""

    model_config = ConfigDict(extra="forbid")

    # a terrestrial scan in its scanner frame has the scanner at the origin; mobile and airborne
    # clouds have a trajectory, not a point
    kinds: list[Literal["tls", "mls", "uls", "als"]] = Field(
        default_factory=lambda: ["tls"],
        description="sensor kinds whose file origin may be the scanner (empty: no side test)",
    )
    radius: float = Field(
        5.0,
        gt=0,
        le=100,
        description="horizontal circle (m) about the origin whose density is compared",
    )
    cell: float = Field(1.0, gt=0, le=100, description="cell (m) of the density comparison")
    # a single scan crowds around its scanner many times over; a merged plot does not
    min_crowding: float = Field(
        4.0,
        gt=1,
        le=1000,
        description="mean points per occupied cell near the origin over the cloud's, at least",
    )
    probe_points: int = Field(
        50_000, ge=1000, le=10_000_000, description="seeded sample the density is counted on"
    )


class StemNormalConfig(BaseModel):
    """Normals of round stems in sparse ground-based scans (align/normals.py stem_normals).

    At the sparse radius (1 m) a stem's neighbourhood is its whole visible arc, and the plane fit's
    normal is the view direction, tens of degrees off at the arc's edges; a circle fitted across the
    stem's axis gives each point its own radial normal.
    """

    model_config = ConfigDict(extra="forbid")

    # ground-based scans see stems from the side; airborne clouds hardly hit them
    kinds: list[Literal["tls", "mls", "uls", "als"]] = Field(
        default_factory=lambda: ["tls", "mls"],
        description="sensor kinds whose sparse normals are refined on stems (empty: never)",
    )
    neighbours: int = Field(
        40, ge=8, le=1000, description="neighbours (within the sparse radius) a circle is fitted to"
    )
    # a 1 m neighbourhood of a stem is a vertical band; of ground, a disc (linearity near 0)
    min_linearity: float = Field(
        0.3, ge=0, le=1, description="(l1 - l2) / l1 of the neighbourhood at least: stem-like"
    )
    min_points: int = Field(8, ge=4, le=1000, description="fewer neighbours: no circle")
    # above bark's roughness; branches, foliage and stem bases fit worse (docs/method.md#fine-stage-settings)
    max_residual: float = Field(
        0.02, gt=0, le=1, description="rms distance (m) of the neighbours from the circle at most"
    )
    min_radius: float = Field(0.02, gt=0, le=10, description="stem radius (m) at least")
    max_radius: float = Field(1.0, gt=0, le=10, description="stem radius (m) at most")


class AlignConfig(BaseModel):
    """Pairwise ForestAlign registration (defaults = the paper's Algorithm 1)."""

    model_config = ConfigDict(extra="forbid")

    voxel: float = Field(0.05, gt=0, le=10, description="delta0: voxel (m) of the working clouds")
    normal_radius: float = Field(
        0.25, gt=0, le=10, description="r: spherical neighbourhood (m) of the normals"
    )
    normal_max_nn: int = Field(
        20, ge=3, le=1000, description="cap on a normal's neighbours: speed on dense TLS"
    )
    # Sparse airborne clouds (~10-50 pts/m2) have almost no neighbours within 0.25 m.
    normal_radius_sparse: float = Field(
        1.0, gt=0, le=100, description="normal radius (m) of a sparse (airborne) cloud"
    )
    sparse_min_neighbors: int = Field(
        6, ge=1, le=1000, description="median neighbours within normal_radius below this: sparse"
    )
    # a sparse stem's plane normal is the view direction; its circle's radius is not
    # (docs/method.md#fine-stage-settings)
    stem_normals: StemNormalConfig = Field(
        default_factory=StemNormalConfig,
        description="circle-fitted normals on stems where a ground-based scan is sparse",
    )
    # level normals/features come from a support cloud of one delta0 point per (ratio x radius)
    # cube, so that `level_max_nn` neighbours span the 0.25 m (normal) and 0.5 m (feature) spheres
    # on dense scans too (20 neighbours of the delta0 cloud span only ~0.13 m on a dense surface)
    level_support_ratio: float = Field(
        0.4, gt=0, le=10, description="support cloud cube as a share of the radius"
    )
    level_max_nn: int = Field(
        32, ge=3, le=1000, description="neighbours of a level normal / feature at most"
    )
    final_voxel: float = Field(0.025, gt=0, le=10, description="delta: voxel (m) of the last ICP")
    complexity: Literal["vmf", "vmf+eigen"] = Field(
        "vmf+eigen", description="grouping signal: vmf (the paper's) or vMF + eigen-features"
    )
    vmf: VmfConfig = Field(default_factory=VmfConfig, description="the vMF mixture's EM")
    # Level steps run on one point per `level_cell` cube: evens out the 1/r^2 density of TLS around
    # the scanner, which otherwise pulls the scanner positions together (and is faster).
    level_cell: float = Field(
        0.2, gt=0, le=100, description="level steps run on one point per cube (m)"
    )
    level_max_points: int = Field(
        150_000,
        ge=1000,
        le=100_000_000,
        description="cap on the labelled sample (seeded): 8M-point TLS gives ~650k cubes",
    )
    level_schedule: list[list[IcpStage]] = Field(
        default_factory=_level_schedule,
        min_length=1,
        description="incremental ICP: per level step, its coarse-to-fine stages",
    )
    level_max_distance_after_coarse: float = Field(
        1.0,
        gt=0,
        le=1000,
        description="after the coarse stage (verified to ~0.3 m) wider level stages are skipped",
    )
    level_max_source_points: int = Field(
        10_000, ge=100, le=100_000_000, description="seeded source subsample per level step"
    )
    # see icp.point_to_plane_icp
    min_eig_ratio: float = Field(
        0.02, ge=0, le=1, description="level steps move only along this well constrained axes"
    )
    level_keep_ratio: float = Field(
        0.98, ge=0, le=10, description="a level result is kept if its fitness >= this x its start's"
    )
    level_tol: float = Field(
        1e-4, gt=0, le=1, description="a level stage ends when a step moves points less (m)"
    )
    final_tol: float = Field(
        5e-5, gt=0, le=1, description="the final ICP ends when a step moves points less (m)"
    )
    final_schedule: list[IcpStage] = Field(
        default_factory=_final_schedule, min_length=1, description="stages of the final ICP"
    )
    # the fine stage's last, tight stage where both clouds are dense (align/fine.final_icp), x the
    # judge's scale factor; on sparse clouds it would be looser than the last stage and is left out
    # (docs/method.md#fine-stage-settings)
    final_polish_distance: float = Field(
        0.05, gt=0, le=1, description="correspondence distance (m) of the fine stage's polish stage"
    )
    final_polish_iterations: int = Field(
        20, ge=0, le=100, description="iterations of the polish stage"
    )
    final_polish_kernel: float = Field(
        0.03, gt=0, le=1, description="least Tukey width (m) of the fine stage when it polishes"
    )
    # two scans of these kinds polish at final_polish_* unscaled, however sparse: their plane
    # residuals are range noise (mm); unpolished, stems seen from opposite sides pull far pairs short
    # (docs/method.md#fine-stage-settings)
    final_polish_fixed_kinds: list[Literal["tls", "mls", "uls", "als"]] = Field(
        default_factory=lambda: ["tls"],
        description="pairs of these sensor kinds polish unscaled (others x the judge's scale factor)",
    )
    # two scans of these kinds end with a symmetric ICP (each one's sample on the other's planes, one
    # solve: neither side's plane errors dominate; docs/method.md#fine-stage-settings); other kinds,
    # and a pair whose target is `final_reverse_ratio` sparser, keep one direction (the denser cloud's
    # planes: a sparse cloud's planes bias it)
    final_symmetric_kinds: list[Literal["tls", "mls", "uls", "als"]] = Field(
        default_factory=lambda: ["tls"],
        description="pairs of these sensor kinds end with a symmetric ICP (empty: one direction)",
    )
    # a pair whose fine sample lies mostly away from the other cloud overlaps thinly (sparse
    # surveys, scans onto maps): its samples are drawn again from where the clouds meet
    # (docs/method.md#fine-stage-settings)
    lens_max_share: float = Field(
        0.25,
        ge=0,
        le=1,
        description="less of the source's fine sample this near the target: the last ICP runs"
        " again on samples of the overlap (0: never)",
    )
    lens_distance: float = Field(
        0.3, gt=0, le=10, description="a point this near (m) the other cloud is in the overlap"
    )
    final_max_source_points: int = Field(
        40_000,
        ge=100,
        le=100_000_000,
        description="seeded sample of the source's delta grid for the last ICP (target whole)",
    )
    robust_kernel: float = Field(
        0.1,
        gt=0,
        le=100,
        description="least Tukey width (m) of the final ICP (half the distance above it)",
    )
    quality_max_points: int = Field(
        100_000,
        ge=1000,
        le=100_000_000,
        description="query points per direction for fitness / overlap (+-0.2 %)",
    )
    quality_distance: float = Field(
        0.25, gt=0, le=100, description="fitness / inlier RMSE / overlap distance (m; paper 25 cm)"
    )
    min_fitness: float = Field(
        0.1, ge=0, le=1, description="below: cannot register (exit 3); sparse true pairs ~0.18"
    )
    min_overlap: float = Field(0.05, ge=0, le=1, description="below: cannot register (exit 3)")
    max_inlier_rmse: float = Field(
        0.2, gt=0, le=100, description="above (m): cannot register; sparse ALS alone gives ~0.16"
    )
    # judge confidence below this => ambiguous => exit 3: a distinct rival pose fits almost as well;
    # between the wrong poses' highest and the right poses' lowest (docs/method.md#judge-settings);
    # register-plot sets 0 and lets its loops decide
    min_confidence: float = Field(
        0.25, ge=0, le=1, description="least judge confidence (margin over the best distinct rival)"
    )
    # the final ICP takes its planes from the denser cloud: planes of a sparse ALS target (1 m
    # normals) bias yaw (docs/method.md#fine-stage-settings); registered the other way round and inverted
    final_reverse_ratio: float = Field(
        2.0,
        ge=1,
        description="target spacing / source spacing above which the final ICP runs target -> source",
    )
    # the final ICP keeps a match only where both scanners see the same side of its plane: a point on
    # the far side of a thin stem or branch no longer pulls two scans together
    # (docs/method.md#fine-stage-settings)
    viewpoint: ViewpointConfig = Field(
        default_factory=ViewpointConfig,
        description="scanner positions for the final ICP's side test",
    )
    # a pose that puts points where a known scanner saw through is ruled out: at thin overlap the
    # wrong poses overlap more by chance (docs/method.md#free-space)
    free_space: FreeSpaceConfig = Field(
        default_factory=FreeSpaceConfig,
        description="the space a scanner saw through: ranks the search, rules out rivals",
    )
    coarse: CoarseConfig = Field(
        default_factory=CoarseConfig, description="the global coarse search"
    )
    judge: JudgeConfig = Field(
        default_factory=JudgeConfig, description="the pose judge (distinct rivals)"
    )
    stray: StrayConfig = Field(
        default_factory=StrayConfig, description="stray points dropped before any grid"
    )
    kinds: KindConfig = Field(
        default_factory=KindConfig,
        description="a cloud's sensor kind from its points, where no kind is given",
    )
