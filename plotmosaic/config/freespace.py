"""Settings of the free-space test (align/freespace.py): a pose that puts points where a scanner saw
through is no pose. Calibration: docs/method.md#free-space."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class FreeSpaceConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(
        True,
        description="weigh poses by the space a scan with a known scanner saw through "
        "(search ranking, the judge's rivals)",
    )
    resolution_deg: float = Field(
        0.5, gt=0, le=10, description="angular cell (deg) of a scanner's nearest-return image"
    )
    # a point this far in front of the nearest return of its direction lies where the beam passed
    margin_m: float = Field(
        0.4,
        gt=0,
        le=10,
        description="in front of the nearest return by more than this: seen through",
    )
    screen_margin_m: float = Field(
        1.0,
        gt=0,
        le=20,
        description="the same for a start after its short ICP (still up to a metre off)",
    )
    # right poses put 0-3 % of the points a scanner could see where it saw through, wrong ones
    # 8-45 %: a share above this marks a pose the scene rules out
    max_share: float = Field(
        0.10,
        gt=0,
        le=1,
        description="share of the points a scanner could see lying where it saw through, at most",
    )
    # a pose that itself lies near the limit gains nothing by its rivals' exclusion: a wrong pose
    # 0.087 of the way seen through passed at sharpness 0.03 once its rivals (0.12-0.14) were out
    pose_max_share: float = Field(
        0.05,
        gt=0,
        le=1,
        description="the judge rules rivals out only for a pose seen through at most this much",
    )
    screen_max_share: float = Field(
        0.12, gt=0, le=1, description="the same for a start after its short ICP"
    )
    min_seen: int = Field(
        30, ge=1, le=100_000, description="fewer points a scanner could see: no figure"
    )
