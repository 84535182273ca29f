"""Settings of the global coarse stage (levelling, vertical hypotheses, generators, verification).

Config modules are leaves: they import nothing of the project but other settings modules.
"""

from __future__ import annotations

from pydantic import ConfigDict, Field

from plotmosaic.config.coarse_generators import CoarseGenerators
from plotmosaic.config.coarse_levelling import CoarseLevelling


# pydantic orders fields from the last base to the first: levelling, generators, then verification
class CoarseConfig(CoarseGenerators, CoarseLevelling):
    model_config = ConfigDict(extra="forbid")

    # --- verification
    start_duplicate_m: float = Field(
        0.5, gt=0, le=10, description="starts closer than this (m) and ..."
    )
    start_duplicate_deg: float = Field(
        2.0, gt=0, le=20, description="... than this (deg) are screened once"
    )
    verify_voxel: float = Field(
        0.3, gt=0, le=5, description="voxel (m) of the clouds hypotheses are refined and scored on"
    )
    verify_points: int = Field(
        6_000,
        ge=100,
        le=1_000_000,
        description="source points used to refine and score the best hypotheses",
    )
    screen_points: int = Field(
        3_000,
        ge=100,
        le=1_000_000,
        description="of those, the points of the first short ICP that ranks every hypothesis",
    )
    verify_iterations: int = Field(
        10, ge=1, le=200, description="ICP iterations per verification stage"
    )
    verify_iterations_airborne: int = Field(
        30,
        ge=1,
        le=200,
        description="the same when a cloud is airborne: a leaf-on strip "
        "levelled 5 deg off needs them to tilt into place (sparse targets: cheap)",
    )
    refine_top: int = Field(
        8,
        ge=1,
        le=64,
        description="distinct screened poses refined fully (each generator's best among them)",
    )
    structure_normal_z: float = Field(
        0.8,
        gt=0,
        le=1,
        description="|normal z| below this: a non-flat point that scores (flat ground matches anywhere)",
    )
    screen_about_vertical: bool = Field(
        True,
        description="ground-based pairs: screening and the refine's wide stages turn only about "
        "the start's vertical (thin overlap tilts a right start away); the last stage turns freely",
    )
    screen_distance_factor: float = Field(
        6.0, gt=0, le=50, description="screening ICP distance, in inlier distances"
    )
    screen_score_factor: float = Field(
        2.0, gt=0, le=20, description="screening score distance, in inlier distances"
    )
    refine_distance_factors: tuple[float, ...] = Field(
        (3.0, 1.5), description="refine ICP distances, in inlier distances"
    )
    verify_distance_ground: float = Field(
        0.2, gt=0, le=5, description="inlier distance (m) between ground-based scans"
    )
    verify_distance_airborne: float = Field(
        0.5, gt=0, le=5, description="inlier distance (m) when one cloud is airborne (sparse)"
    )
    distinct_m: float = Field(
        1.0, gt=0, le=50, description="poses further apart than this (m) are distinct rivals ..."
    )
    distinct_deg: float = Field(
        3.0, gt=0, le=90, description="... or further apart than this (deg)"
    )
    # the quick refine leaves starts of the best pose's own basin a few degrees short on loose
    # fits (scattered foliage): one near the best is refined on, so it is no rival of the
    # confidence (docs/method.md#coarse-stage-settings)
    near_rival_radii: float = Field(
        3.0,
        ge=1,
        le=10,
        description="a refined pose within this many distinct radii of the best is refined on",
    )
    near_rival_passes: int = Field(
        4, ge=0, le=16, description="further refinements of such a pose at most (0: none)"
    )
    prior_yaw_deg: float = Field(
        30.0, gt=0, le=180, description="with an initial guess: headings searched either side of it"
    )
    prior_shift_m: float = Field(
        8.0,
        gt=0,
        le=1000,
        description="with an initial guess: horizontal distance searched around it",
    )
