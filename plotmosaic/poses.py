"""poses.json: per-scan 4x4 transforms from each scan's own file coordinates into a common frame.

Written by `simulate` (ground truth), `register-plot` (plot frame) and `tie-to-als` (ALS CRS);
read by `merge`, `report` and the benchmarks. One format for all of them:

    {"frame": "plot" | "crs", "crs": "<WKT>" | null,
     "scans": {"<scan id>": {"plot": "P1", "transform": [[4x4]], "sigma": [rx, ry, rz, tx, ty, tz] | null}}}

`sigma` is the 1-sigma uncertainty (radians, metres) where an optimiser produced one.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plotmosaic.errors import InputError
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.paths import check_input_file


@dataclass(frozen=True)
class ScanPose:
    transform: np.ndarray
    plot: str | None = None
    sigma: np.ndarray | None = None
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Poses:
    scans: dict[str, ScanPose]
    frame: str = "plot"
    crs: str | None = None
    extra: dict = field(default_factory=dict)

    def transform(self, scan_id: str) -> np.ndarray:
        if scan_id not in self.scans:
            raise InputError(f"no pose for scan {scan_id!r}")
        return self.scans[scan_id].transform

    def to_dict(self) -> dict:
        return {
            "frame": self.frame,
            "crs": self.crs,
            **self.extra,
            "scans": {
                sid: {
                    "plot": p.plot,
                    "transform": np.asarray(p.transform, dtype=float).tolist(),
                    "sigma": None if p.sigma is None else np.asarray(p.sigma, dtype=float).tolist(),
                    **p.extra,
                }
                for sid, p in self.scans.items()
            },
        }

    def save(self, path: str | Path) -> Path:
        return write_text_atomic(path, json.dumps(self.to_dict(), indent=1))


def read_json(path: str | Path, what: str = "JSON file"):
    """Parsed JSON of a file the user named; one-line errors for a missing or broken file."""
    path = Path(path)
    check_input_file(path, what)
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not valid JSON ({getattr(exc, 'msg', exc)})") from None


# |R R^T - I| and |det R - 1| allowed in a transform read from a file: JSON keeps 15-17 digits, so a
# rigid transform written by us is far inside it; a scaled, sheared or hand-rounded matrix is not.
RIGID_TOLERANCE = 1e-5


def rigid_problem(T: np.ndarray) -> str | None:
    """Why a 4x4 array is not a finite rigid transform (None if it is one)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        return f"must be a 4x4 matrix, got shape {list(T.shape)}"
    if not np.isfinite(T).all():
        return "has NaN or infinite values"
    if not np.allclose(T[3], [0, 0, 0, 1], atol=RIGID_TOLERANCE):
        return f"last row must be [0, 0, 0, 1], got {T[3].tolist()}"
    R = T[:3, :3]
    det = float(np.linalg.det(R))
    if det < 0:
        return f"is a reflection (determinant {det:+.4f}), not a rotation"
    if (
        not np.allclose(R @ R.T, np.eye(3), atol=RIGID_TOLERANCE)
        or abs(det - 1.0) > RIGID_TOLERANCE
    ):
        return (
            f"rotation part is not orthonormal within {RIGID_TOLERANCE:g} (determinant {det:.6f})"
        )
    return None


def rigid_matrix(value, where: str) -> np.ndarray:
    """A finite rigid 4x4 transform (det +1) from JSON data, or a one-line error naming `where`."""
    try:
        T = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{where}: 'transform' is not a 4x4 matrix of numbers") from None
    problem = rigid_problem(T)
    if problem:
        raise InputError(f"{where}: 'transform' {problem}")
    return T


def _sigma(value, where: str) -> np.ndarray | None:
    if value is None:
        return None
    try:
        sigma = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        sigma = None
    if sigma is None or sigma.shape != (6,) or np.isnan(sigma).any() or (sigma < 0).any():
        raise InputError(f"{where}: 'sigma' must be 6 non-negative numbers or null")
    return sigma


def load_poses(path: str | Path) -> Poses:
    path = Path(path)
    data = read_json(path, "poses file")
    if not isinstance(data, dict) or not isinstance(data.get("scans"), dict):
        raise InputError(f"{path}: missing the 'scans' object")
    scans = {}
    for sid, entry in data["scans"].items():
        where = f"{path}: scan {sid!r}"
        if not isinstance(entry, dict) or "transform" not in entry:
            raise InputError(f"{where}: missing field 'transform'")
        extra = {k: v for k, v in entry.items() if k not in ("transform", "plot", "sigma")}
        scans[sid] = ScanPose(
            rigid_matrix(entry["transform"], where),
            entry.get("plot"),
            _sigma(entry.get("sigma"), where),
            extra,
        )
    extra = {k: v for k, v in data.items() if k not in ("frame", "crs", "scans")}
    return Poses(scans, data.get("frame", "plot"), data.get("crs"), extra)
