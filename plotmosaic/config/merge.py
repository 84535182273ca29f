"""Settings of `merge` (a leaf: imports nothing else of the project)."""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

SCALE = 0.001  # 1 mm: the output's coordinate resolution
CHUNK_SIZE = 2_000_000  # points read at once (as plotmosaic.io.las reads)


class MergeConfig(BaseModel):
    """Options of `merge` (defaults = plain merge of every posed scan)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    voxel: float | None = Field(
        default=None,
        gt=0,
        le=1000,
        description="voxel size (m) for thinning, rounded to whole mm (unset: no thinning)",
    )
    include_als: bool = Field(default=False, description="add the manifest's ALS tiles")
    bbox: tuple[float, ...] | None = Field(
        default=None,
        description="keep only xmin, ymin, xmax, ymax[, zmin, zmax] in output coordinates",
    )
    force: bool = Field(default=False, description="overwrite an existing output")
    skip_missing: bool = Field(
        default=False, description="skip scans without a pose instead of failing"
    )
    chunk_size: int = Field(
        default=CHUNK_SIZE, ge=1, le=1_000_000_000, description="points read and written at once"
    )
    tile_memory_mb: int = Field(
        default=512,
        ge=1,
        le=1 << 20,
        description="memory (MB) for the tiles thinned at once: tiles are cut to fit it, whatever the output size",
    )
    tiles: bool = Field(
        default=False,
        description="write one LAZ per square tile into the folder --out, plus index.json",
    )
    tile_size: float = Field(
        default=100.0,
        gt=0,
        le=100_000,
        description="tile edge (m) with --tiles, whole mm; tiles are anchored at the output offset (a multiple of 1 km)",
    )

    @field_validator("voxel")
    @classmethod
    def _voxel_mm(cls, value: float | None) -> float | None:
        if value is not None and round(value / SCALE) < 1:
            raise ValueError("must be at least 0.001 (1 mm, the output resolution)")
        return value

    @field_validator("tile_size")
    @classmethod
    def _tile_mm(cls, value: float) -> float:
        if abs(round(value / SCALE) * SCALE - value) > 1e-9 * max(1.0, value):
            raise ValueError("must be a whole number of mm")
        return value

    @model_validator(mode="after")
    def _tiles_on_voxel_faces(self) -> MergeConfig:
        # a voxel cut by a tile edge would be thinned twice: tiles must be whole voxels
        if self.tiles and self.voxel and round(self.tile_size / SCALE) % round(self.voxel / SCALE):
            raise ValueError(
                f"--tile-size {self.tile_size:g} must be a whole multiple of --voxel {self.voxel:g}"
            )
        return self

    @field_validator("bbox")
    @classmethod
    def _bbox(cls, value: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if value is None:
            return None
        if len(value) not in (4, 6):
            raise ValueError("needs 4 or 6 numbers: xmin,ymin,xmax,ymax[,zmin,zmax]")
        if not all(np.isfinite(value)):
            raise ValueError("numbers must be finite")
        lo, hi = bbox_limits(value)
        if np.any(lo >= hi):
            raise ValueError("each min must be smaller than its max")
        return tuple(float(v) for v in value)


def bbox_limits(bbox: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    zlo, zhi = (bbox[4], bbox[5]) if len(bbox) == 6 else (-np.inf, np.inf)
    return np.array([bbox[0], bbox[1], zlo]), np.array([bbox[2], bbox[3], zhi])
