"""Local frames: a recorded offset so UTM-sized coordinates are processed near the origin.

A transform estimated between two local frames is converted back into the files' own
coordinates with `to_global_transform`, so every figure the tool reports is in file coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# rows whose columns are reduced while they sit in cache (32k rows of float64 xyz: 768 kB)
BOUNDS_BLOCK = 1 << 15


def column_bounds(xyz: np.ndarray) -> np.ndarray:
    """(3, 2): each column's (min, max). Column by column (axis-0 reductions over (N, 3) are slower),
    block by block: a block's three columns share its cache lines, so a large cloud is read from
    memory once instead of six times. Exact: min and max do not depend on the order."""
    n = len(xyz)
    if n <= BOUNDS_BLOCK:
        return np.array([[xyz[:, i].min(), xyz[:, i].max()] for i in range(3)], dtype=np.float64)
    blocks = [
        [(xyz[s : s + BOUNDS_BLOCK, i].min(), xyz[s : s + BOUNDS_BLOCK, i].max()) for i in range(3)]
        for s in range(0, n, BOUNDS_BLOCK)
    ]
    per = np.asarray(blocks, dtype=np.float64)  # (blocks, 3, 2)
    return np.column_stack([per[:, :, 0].min(axis=0), per[:, :, 1].max(axis=0)])


def translation(t) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


@dataclass(frozen=True)
class Frame:
    """Local coordinates = file coordinates - offset (all float64)."""

    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @classmethod
    def around(cls, xyz: np.ndarray, step: float = 1.0) -> Frame:
        """A frame centred on the cloud's bounding box, offset rounded to `step` metres."""
        xyz = np.asarray(xyz, dtype=np.float64)
        if len(xyz) == 0:
            return cls(np.zeros(3))
        # column by column: axis-0 reductions over (N, 3) are several times slower on large clouds
        return cls.of_bounds(column_bounds(xyz), step)

    @classmethod
    def of_bounds(cls, bounds: np.ndarray, step: float = 1.0) -> Frame:
        """`around` a cloud whose columns' (min, max) are the rows of `bounds` (3, 2)."""
        centre = np.array([(lo + hi) / 2.0 for lo, hi in np.asarray(bounds, dtype=np.float64)])
        return cls(np.round(centre / step) * step)

    def to_local(self, xyz: np.ndarray) -> np.ndarray:
        return np.asarray(xyz, dtype=np.float64) - self.offset

    def to_global(self, xyz: np.ndarray) -> np.ndarray:
        return np.asarray(xyz, dtype=np.float64) + self.offset


def to_global_transform(T_local: np.ndarray, source: Frame, target: Frame) -> np.ndarray:
    """Transform mapping source file coordinates to target file coordinates."""
    return (
        translation(target.offset)
        @ np.asarray(T_local, dtype=np.float64)
        @ translation(-source.offset)
    )


def to_local_transform(T_global: np.ndarray, source: Frame, target: Frame) -> np.ndarray:
    """Inverse of `to_global_transform`: a file-coordinate transform expressed between local frames."""
    return (
        translation(-target.offset)
        @ np.asarray(T_global, dtype=np.float64)
        @ translation(source.offset)
    )


def apply_transform(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    xyz = np.asarray(xyz, dtype=np.float64)
    # einsum, not `xyz @ R.T`: the BLAS path for (N,3)x(3,3) is many times slower here
    return np.einsum("ij,...j->...i", T[:3, :3], xyz) + T[:3, 3]


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (exact, no general matrix inverse)."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def rotation_deg(T: np.ndarray) -> float:
    """Angle (degrees) of the rotation part of T."""
    c = (np.trace(T[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation deg, translation m) between two poses."""
    return rotation_deg(inverse(T_true) @ T_est), float(
        np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])
    )
