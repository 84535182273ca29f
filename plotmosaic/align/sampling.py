"""Seeded subsets that keep the input order (cube-ordered points stay spatially coherent)."""

from __future__ import annotations

import numpy as np


def sample(n: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted indices of a seeded random subset of range(n) of at most `size` (all when n <= size)."""
    return np.arange(n) if n <= size else np.sort(rng.choice(n, size, replace=False))
