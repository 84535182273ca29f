"""A pair's registration result: the pose in file coordinates, its quality figures and
information, and its JSON form (written by `plotmosaic align`, read by `report` and register-plot;
its fields: docs/formats.md#aligns-result)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plotmosaic import __version__
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.frame import rotation_deg

METHOD = "forestalign"


def motion_at(T: np.ndarray, point) -> list[float]:
    """Where `T` moves `point` minus where it was: [dx, dy, dz]."""
    T, p = np.asarray(T, dtype=float), np.asarray(point, dtype=float)
    return [float(v) for v in T[:3, :3] @ p + T[:3, 3] - p]


@dataclass(frozen=True)
class PairResult:
    transform: np.ndarray  # 4x4, source file coordinates -> target file coordinates
    fitness: float
    inlier_rmse: float
    overlap: float
    information: np.ndarray  # 6x6, xi = (wx, wy, wz, vx, vy, vz) on the right of `transform`
    levels: dict  # {"source": [...], "target": [...], "matching": {s: t}, "steps": [...]}
    seconds: float
    source_kind: str = "tls"
    target_kind: str = "tls"
    source_offset: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    target_offset: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    sigma: float = float("nan")  # point-to-plane residual std behind `information`
    coarse: dict | None = None
    confidence: float | None = None  # the judge's: margin over the best distinct rival pose, 0-1
    judge: dict | None = None  # the judge's profile figures of this pose and of its best rival
    timings: dict = field(default_factory=dict)  # seconds per step only
    steps: dict = field(default_factory=dict)  # what the steps did, in their units (not seconds)
    # the centre of the source's bounding box (stray points dropped), source file coordinates
    source_centre: list | None = None
    detected_kinds: dict = field(default_factory=dict)  # "source"/"target": kind, reason, evidence
    config: dict = field(default_factory=dict)
    method: str = METHOD
    version: str = __version__
    source_path: str | None = (
        None  # the two files, when registered from files (`plotmosaic report RESULT.json`)
    )
    target_path: str | None = None
    # the target's share near the source (`fitness` the other way); None in results made before it
    fitness_reverse: float | None = None

    @property
    def rotation_deg(self) -> float:
        return rotation_deg(self.transform)

    @property
    def motion_at_centre_m(self) -> list[float] | None:
        """[dx, dy, dz] the source's bounding-box centre moves (source -> target)."""
        return None if self.source_centre is None else motion_at(self.transform, self.source_centre)

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "version": self.version,
            "rotation_deg": self.rotation_deg,
            "motion_at_centre_m": self.motion_at_centre_m,
            "source_centre": self.source_centre,
            "transform": np.asarray(self.transform, dtype=float).tolist(),
            "fitness": self.fitness,
            "fitness_reverse": self.fitness_reverse,
            "inlier_rmse": self.inlier_rmse,
            "overlap": self.overlap,
            "information": np.asarray(self.information, dtype=float).tolist(),
            "sigma": self.sigma,
            "levels": self.levels,
            "seconds": self.seconds,
            "timings": self.timings,
            "steps": self.steps,
            "source_kind": self.source_kind,
            "target_kind": self.target_kind,
            "detected_kinds": self.detected_kinds,
            "source_offset": list(self.source_offset),
            "target_offset": list(self.target_offset),
            "confidence": self.confidence,
            "judge": self.judge,
            "coarse": self.coarse,
            "config": self.config,
            "source_path": self.source_path,
            "target_path": self.target_path,
        }

    @classmethod
    def from_dict(cls, d: dict) -> PairResult:
        return cls(
            transform=np.asarray(d["transform"], dtype=float),
            fitness=float(d["fitness"]),
            fitness_reverse=d.get("fitness_reverse"),
            inlier_rmse=float(d["inlier_rmse"]),
            overlap=float(d["overlap"]),
            information=np.asarray(d["information"], dtype=float),
            levels=d.get("levels", {}),
            seconds=float(d.get("seconds", 0.0)),
            source_kind=d.get("source_kind", "tls"),
            target_kind=d.get("target_kind", "tls"),
            source_offset=d.get("source_offset", [0.0, 0.0, 0.0]),
            target_offset=d.get("target_offset", [0.0, 0.0, 0.0]),
            sigma=float(
                d.get("sigma", float("nan")) if d.get("sigma") is not None else float("nan")
            ),
            coarse=d.get("coarse"),
            confidence=d.get("confidence"),
            judge=d.get("judge"),  # absent from results cached before the judge
            timings=d.get("timings", {}),
            steps=d.get("steps", {}),
            source_centre=d.get("source_centre"),
            detected_kinds=d.get("detected_kinds", {}),
            config=d.get("config", {}),
            method=d.get("method", METHOD),
            version=d.get("version", __version__),
            source_path=d.get("source_path"),
            target_path=d.get("target_path"),
        )

    def save(self, path: str | Path) -> Path:
        return write_text_atomic(path, json.dumps(self.to_dict(), indent=1))

    @classmethod
    def load(cls, path: str | Path) -> PairResult:
        return cls.from_dict(json.loads(Path(path).read_text()))
