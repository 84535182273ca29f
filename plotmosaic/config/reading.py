"""Settings of reading a scan for registration (a leaf: imports nothing else of the project)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class ReadingConfig(BaseModel):
    """How much of a scan registration holds at once while reading it (io/bounded.py)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # a scan within the budget is read whole, exactly; a bigger one keeps the first point (in file
    # order) of each occupied cell, far finer than any grid registration builds on it
    max_points_in_memory: int = Field(
        20_000_000,
        ge=10_000,
        le=2_000_000_000,
        description="float64 points held at once while reading a scan: a bigger scan is thinned "
        "on reading to one point per cell",
    )
    cell_share: float = Field(
        0.5,
        gt=0,
        le=1,
        description="the thinning cell as a share of the finest voxel registration uses "
        "(align.voxel, align.final_voxel); doubled until the kept points fit the budget",
    )

    def thinning_cell(self, finest_voxel: float) -> float:
        """The first thinning cell (m) for a registration whose finest voxel is `finest_voxel`."""
        return self.cell_share * finest_voxel
