"""Global coarse alignment (work in progress by the lead; interface fixed)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel


class CoarseConfig(BaseModel):
    enabled: bool = True


@dataclass
class CoarseResult:
    transform: np.ndarray  # 4x4, source local frame -> target local frame
    confidence: float
    hypotheses: list[dict] = field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        return {"confidence": self.confidence, "hypotheses": self.hypotheses, "seconds": self.seconds}


def coarse_align(source, target, config: CoarseConfig, seed: int = 0) -> CoarseResult:
    raise NotImplementedError("coarse alignment lands with its issue")
