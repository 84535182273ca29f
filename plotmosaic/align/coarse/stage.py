"""The coarse stage's order of work: level both clouds, generate starts under the first vertical
pair, verify; the other vertical pairs and the slice search only when that pose has not settled."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from plotmosaic.align.coarse import verify as verification
from plotmosaic.align.coarse.clouds import AIRBORNE, Levels, remembered, vertical_pairs
from plotmosaic.align.coarse.fpfh import fpfh_matches, fpfh_starts
from plotmosaic.align.coarse.hypothesis import Hypothesis, Start
from plotmosaic.align.coarse.raster import pyramid, raster_starts, weights
from plotmosaic.align.coarse.slices import slice_starts
from plotmosaic.align.coarse.stems import stem_starts
from plotmosaic.align.coarse.verify import GENERATORS, Verifier, unique_starts
from plotmosaic.align.freespace import FreeSpace
from plotmosaic.align.memo import PairMemo
from plotmosaic.config.coarse import CoarseConfig
from plotmosaic.parallel import both


@dataclass(frozen=True, kw_only=True, eq=False)
class CoarseResult:
    """The coarse stage's pose, its confidence, and every verified hypothesis, best first."""

    transform: np.ndarray  # 4x4, source local frame -> target local frame
    confidence: float
    hypotheses: tuple[Hypothesis, ...] = ()
    seconds: float = 0.0
    levelling: dict = field(default_factory=dict)
    timing: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "transform": np.asarray(self.transform).tolist(),
            "confidence": self.confidence,
            "seconds": self.seconds,
            "levelling": self.levelling,
            "timing": self.timing,
            "hypotheses": [h.to_dict() for h in self.hypotheses],
        }


def _clock(timing: dict, name: str, t: float) -> None:
    timing[name] = timing.get(name, 0.0) + time.perf_counter() - t


class _Generators:
    """The generators under some vertical pairs, each timed into `timing` and drawing from its own
    random stream (so the order they run in changes none of them); the FPFH matches (which need no
    vertical) computed once."""

    def __init__(
        self,
        src: Levels,
        tgt: Levels,
        weights: dict[str, float],
        pyramid: int,
        config: CoarseConfig,
        prior: np.ndarray | None,
        seed: int,
        timing: dict,
    ) -> None:
        self.src, self.tgt, self.weights, self.pyramid = src, tgt, weights, pyramid
        self.config = config
        self.prior, self.timing = prior, timing
        self.fpfh_rng = np.random.default_rng([seed, 1])
        self.stems_rng = np.random.default_rng([seed, 2])
        self.matches = None
        self.cell: float | None = None  # the raster cell of the first vertical pair

    def raster(self, first: int, chosen) -> list[Start]:
        t = time.perf_counter()
        out, cell = raster_starts(
            self.src, self.tgt, chosen, self.weights, self.config, self.prior, first, self.pyramid
        )
        self.cell = cell if self.cell is None else self.cell
        _clock(self.timing, "search", t)
        return out

    def fpfh(self, first: int, chosen) -> list[Start]:
        config = self.config
        if not config.fpfh:
            return []
        t = time.perf_counter()
        if self.matches is None:
            self.matches = fpfh_matches(self.src, self.tgt, config)
        own = chosen[: max(0, config.fpfh_vertical_pairs - first)]
        out = fpfh_starts(self.matches, own, config, self.fpfh_rng, six_dof=first == 0)
        _clock(self.timing, "fpfh", t)
        return out

    def stems(self, chosen) -> list[Start]:
        if not self.config.stems:
            return []
        t = time.perf_counter()
        out = stem_starts(self.src, self.tgt, chosen, self.config, self.stems_rng)
        _clock(self.timing, "stems", t)
        return out

    def __call__(self, first: int, chosen) -> list[Start]:
        """Every generator's starts under the vertical pairs `chosen`, the first of which is pair `first`."""
        return self.raster(first, chosen) + self.fpfh(first, chosen) + self.stems(chosen)


