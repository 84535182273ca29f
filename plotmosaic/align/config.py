"""Typed settings for ForestAlign pairwise registration (defaults = the paper's Algorithm 1)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from plotmosaic.align.coarse_config import CoarseConfig
from plotmosaic.align.judge_config import JudgeConfig

KINDS = ("tls", "mls", "uls", "als")

# Levels per sensor kind (paper, Algorithm 1): ground-based scans see ground, stems and foliage;
# airborne scans mostly ground and canopy. Grassland plots (no trees) should use 1-2 via the flag.
DEFAULT_LEVELS = {"tls": 3, "mls": 3, "uls": 2, "als": 2}


def default_levels(kind: str) -> int:
    return DEFAULT_LEVELS[kind.lower()]


class StrayConfig(BaseModel):
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
    sample_size: int = 10_000  # EM runs on a seeded subsample (drawn at delta0 density); every point is then labelled
    max_iter: int = 60
    tol: float = 1e-4  # relative change of the mean log-likelihood
    n_init: int = 2  # restarts; the best log-likelihood wins
    kappa_max: float = 500.0


class IcpStage(BaseModel):
    max_distance: float  # correspondence distance (m)
    iterations: int


class AlignConfig(BaseModel):
    voxel: float = Field(0.05, gt=0)  # delta0
    normal_radius: float = Field(0.25, gt=0)  # r, spherical neighbourhood
    normal_max_nn: int = 20  # cap the neighbourhood size: speed on dense TLS, same planes
    # Sparse airborne clouds (~10-50 pts/m2) have almost no neighbours within 0.25 m; use a wider sphere.
    normal_radius_sparse: float = 1.0
    sparse_min_neighbors: int = (
        6  # median neighbours within normal_radius below this => sparse cloud
    )
    # level normals/features come from a support cloud of one delta0 point per (ratio x radius) cube,
    # so that `level_max_nn` neighbours span the 0.25 m (normal) and 0.5 m (feature) spheres on
    # dense scans too (20 neighbours of the delta0 cloud span only ~0.13 m on a dense surface)
    level_support_ratio: float = 0.4
    level_max_nn: int = 32
    final_voxel: float = Field(0.025, gt=0)  # delta for the last ICP
    complexity: Literal["vmf", "vmf+eigen"] = "vmf+eigen"
    vmf: VmfConfig = VmfConfig()
    # Level steps run on one point per `level_cell` cube: evens out the 1/r^2 density of TLS around
    # the scanner, which otherwise pulls the scanner positions together (and is faster).
    level_cell: float = 0.2
    level_max_points: int = (
        150_000  # cap on the labelled sample (seeded): TLS scans of 8M points give ~650k cubes
    )
    # Incremental ICP: for level step j (0 = least complex), a coarse-to-fine schedule of stages.
    level_schedule: list[list[IcpStage]] = [
        [IcpStage(max_distance=3.0, iterations=30), IcpStage(max_distance=1.0, iterations=30)],
        # the second level brings the first x/y/yaw constraints: start wide again
        [
            IcpStage(max_distance=3.0, iterations=30),
            IcpStage(max_distance=1.0, iterations=30),
            IcpStage(max_distance=0.4, iterations=20),
        ],
        [IcpStage(max_distance=0.4, iterations=30), IcpStage(max_distance=0.2, iterations=30)],
    ]
    # after the coarse stage (verified to ~0.3 m) level stages wider than this are skipped
    level_max_distance_after_coarse: float = 1.0
    level_max_source_points: int = 10_000  # seeded subsample of the source per level step
    min_eig_ratio: float = 0.02  # level steps move only along directions this well constrained (see icp.point_to_plane_icp)
    level_keep_ratio: float = (
        0.98  # level ICP result kept only if its fitness >= this x that of its start
    )
    level_tol: float = (
        1e-4  # a level stage ends when a step moves points < this (m); the final ICP refines
    )
    final_tol: float = 5e-5
    final_schedule: list[IcpStage] = [
        IcpStage(max_distance=0.25, iterations=30),
        IcpStage(max_distance=0.1, iterations=20),
    ]
    final_max_source_points: int = (
        40_000  # seeded sample of the source's delta grid for the last ICP (target kept whole)
    )
    robust_kernel: float = (
        0.1  # least Tukey width (m) of the final ICP (half the correspondence distance above it)
    )
    quality_max_points: int = (
        100_000  # query points per direction for fitness / overlap (+-0.2 % on the figures)
    )
    quality_distance: float = 0.25  # fitness / inlier RMSE / overlap distance (paper: 25 cm)
    min_fitness: float = 0.1  # below => RegistrationFailed (exit 3); sparse true pairs reach ~0.18
    min_overlap: float = 0.05
    max_inlier_rmse: float = 0.2  # point-to-point at 0.25 m; a sparse ALS target alone gives ~0.16
    # judge confidence below this => ambiguous => exit 3: a distinct rival pose fits almost as well
    # (benchmarks/bench_judge.py, 12 real and simulated cases: right poses 0.29-1.0, wrong ones 0.00-0.10;
    # but a leaf-on UAS strip -> ALS pose 10.6 deg / 1.6 m off reached 0.21 in bench_coarse_real.py, so
    # the floor sits between that and the lowest right pose; register-plot sets 0 and lets its loops decide)
    min_confidence: float = Field(
        0.25, ge=0, le=1, description="least judge confidence (margin over the best distinct rival)"
    )
    # the final ICP takes its planes from the denser cloud: planes of a sparse ALS target (1 m
    # normals) bias yaw by ~0.2 deg on UAS -> ALS; registered the other way round and inverted
    final_reverse_ratio: float = Field(
        2.0,
        ge=1,
        description="target spacing / source spacing above which the final ICP runs target -> source",
    )
    coarse: CoarseConfig = CoarseConfig()
    judge: JudgeConfig = JudgeConfig()
    stray: StrayConfig = StrayConfig()
