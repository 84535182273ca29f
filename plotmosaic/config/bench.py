"""Settings of the benchmark harness: perturbation protocols and the baseline methods (a leaf)."""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class Protocol(BaseModel):
    """Half-widths of the uniform perturbation ranges (degrees, metres)."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field("paper", min_length=1, description="protocol name in tables")
    roll: float = Field(45.0, ge=0, le=180, description="+- roll (deg)")
    pitch: float = Field(45.0, ge=0, le=90, description="+- pitch (deg)")
    yaw: float = Field(45.0, ge=0, le=180, description="+- heading (deg)")
    tx: float = Field(15.0, ge=0, le=10_000, description="+- x shift (m)")
    ty: float = Field(15.0, ge=0, le=10_000, description="+- y shift (m)")
    tz: float = Field(15.0, ge=0, le=10_000, description="+- z shift (m)")

    @property
    def ranges(self) -> np.ndarray:
        return np.array([self.roll, self.pitch, self.yaw, self.tx, self.ty, self.tz])


PROTOCOLS = {
    # Section 4 of the paper: all six parameters at once, uniform +-45 deg / +-15 m
    "paper": Protocol(name="paper"),
    # beyond the paper: any heading, a tilted-tripod roll/pitch, larger offsets
    "beyond": Protocol(name="beyond", roll=10, pitch=10, yaw=180, tx=25, ty=25, tz=25),
}

# The real-data suite's protocols (benchmarks/bench_real.py). paper: as above; beyond: any heading,
# +-20 m (tilts as the paper); true: the source handed over in its true pose (the control)
SUITE_PROTOCOLS: dict[str, Protocol] = {
    "paper": PROTOCOLS["paper"],
    "beyond": Protocol(name="beyond", roll=45, pitch=45, yaw=180, tx=20, ty=20, tz=20),
    "true": Protocol(name="true", roll=0, pitch=0, yaw=0, tx=0, ty=0, tz=0),
}


class IcpConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    voxel: float = Field(0.15, gt=0, le=10, description="voxel thinning of both clouds (m)")
    # a wide first pass to pull in metre-scale offsets, then a tight one (the paper refines at 0.25 m)
    distances: tuple[float, ...] = Field(
        (1.0, 0.25), min_length=1, description="correspondence distance of each pass (m)"
    )
    iterations: int = Field(30, ge=1, le=1000, description="iterations of each pass")


class FpfhConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    voxel: float = Field(0.5, gt=0, le=10, description="forest scale: features over 2.5 m")
    max_points: int = Field(
        8000, ge=100, le=1_000_000, description="RANSAC scores on all points: a seeded subset"
    )
    max_nn_normal: int = Field(30, ge=3, le=1000, description="neighbours of a normal")
    max_nn_feature: int = Field(100, ge=3, le=1000, description="neighbours of a feature")
    ransac_iterations: int = Field(50_000, ge=1, le=10_000_000, description="RANSAC iterations")
    ransac_confidence: float = Field(0.999, gt=0, lt=1, description="RANSAC stop confidence")


class CpdConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    points: int = Field(2000, ge=10, le=100_000, description="CPD is O(N*M): subsample hard")
    voxel: float = Field(0.3, gt=0, le=10, description="voxel thinning before subsampling (m)")
    maxiter: int = Field(50, ge=1, le=10_000, description="EM iterations")
    w: float = Field(0.1, ge=0, lt=1, description="outlier weight: forests never overlap fully")
    tol: float = Field(1e-4, gt=0, le=1, description="EM stop tolerance")
    refine: bool = Field(
        True, description="then the ICP of fpfh-ransac (IcpConfig), as a global method is used"
    )


class MethodsConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    icp: IcpConfig = Field(default_factory=IcpConfig, description="ICP baseline")
    fpfh: FpfhConfig = Field(default_factory=FpfhConfig, description="FPFH + RANSAC baseline")
    cpd: CpdConfig = Field(default_factory=CpdConfig, description="CPD baseline")
    no_coarse: bool = Field(
        False, description="forestalign from identity (the paper's local setting)"
    )


class BenchConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    protocol: Protocol = Field(
        default_factory=lambda: PROTOCOLS["paper"], description="perturbation ranges"
    )
    trials: int = Field(10, ge=1, le=100_000, description="draws per pair")
    seed: int = Field(0, ge=0, description="seed of the draws")
    methods: list[str] = Field(
        ["forestalign", "icp", "fpfh-ransac", "cpd"], min_length=1, description="methods compared"
    )
    overlaps: list[float] | None = Field(
        None, description="overlap levels to crop to (percent, e.g. [28, 15, 5, 1]); None: as is"
    )
    success_rotation_deg: float = Field(1.0, gt=0, le=180, description="success: rotation within")
    success_translation_m: float = Field(0.10, gt=0, le=100, description="success: shift within")
    methods_config: MethodsConfig = Field(
        default_factory=MethodsConfig, description="the baselines' settings"
    )
