"""Point clouds in memory: coordinates (float64, file coordinates) with per-point attributes and a
CRS, and what a file's header says about its points (`HeaderInfo`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
from pyproj import CRS

# Standard attributes carried through the tool (LAS dimension name -> dtype).
STANDARD_ATTRIBUTES: dict[str, np.dtype] = {
    "intensity": np.dtype(np.uint16),
    "return_number": np.dtype(np.uint8),
    "number_of_returns": np.dtype(np.uint8),
    "classification": np.dtype(np.uint8),
    "gps_time": np.dtype(np.float64),
    "red": np.dtype(np.uint16),
    "green": np.dtype(np.uint16),
    "blue": np.dtype(np.uint16),
    "point_source_id": np.dtype(np.uint16),
}
RGB = ("red", "green", "blue")


@dataclass(frozen=True)
class PointCloud:
    """Points in file coordinates (float64) with optional per-point attributes and a CRS."""

    xyz: np.ndarray
    attrs: dict[str, np.ndarray] = field(default_factory=dict)
    crs: CRS | None = None

    def __post_init__(self) -> None:
        # frozen: the normalised array replaces the given one, once, before anyone sees it
        object.__setattr__(
            self, "xyz", np.ascontiguousarray(self.xyz, dtype=np.float64).reshape(-1, 3)
        )
        for name, values in self.attrs.items():
            if len(values) != len(self.xyz):
                raise ValueError(
                    f"attribute {name!r} has {len(values)} values for {len(self.xyz)} points"
                )

    def __len__(self) -> int:
        return len(self.xyz)

    def select(self, index: np.ndarray) -> PointCloud:
        return PointCloud(self.xyz[index], {k: v[index] for k, v in self.attrs.items()}, self.crs)


@dataclass(frozen=True)
class HeaderInfo:
    """What a file's header says. `box`: (mins, maxs), or a function giving them (E57 / PLY without
    trusted bounds: one streamed pass), called on the first use of `mins` / `maxs` only."""

    path: Path
    point_count: int
    point_format: int
    version: str
    box: tuple[np.ndarray, np.ndarray] | Callable[[], tuple[np.ndarray, np.ndarray]]
    crs: CRS | None
    dimensions: tuple[str, ...]

    @cached_property
    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self.box() if callable(self.box) else self.box
        return np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)

    @property
    def mins(self) -> np.ndarray:
        return self._bounds[0]

    @property
    def maxs(self) -> np.ndarray:
        return self._bounds[1]
