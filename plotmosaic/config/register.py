"""Settings of register-plot, its pose graph and tie-to-als (a leaf: imports only config modules)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from plotmosaic.config.align import AlignConfig
from plotmosaic.config.coarse import CoarseConfig
from plotmosaic.config.reading import ReadingConfig
from plotmosaic.config.report import ReportConfig
from plotmosaic.config.scale import MapConfig, PlacedPriors, SignatureConfig


class PairSelection(BaseModel):
    """How register-plot chooses the pairs to register."""

    model_config = ConfigDict(extra="forbid")

    all_pairs_up_to: int = Field(
        8, ge=2, le=64, description="plots of at most this many scans try every pair"
    )
    neighbours: int = Field(
        6, ge=2, le=16, description="nearest scans each scan of a big plot is paired with"
    )
    max_per_scan: int = Field(
        8, ge=2, le=16, description="cap on the pairs of one scan (linear growth)"
    )


class PoseGraphConfig(BaseModel):
    """Tuning of the pose-graph solve. Angles in degrees, lengths in metres."""

    model_config = ConfigDict(extra="forbid")

    robust: Literal["cauchy", "huber", "none"] = Field(
        "cauchy", description="robust kernel of every edge"
    )
    robust_k: float = Field(3.0, gt=0, le=100, description="kernel width in whitened (sigma) units")
    # Pairwise information matrices from ICP are often over-confident: floor each sigma and cap
    # the ratio of strongest to weakest direction so the problem stays well conditioned.
    min_sigma_rotation_deg: float = Field(
        0.01, gt=0, le=10, description="floor of an edge's rotation sigma"
    )
    min_sigma_translation: float = Field(
        0.002, gt=0, le=1, description="floor of an edge's translation sigma (m)"
    )
    max_information_ratio: float = Field(
        1e4, ge=1, le=1e12, description="cap on strongest / weakest direction"
    )
    # a scan placed on a sparse ALS tile is off by 0.02-0.12 deg and 0.3-1.5 cm (16 placements
    # of a sparse understorey plot, docs/method.md#plot-settings), whatever its ICP information says
    anchor_min_sigma_rotation_deg: float = Field(
        0.05, gt=0, le=10, description="floor of an ALS placement edge's rotation sigma"
    )
    anchor_min_sigma_translation: float = Field(
        0.01, gt=0, le=1, description="floor of an ALS placement edge's translation sigma (m)"
    )
    fallback_sigma_rotation_deg: float = Field(
        0.1, gt=0, le=45, description="when a pair carries no information matrix"
    )
    # A triangle of edges is inconsistent when going around it is off by more than this.
    cycle_rotation_deg: float = Field(
        1.0, gt=0, description="triangle loop rotation beyond which it is inconsistent"
    )
    cycle_translation: float = Field(
        0.10, gt=0, description="triangle loop translation (m) beyond which it is inconsistent"
    )
    # An edge whose coarse-stage confidence is below this is kept only when a consistent triangle
    # confirms it: a wrong coarse solution can still pass the pair's own fitness checks.
    sure_edge_confidence: float = Field(
        0.25,
        ge=0,
        le=1,
        description="least confidence of an edge kept without a consistent triangle confirming it",
    )
    # After a solve, an edge is an outlier when its residual exceeds both a metric bound and a
    # chi-square bound (6 dof); the metric bound keeps over-confident good edges.
    outlier_rotation_deg: float = Field(
        0.5, gt=0, description="residual rotation an outlier exceeds"
    )
    outlier_translation: float = Field(
        0.10, gt=0, description="residual translation (m) an outlier exceeds"
    )
    outlier_chi2: float = Field(
        22.46, gt=0, description="residual chi2 an outlier exceeds (6 dof, p = 0.999)"
    )
    max_drops: int = Field(
        50,
        ge=0,
        le=100_000,
        description="residual drops (one re-solve each); cycle-vote drops not counted",
    )
    max_iterations: int = Field(
        100, ge=1, le=10_000, description="Levenberg-Marquardt iterations per solve"
    )
    # ICP information gives an edge's shape, not its scale: where loops observe it, each edge
    # group's information is scaled by its residuals (graph/covariance.py); 0 keeps it as is
    calibration_rounds: int = Field(
        3, ge=0, le=20, description="rounds of scaling edge noise by the residuals (re-solve each)"
    )


def _onto_als(align: AlignConfig, fpfh: bool, **search: int) -> AlignConfig:
    """[align] for a TLS cloud onto an ALS tile, with its own FPFH switch (off there, or off in
    [align.coarse], is off) and its own coarse-search settings."""
    coarse = align.coarse.model_copy(update={"fpfh": fpfh and align.coarse.fpfh, **search})
    return align.model_copy(update={"coarse": coarse})


def _fpfh_switch(when: str) -> Any:
    """The FPFH switch of a TLS -> ALS search."""
    return Field(
        CoarseConfig.model_fields["fpfh"].default,
        description=f"FPFH starts when {when} (off here or in align.coarse is off): they run only "
        "where the cheaper generators have not settled, and a real UAS strip onto its ALS found "
        "its pose only by them",
    )


class _Shared(BaseModel):
    """The sections a stage shares with the others and does not hold in its own table (excluded
    from it; Settings fills them in)."""

    model_config = ConfigDict(extra="forbid")

    report: ReportConfig = Field(
        default_factory=ReportConfig, exclude=True, description="the report's pictures"
    )
    read: ReadingConfig = Field(
        default_factory=ReadingConfig,
        exclude=True,
        description="the memory budget of reading a scan",
    )


class RegisterConfig(_Shared):
    """register-plot: its [register_plot] section; the sections it shares with the other stages
    ([align], [posegraph], [pairs], [report], [read]) are filled in by Settings.register_config()."""

    model_config = ConfigDict(extra="forbid")

    max_distance: float | None = Field(
        60.0,
        gt=0,
        le=100_000,
        description="with approximate positions: pairs of scans farther apart (m) are not tried",
    )
    place_on_als: bool = Field(
        True, description="big plots without positions: place each scan on the ALS first"
    )
    # every placement the judge verified is used (a position, a prior and an anchor): a sparse
    # survey's placements are right at confidences 0.26-0.49 (docs/method.md#plot-settings)
    placement_min_confidence: float = Field(
        0.0,
        ge=0,
        le=1,
        description="least judge confidence of an ALS placement that is used, beyond the judge's own"
        " verdict (0: every verified placement)",
    )
    # the ALS placements as edges to one ALS node per plot: they do not depend on the scan-to-scan
    # edges, so they hold the far corners of a big plot where a chain of pairs drifts, and place a
    # scan whose pairs are refused (docs/method.md#plot-settings)
    als_anchors: bool = Field(
        True, description="ALS placements of a plot's scans are edges of its pose graph"
    )
    # unsure pairs still become edges: the pose graph keeps one only when a loop confirms it
    pair_min_confidence: float = Field(
        0.0,
        ge=0,
        le=1,
        description="judge floor of register-plot's pairs (replaces align.min_confidence there): "
        "unsure pairs still become edges, a loop must confirm them",
    )
    placement_fpfh: bool = _fpfh_switch("placing a scan on the ALS tile")
    # a placement is a prior and an edge that the pairs it implies verify again
    # (benchmarks/results/speed.md)
    placement_settled_generators: int = Field(
        1,
        ge=1,
        le=3,
        description="generators that must agree before a placement's search stops at the first "
        "vertical pair (replaces align.coarse.settled_generators there): a placement is a prior "
        "the pairs verify again, and one clear pose ahead of its rivals is enough",
    )
    signature: SignatureConfig = Field(
        default_factory=SignatureConfig,
        description="stem-map signatures: partners of the scans without a position",
    )
    placed_priors: PlacedPriors = Field(
        default_factory=PlacedPriors,
        description="priors from two ALS placements, verified before any search",
    )
    maps: MapConfig = Field(
        default_factory=MapConfig,
        description="scans without a verified pair placed onto their placed neighbours together",
    )
    # the shared sections: not keys of [register_plot] (exclude: the file never holds them here)
    align_settings: AlignConfig = Field(
        default_factory=AlignConfig,
        exclude=True,
        description="[align]: pairs take it with pair_min_confidence, placements with placement_*",
    )
    graph: PoseGraphConfig = Field(
        default_factory=PoseGraphConfig,
        exclude=True,
        description="the pose-graph solve of each plot",
    )
    pairs: PairSelection = Field(
        default_factory=PairSelection, exclude=True, description="which pairs are registered"
    )

    @property
    def align(self) -> AlignConfig:
        """Pairwise registration of two scans."""
        return self.align_settings.model_copy(update={"min_confidence": self.pair_min_confidence})

    @property
    def placement(self) -> AlignConfig:
        """Scan -> ALS: verified poses only; its search stops at the first vertical pair once
        `placement_settled_generators` agree."""
        return _onto_als(
            self.align_settings,
            self.placement_fpfh,
            settled_generators=self.placement_settled_generators,
        )


def placement_align_config() -> AlignConfig:
    """A scan onto the ALS tile to place it, as register-plot does by default."""
    return RegisterConfig().placement


class TieConfig(_Shared):
    """tie-to-als: its [tie_to_als] section; the sections it shares with the other stages
    ([align], [posegraph], [report], [read]) are filled in by Settings.tie_config()."""

    model_config = ConfigDict(extra="forbid")

    buffer: float = Field(
        20.0,
        ge=0,
        le=100_000,
        description="metres of ALS kept around each plot's footprint (with CRS positions)",
    )
    plot_voxel: float = Field(
        0.05,
        gt=0,
        le=10,
        description="thinning (m) of the merged plot cloud: TLS is far denser than needed",
    )
    # one anchor a plot: no loop shows its error, so the spread of the ALS fit over blocks of
    # ground left out one at a time is its covariance (stages/tie_to_als/anchor_fit.py)
    anchor_block: float = Field(
        10.0, gt=0, le=1000, description="largest side (m) of the blocks of the anchor's jackknife"
    )
    anchor_max_distance: float = Field(
        0.3, gt=0, le=10, description="ALS points farther (m) from the TLS surfaces are not matched"
    )
    anchor_fpfh: bool = _fpfh_switch("registering a plot to the ALS")
    # the shared sections: not keys of [tie_to_als]
    align_settings: AlignConfig = Field(
        default_factory=AlignConfig, exclude=True, description="[align]: taken with anchor_fpfh"
    )
    graph: PoseGraphConfig = Field(
        default_factory=PoseGraphConfig,
        exclude=True,
        description="the region's pose graph, ALS fixed",
    )

    @property
    def align(self) -> AlignConfig:
        """Registration of each plot to the ALS."""
        return _onto_als(self.align_settings, self.anchor_fpfh)
