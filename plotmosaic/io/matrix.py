"""A 4x4 transform as text: four rows of four numbers, the form CloudCompare and PDAL read."""

from __future__ import annotations

import numpy as np


def matrix_text(T: np.ndarray) -> str:
    """Four lines of four numbers, each float64 in its shortest exact decimal form, so a
    georeferenced translation keeps every digit."""
    return "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in np.asarray(T))
