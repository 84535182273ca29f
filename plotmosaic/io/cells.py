"""Cubic cells named by one int64: three signed cell indices packed, in x, y, z lexicographic order."""

from __future__ import annotations

import numpy as np

BITS = 21  # per axis: 2M cells a side (105 km at 5 cm)
HALF = 1 << (BITS - 1)


def fits(lowest: int, highest: int) -> bool:
    """Whether signed cell indices from `lowest` to `highest` (any axis) can be packed."""
    return lowest >= -HALF and highest < HALF


def pack(ijk: np.ndarray) -> np.ndarray:
    """One int64 key per row of signed (i, j, k) cell indices (each within `fits`)."""
    idx = ijk + HALF
    return (idx[:, 0] << (2 * BITS)) | (idx[:, 1] << BITS) | idx[:, 2]
