"""Levelling: find a cloud's vertical from its normals and rotate it upright.

Forests give two strong cues. Ground and other near-horizontal surfaces put their normals
near the vertical; stems put theirs in the horizontal plane. The first cue alone is biased on
slopes (the terrain normal is not the vertical), so when there are enough stem-like normals the
estimate is refined as the direction most perpendicular to them.
"""

from __future__ import annotations

import numpy as np


def fibonacci_hemisphere(n: int) -> np.ndarray:
    """Unit vectors spread evenly over the upper hemisphere (z >= 0)."""
    i = np.arange(n) + 0.5
    z = 1.0 - i / n  # uniform in z over (0, 1]
    r = np.sqrt(1.0 - z**2)
    phi = np.pi * (1.0 + 5**0.5) * i
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit vector a onto unit vector b."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-12:
        if c > 0:
            return np.eye(3)
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def estimate_up(normals: np.ndarray, max_tilt_deg: float = 75.0, n_candidates: int = 1000) -> tuple[np.ndarray, dict]:
    """The cloud's up direction (unit vector, z-component positive) and the figures behind it.

    Up is taken on the side of the file's +z: a scan is never mounted upside down, and the
    search allows tilts up to `max_tilt_deg`.
    """
    n = np.asarray(normals, dtype=np.float64)
    cands = fibonacci_hemisphere(n_candidates)
    cands = cands[cands[:, 2] >= np.cos(np.radians(max_tilt_deg))]
    dots = np.abs(n @ cands.T)  # axial normals: n and -n are the same plane
    flat = (dots > np.cos(np.radians(15))).mean(axis=0)
    upright = (dots < np.sin(np.radians(8))).mean(axis=0)
    up = cands[np.argmax(flat + 0.5 * upright)]

    # refine on stems (perpendicular to up) when there are enough of them, else on the ground cluster
    stem_share = 0.0
    for band in (20.0, 12.0, 8.0):
        d = np.abs(n @ up)
        stems = n[d < np.sin(np.radians(band))]
        stem_share = len(stems) / max(len(n), 1)
        if stem_share > 0.04 and len(stems) > 200:
            w, v = np.linalg.eigh(stems.T @ stems)
            cand = v[:, 0]
        else:
            ground = n[d > np.cos(np.radians(band))]
            if len(ground) < 50:
                break
            w, v = np.linalg.eigh(ground.T @ ground)
            cand = v[:, -1]
        cand = cand if cand[2] >= 0 else -cand
        if np.degrees(np.arccos(np.clip(cand @ up, -1, 1))) < 2 * band:
            up = cand / np.linalg.norm(cand)
    return up, {"tilt_deg": float(np.degrees(np.arccos(np.clip(up[2], -1, 1)))), "stem_share": float(stem_share)}


def levelling_rotation(normals: np.ndarray, **kwargs) -> tuple[np.ndarray, dict]:
    """Rotation R with R @ up = +z, plus the estimate's figures."""
    up, info = estimate_up(normals, **kwargs)
    return rotation_between(up, np.array([0.0, 0.0, 1.0])), info
