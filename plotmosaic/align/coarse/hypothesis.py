"""What the coarse stage hands from step to step: a generator's start, and a verified hypothesis
(its row in CoarseResult.hypotheses, as dict only at the JSON boundary).

Every transform here maps source-local to target-local coordinates (see PreparedCloud.frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, kw_only=True, eq=False)
class Start:
    """A generator's pose and where it came from."""

    T: np.ndarray  # 4x4
    generator: str  # one of verify.GENERATORS
    vertical: str  # "source/target" vertical hypothesis names it was found under
    yaw: float | None = None  # heading (rad) of a raster, slice or stem match
    score: float | None = None  # raster correlation score
    slice_score: float | None = None  # slice correlation score
    overlap: float | None = None  # raster or slice overlap share
    votes: int | None = None  # FPFH or stem matches behind it
    prior: bool = False  # the prior itself: never merged into another start
    agree: tuple[str, ...] = ()  # "generator:vertical" of the near-duplicate starts merged into it

    @property
    def key(self) -> tuple[bytes, str, str]:
        """The start as verification keeps its results (unchanged when other starts agree with it)."""
        return np.asarray(self.T).tobytes(), self.generator, self.vertical

    def label(self) -> str:
        return f"{self.generator}:{self.vertical}"


@dataclass(frozen=True, kw_only=True, eq=False)
class Hypothesis:
    """A verified start: screened by a short ICP and, when chosen, refined."""

    T: np.ndarray  # 4x4, the screened or refined pose
    refined: bool
    score: (
        float | None
    )  # share of non-flat points with a partner after refining (None: not refined)
    screen_score: float
    raster_score: float | None  # the raster correlation score (None for other generators)
    yaw_deg: float
    overlap: float | None
    prior: bool
    generator: str
    vertical: str
    votes: int | None = None
    agree: tuple[str, ...] = ()
    slice_score: float | None = None
    through: bool = False  # ruled out: puts points where a scanner saw through (align/freespace.py)
    seen_through: float | None = None  # the share it puts there (None: no scanner known)

    @classmethod
    def verified(
        cls,
        start: Start,
        T: np.ndarray,
        screen_score: float,
        score: float | None,
        through: bool = False,
        seen_through: float | None = None,
    ) -> Hypothesis:
        """`start` at pose T after verification (`score` None: screened only)."""
        yaw = start.yaw if start.yaw is not None else np.arctan2(T[1, 0], T[0, 0])
        return cls(
            T=T,
            refined=score is not None,
            score=score,
            screen_score=screen_score,
            raster_score=start.score,
            yaw_deg=float(np.degrees(yaw)),
            overlap=start.overlap,
            prior=start.prior,
            generator=start.generator,
            vertical=start.vertical,
            votes=start.votes,
            agree=start.agree,
            slice_score=start.slice_score,
            through=through,
            seen_through=seen_through,
        )

    @classmethod
    def none(cls) -> Hypothesis:
        """The row of a search that found nothing: the identity."""
        return cls(
            T=np.eye(4),
            refined=True,
            score=0.0,
            screen_score=0.0,
            raster_score=0.0,
            yaw_deg=0.0,
            overlap=0.0,
            prior=False,
            generator="none",
            vertical="none",
        )

    def to_dict(self) -> dict:
        """Its row in RESULT.json (coarse.hypotheses)."""
        out = {
            "refined": self.refined,
            "score": self.score,
            "screen_score": self.screen_score,
            "raster_score": self.raster_score,  # None for other generators (strict JSON: no NaN)
            "yaw_deg": self.yaw_deg,
            "overlap": self.overlap,
            "prior": self.prior,
            "generator": self.generator,
            "vertical": self.vertical,
        }
        if self.votes is not None:
            out["votes"] = self.votes
        if self.agree:
            out["agree"] = list(self.agree)
        if self.slice_score is not None:
            out["slice_score"] = self.slice_score
        if self.seen_through is not None:
            out["seen_through"] = self.seen_through
        return out | {"transform": np.asarray(self.T).tolist()}