def coarse_align(
    source,
    target,
    config: CoarseConfig | None = None,
    seed: int = 0,
    prior: np.ndarray | None = None,
    memo: PairMemo | None = None,
    space: FreeSpace | None = None,
) -> CoarseResult:
    """Global alignment of two prepared clouds (anything with local `points` and a `kind`).

    Hypotheses come from three generators (forest rasters, FPFH matches, stem maps) under every
    vertical hypothesis, and all go through one verification. `prior` (source local -> target
    local, e.g. from --init): the raster search looks around it instead of everywhere, and the prior
    itself is verified beside the hypotheses found, so a start that is already right stays.

    The first vertical pair is searched and verified first; the other pairs only when its best pose
    is not already settled (`verify.settled`): clearly ahead of its distinct rivals, fitting well and
    found by two generators independently. Its rivals stay in the hypotheses for the judge.
    `memo`: the pair's, where each cloud's sample and its levelled forms are kept. `space`: the
    pair's free space, where a scanner is known (verify.py ranks by it).
    """
    config = config or CoarseConfig()
    memo = memo or PairMemo()
    start = time.perf_counter()
    rng = np.random.default_rng(seed)
    src, tgt = _coarse_clouds(source, target, config, seed, memo)
    pairs = vertical_pairs(src.cloud, tgt.cloud, config)
    timing = {"levelling": time.perf_counter() - start}
    prior = None if prior is None else np.asarray(prior, dtype=float)
    airborne = source.kind in AIRBORNE or target.kind in AIRBORNE
    verify = Verifier(src.cloud, tgt, airborne, config, rng, space)
    kinds = source.kind, target.kind
    generate = _Generators(
        src, tgt, weights(*kinds, config), pyramid(*kinds, config), config, prior, seed, timing
    )
    first = pairs[:1]
    raster, stems = generate.raster(0, first), generate.stems(first)
    # the prior is never merged away
    own = [] if prior is None else [Start(T=prior, generator="prior", vertical="prior", prior=True)]
    early = config.settle_early and len(pairs) > 1
    # the cheap generators first: FPFH's descriptors cost as much as the raster search, and where
    # the raster and the stem map already agree on a clear pose they add nothing
    found = (
        _settle(verify, unique_starts(raster + stems + own, config), config, timing)
        if early
        else None
    )
    if found is None:
        fpfh = generate.fpfh(0, first)
        starts = unique_starts(raster + fpfh + stems + own, config)
        found = _settle(verify, starts, config, timing) if early and fpfh else None
    settled = found is not None
    if not settled:
        starts = _more_starts(generate, pairs, starts)
        t = time.perf_counter()
        found = verify(starts)
        _clock(timing, "verify", t)
    results, confidence = found
    searched = pairs if len(pairs) == 1 or not settled else pairs[:1]
    return CoarseResult(
        transform=results[0].T,
        confidence=confidence,
        hypotheses=tuple(results),
        seconds=time.perf_counter() - start,
        levelling={
            "source": src.cloud.info,
            "target": tgt.cloud.info,
            "raster_cell": generate.cell,
            "vertical_pairs": [f"{a.name}/{b.name}" for a, b in searched],
            "vertical_pairs_skipped": len(pairs) - len(searched),
            "hypotheses_by_generator": {
                g: sum(r.generator == g for r in results) for g in GENERATORS
            },
        },
        timing=timing,
    )


def _coarse_clouds(
    source, target, config: CoarseConfig, seed: int, memo: PairMemo
) -> tuple[Levels, Levels]:
    """Both clouds as the coarse stage sees them, with their levelled forms; the target seeded
    `seed + 1`. An airborne target (ALS/ULS) is georeferenced: its z is the vertical, while its
    ground normals show the terrain's slope and few stems correct them
    (docs/method.md#coarse-stage-settings). The source may come in any orientation: several
    vertical hypotheses (z-up first when it is airborne), each searched."""
    return both(
        lambda job: remembered(*job),
        (source, config, seed, source.kind in AIRBORNE, False, config.max_verticals, memo.source),
        (
            target,
            config,
            seed + 1,
            target.kind in AIRBORNE,
            target.kind in AIRBORNE,
            config.max_target_verticals,
            memo.target,
        ),
    )


def _settle(verify: Verifier, starts: list[Start], config: CoarseConfig, timing: dict):
    """(hypotheses, confidence) when the first vertical pair's starts settle the pose, else None.
    Refined only when two generators' screened poses already agree: otherwise it cannot settle."""
    t = time.perf_counter()
    try:
        if not verify.agreed(starts):
            return None
        results, confidence = verify(starts)
        return (results, confidence) if verification.settled(results, confidence, config) else None
    finally:
        _clock(timing, "verify", t)


def _more_starts(generate: _Generators, pairs, starts: list[Start]) -> list[Start]:
    """The starts with those of the other vertical pairs and of the slice search (only now: a
    settled pair needs no finer search)."""
    config = generate.config
    if len(pairs) > 1:
        starts = unique_starts(starts + generate(1, pairs[1:]), config)
    if config.slices:
        t = time.perf_counter()
        more = slice_starts(
            generate.src, generate.tgt, pairs[: config.slice_vertical_pairs], config
        )
        starts = unique_starts(starts + more, config)
        _clock(generate.timing, "slices", t)
    return starts
