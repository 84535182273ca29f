"""Settings of register-plot's scaling steps: stem-map signatures (graph/signature.py) and the use of
ALS placements as verified-first priors (graph/placement.py). A leaf: imports nothing of the project.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class SignatureConfig(BaseModel):
    """Per-scan stem-map signatures that rank candidate partners without positions."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(
        True, description="big plots without positions: rank partners by signature"
    )
    voxel: float = Field(0.05, gt=0, le=1, description="voxel (m) the scan is thinned to first")
    max_points: int = Field(
        400_000, ge=1000, le=10_000_000, description="cap on the thinned points used"
    )
    normal_radius: float = Field(0.3, gt=0, le=5, description="normal neighbourhood (m)")
    normal_neighbours: int = Field(30, ge=5, le=200, description="cap on normal neighbours")
    min_side_m: float = Field(1.0, ge=0, le=20, description="shortest triangle side kept (m)")
    max_side_m: float = Field(15.0, gt=0, le=50, description="longest triangle side kept (m)")
    max_triangles: int = Field(
        20_000, ge=10, le=1_000_000, description="cap on triangles per scan (most compact first)"
    )
    tolerance_m: float = Field(
        0.3, gt=0, le=2, description="triangles within this (m, side lengths) match"
    )
    min_votes: int = Field(2, ge=1, le=1000, description="fewer matches than this: no candidate")
    agree_deg: float = Field(3.0, gt=0, le=45, description="triangle poses this close agree (deg)")
    agree_m: float = Field(0.5, gt=0, le=10, description="... and this close (m)")
    footprint_m: float = Field(
        3.0, gt=0, le=50, description="a moved stem this near the other map's stems is inside it"
    )
    min_share: float = Field(
        0.3, ge=0, le=1, description="fewer of the stems inside the other map matched: chance"
    )
    stem_match_m: float = Field(
        0.3, gt=0, le=5, description="a moved stem this near a stem matches"
    )
    min_stems: int = Field(4, ge=3, le=100, description="fewer stems matched: not a candidate")
    shortlist: int = Field(
        12, ge=1, le=200, description="scans per scan whose shared triangles get the pose check"
    )
    max_matches: int = Field(
        3000, ge=10, le=100_000, description="cap on triangle matches examined per scan pair"
    )
    grow_rounds: int = Field(
        2, ge=0, le=10, description="rounds of extra pairs while a plot's graph is in pieces"
    )
    grow_per_scan: int = Field(
        2, ge=1, le=8, description="extra ranked partners per disconnected scan and round"
    )
    partners: int = Field(
        4, ge=1, le=16, description="best-ranked partners each scan is registered with"
    )
    # the best-ranked partner of an unplaced scan is mostly its grid neighbour
    # (docs/method.md#plot-settings)
    placed_partners: int = Field(
        1,
        ge=1,
        le=16,
        description="... in a plot with ALS placements (the graph places the rest by position)",
    )


class PlacedPriors(BaseModel):
    """Pairs of two scans placed on the ALS: their prior is checked first, the search run only if it fails."""

    model_config = ConfigDict(extra="forbid")

    verify_first: bool = Field(
        True, description="a prior from two sure placements is verified before any search"
    )
    # placements this sure were all right to cm (docs/method.md#plot-settings); a prior that does not
    # verify still gets the full search
    sure_placement_confidence: float = Field(
        0.8,
        ge=0,
        le=1,
        description="both placements at least this sure (judge confidence) to verify first",
    )
    # far pairs rarely verify and cost a full search each (docs/method.md#plot-settings); two placed
    # scans close a loop through the ALS node anyway
    reach: float = Field(
        1.25,
        gt=0,
        le=10,
        description="scans placed to cm paired at most this many times the scan spacing apart",
    )
    position_rounds: int = Field(
        3,
        ge=0,
        le=10,
        description="rounds of neighbour pairs between scans the verified graph has placed",
    )


class MapConfig(BaseModel):
    """Scan-to-map placement (graph/maps.py): a scan without a verified pair registered against
    the union of the placed scans near it."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(
        True, description="place scans without a verified pair onto their placed neighbours"
    )
    # a map measured at placements that the next solve moves is measured again from there: the
    # rounds settle the survey as one (multi-view ICP through the pose graph)
    rounds: int = Field(
        1, ge=0, le=10, description="rounds of map placements, each from the last solve's poses"
    )
    settled_m: float = Field(
        0.002, gt=0, le=1, description="no scan moved more (m) in a round: the maps are settled"
    )
    settled_deg: float = Field(0.005, gt=0, le=1, description="... nor turned more (deg)")
    reach: float = Field(
        2.0,
        gt=0,
        le=10,
        description="placed scans within this many scan spacings of a scan form its map",
    )
    margin_m: float = Field(
        2.0, ge=0, le=50, description="the map is cropped this far (m) beyond the scan's reach"
    )
    thin_voxel: float = Field(
        0.1,
        gt=0,
        le=5,
        description="voxel (m) of a whole-plot map, for a scan with no start (its memory bounded)",
    )
    # rounds of maps remove a bend or a tilt across the plot only slowly: all poses are solved
    # together on every scan-neighbour pair once the maps have verified where each scan stands
    survey: bool = Field(
        True, description="refine the survey as one (multi-view ICP) after the map placements"
    )
    survey_points: int = Field(
        20_000, ge=100, le=1_000_000, description="sample points of each pair and direction"
    )
    survey_schedule: list[tuple[float, int]] = Field(
        [(0.1, 5), (0.05, 10)],
        description="(correspondence distance m, iterations) stages of the survey refinement",
    )
    # a pair's residuals err together over a patch of bark or a twig: its information counts
    # patches, not points (docs/method.md#plot-settings)
    survey_patch_m: float = Field(
        2.0, gt=0, le=10, description="side (m) of the patches whose residuals err together"
    )
    edge_distance: float = Field(
        0.1, gt=0, le=2, description="correspondences (m) that give a map member its share"
    )
    min_edge_points: int = Field(
        200, ge=10, le=100_000, description="fewer correspondences: the member gets no edge"
    )
