"""Verification of the coarse stage's starts: screen every start with a short ICP, refine the best
of each generator and the best overall with a quick robust ICP, and rank them by how many non-flat
points (stems, branches, crowns: flat ground matches anywhere) find a partner; the gap to the best
distinct runner-up is the confidence. Where a scanner is known, a pose that puts points where it saw
through (align/freespace.py) ranks after every pose that does not, and is no rival of a best pose
the free space clearly allows."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from plotmosaic.align.coarse.clouds import CoarseCloud, Levels
from plotmosaic.align.coarse.hypothesis import Hypothesis, Start
from plotmosaic.align.freespace import FreeSpace
from plotmosaic.align.icp import IcpOptions, MovingNearest, evaluate, point_to_plane_icp
from plotmosaic.align.sampling import sample
from plotmosaic.align.voxel import thin
from plotmosaic.config.align import IcpStage
from plotmosaic.config.coarse import CoarseConfig
from plotmosaic.io.frame import pose_error
from plotmosaic.parallel import in_two_threads

GENERATORS = ("raster", "fpfh", "stems", "slices", "prior")


def _refine(
    src_pts: np.ndarray,
    tgt: tuple,
    T0: np.ndarray,
    distances: tuple[float, ...],
    iterations: int,
    axis: np.ndarray | None = None,
) -> np.ndarray:
    """Quick robust point-to-plane ICP over shrinking correspondence distances (Tukey width = distance)."""
    points, normals, tree = tgt
    stages = tuple(IcpStage(max_distance=d, iterations=iterations) for d in distances)
    options = IcpOptions(stages=stages, kernel_floor=0.0, kernel_ratio=1.0, tol=1e-4, axis=axis)
    return point_to_plane_icp(src_pts, points, normals, T0, options, MovingNearest(tree)).T


def _score(structure: np.ndarray, tgt: tuple, T: np.ndarray, distance: float) -> float:
    """Share of non-flat source points with a target partner: flat ground matches anywhere, stems do not."""
    return evaluate(structure, tgt[2], T, distance)[0]


@dataclass(frozen=True, kw_only=True, eq=False)
class _Screened:
    """A start after its short ICP."""

    score: float
    T: np.ndarray
    start: Start
    through: bool = False  # ruled out by a scanner's free space at the screening margin


def radii(A: np.ndarray, B: np.ndarray, config: CoarseConfig) -> float:
    """How far apart two poses are, in distinct radii (the larger of rotation and displacement)."""
    degrees, metres = pose_error(A, B)
    return max(metres / config.distinct_m, degrees / config.distinct_deg)


def distinct(A: np.ndarray, B: np.ndarray, config: CoarseConfig) -> bool:
    return radii(A, B, config) > 1.0


def unique_starts(starts: list[Start], config: CoarseConfig) -> list[Start]:
    """Starts without near-duplicates (the first kept; the generators that agreed with it noted in `agree`)."""
    out: list[Start] = []
    for s in starts:
        for i, kept in enumerate(out):
            deg, m = pose_error(s.T, kept.T)
            if m < config.start_duplicate_m and deg < config.start_duplicate_deg and not s.prior:
                out[i] = replace(kept, agree=(*kept.agree, s.label()))
                break
        else:
            out.append(s)
    return out


def support(results: list[Hypothesis], best: Hypothesis, config: CoarseConfig) -> set[str]:
    """Generators whose own hypotheses reached `best`'s pose (screened or as a duplicate start)."""
    out = set()
    for r in results:
        if not distinct(best.T, r.T, config):
            out.add(r.generator)
            out.update(a.split(":")[0] for a in r.agree)
    return out - {"prior"}


def settled(results: list[Hypothesis], confidence: float, config: CoarseConfig) -> bool:
    """The first vertical pair's best pose needs no other: ahead of its rivals, fitting, found twice."""
    best = results[0]
    return (
        best.refined
        and confidence >= config.settled_confidence
        and (best.score or 0.0) >= config.settled_score
        and len(support(results, best, config)) >= config.settled_generators
    )


def _confidence(
    results: list[Hypothesis], config: CoarseConfig, clear_share: float | None = None
) -> float:
    """1 - the best distinct refined runner-up's score / the best's (0 when the best scores 0);
    a pose the free space rules out is no rival of a best it clearly allows (seen through at most
    `clear_share`)."""
    best = results[0]
    clear = clear_share is not None and best.seen_through is not None
    clear = clear and best.seen_through <= clear_share
    # only refined hypotheses compete: an unrefined one may be the best pose not yet converged
    runner_up = next(
        (
            r
            for r in results[1:]
            if r.refined and distinct(best.T, r.T, config) and not (clear and r.through)
        ),
        None,
    )
    second = runner_up.score if runner_up else 0.0
    return float(1.0 - second / best.score) if best.score > 0 else 0.0


class Verifier:
    """Screens starts (short ICP), refines the best distinct ones, and ranks them; each start and each
    refinement is computed once, so a second call with more starts only pays for the new ones."""

    def __init__(
        self,
        src: CoarseCloud,
        tgt: Levels,
        airborne: bool,
        config: CoarseConfig,
        rng,
        space: FreeSpace | None = None,
    ):
        self.config = config
        self.space = space
        d = config.verify_distance_airborne if airborne else config.verify_distance_ground
        self.d = d
        self.iterations = (
            config.verify_iterations_airborne if airborne else config.verify_iterations
        )
        # verification in the clouds' local frames (each hypothesis carries its own verticals); one kept
        # point (and its own normal: averaged axial normals cancel) per verify cube
        self.tgt_v = tgt.verify_sample(config)  # the target's memo: one per target cloud
        keep = thin(src.points, config.verify_voxel)
        keep = keep[sample(len(keep), config.verify_points, rng)]
        self.src_v = src.points[keep]
        # non-flat under the source's first vertical: one fixed set, so every hypothesis is scored on the same points
        up = src.verticals[0].up
        flat_ok = np.abs(src.normals[keep] @ up) < config.structure_normal_z
        self.structure = self.src_v[flat_ok]
        few = sample(len(self.src_v), config.screen_points, rng)
        self.src_few, self.structure_few = self.src_v[few], self.src_v[few][flat_ok[few]]
        # the target's non-flat points, for the source scanner's free space (its own draw: the
        # verification's samples are the same with or without a scanner)
        tgt_up = tgt.cloud.verticals[0].up
        self.tgt_structure = self.tgt_v[0][
            np.abs(self.tgt_v[1] @ tgt_up) < config.structure_normal_z
        ]
        few = sample(len(self.tgt_structure), config.screen_points, np.random.default_rng(0))
        self.tgt_few = self.tgt_structure[few]
        self.shares: dict[tuple[bytes, bool], float | None] = {}
        # a start's key -> (score, pose) screened, and -> (pose, score) refined
        self.screened: dict[tuple, tuple[float, np.ndarray]] = {}
        # ground-based pairs: a start's ICPs turn about its vertical while the matches are loose (thin
        # overlap, mostly ground, tilts a right start away); airborne ones must tilt a strip into place
        self.about_vertical = config.screen_about_vertical and not airborne
        self.ups = {v.name: np.asarray(v.up, dtype=float) for v in tgt.cloud.verticals}
        self.refined: dict[tuple, tuple[np.ndarray, float]] = {}
        self.refined_on: set[tuple] = set()  # refined poses refined on near a best (`_near_rivals`)

    def _axis(self, start: Start) -> np.ndarray | None:
        """The target's vertical the start was levelled under, where its ICPs turn about it (None:
        they turn freely)."""
        if not self.about_vertical or "/" not in start.vertical:
            return None  # a 6-DoF or prior start has no vertical of its own
        return self.ups.get(start.vertical.rpartition("/")[2])

    def _share(self, A: np.ndarray, screening: bool) -> float | None:
        """Pose A's seen-through share (align/freespace.py; None without a scanner)."""
        if self.space is None:
            return None
        key = (A.tobytes(), screening)
        if key not in self.shares:
            src, tgt = (
                (self.structure_few, self.tgt_few)
                if screening
                else (self.structure, self.tgt_structure)
            )
            self.shares[key] = self.space.share(src, tgt, A, screening)
        return self.shares[key]

    def _through(self, A: np.ndarray, screening: bool) -> bool:
        """Whether pose A is ruled out by a scanner's free space (never without one)."""
        return self.space is not None and self.space.beyond(self._share(A, screening), screening)

    def _screen(self, start: Start) -> tuple[float, np.ndarray]:
        c, d = self.config, self.d
        axis = self._axis(start)
        A = _refine(
            self.src_few,
            self.tgt_v,
            start.T,
            (c.screen_distance_factor * d,),
            self.iterations,
            axis,
        )
        return _score(self.structure_few, self.tgt_v, A, c.screen_score_factor * d), A

    def _refine(self, job: tuple[np.ndarray, np.ndarray | None]) -> tuple[np.ndarray, float]:
        """A screened pose refined: its wide stages turn about `axis` (when given), the last, tight
        stage freely, where the matches are right enough to decide the tilt."""
        A, axis = job
        c, d = self.config, self.d
        distances = tuple(f * d for f in c.refine_distance_factors)
        wide, tight = (distances[:-1], distances[-1:]) if axis is not None else ((), distances)
        if wide:
            A = _refine(self.src_v, self.tgt_v, A, wide, self.iterations, axis)
        A = _refine(self.src_v, self.tgt_v, A, tight, self.iterations)
        return A, _score(self.structure, self.tgt_v, A, d)

    def _screen_all(self, starts: list[Start]) -> list[_Screened]:
        """Every start screened, best first (those the free space rules out after the rest)."""
        new = [s for s in starts if s.key not in self.screened]
        for s, r in zip(new, in_two_threads(self._screen, new)):
            self.screened[s.key] = r
        screened = []
        for s in starts:
            score, A = self.screened[s.key]
            through = self._through(A, screening=True)
            screened.append(_Screened(score=score, T=A, start=s, through=through))
        return sorted(screened, key=lambda r: (r.through, -r.score))

    def agreed(self, starts: list[Start]) -> bool:
        """Whether the best screened pose was reached by `settled_generators` generators."""
        screened = self._screen_all(starts)
        if not screened:
            return False
        rows = [Hypothesis.verified(r.start, r.T, r.score, None) for r in screened]
        return len(support(rows, rows[0], self.config)) >= self.config.settled_generators

    def _chosen(self, screened: list[_Screened]) -> list[int]:
        """Which screened poses to refine: the best of each generator first (so no generator's best
        is lost to another's near-duplicates), then by score; distinct ones only, so the runner-up
        is a real rival (screened poses have converged)."""
        config = self.config
        distinct_ones: list[int] = []
        for i, r in enumerate(screened):
            if all(distinct(r.T, screened[j].T, config) for j in distinct_ones):
                distinct_ones.append(i)
        chosen = [
            k
            for k in (
                next((i for i in distinct_ones if screened[i].start.generator == gen), None)
                for gen in GENERATORS
            )
            if k is not None and screened[k].score > 0
        ]
        rest = [i for i in distinct_ones if i not in chosen]
        return sorted(chosen + rest[: max(0, config.refine_top - len(chosen))])

    def _near_rivals(self, screened: list[_Screened], best: np.ndarray) -> bool:
        """Refined poses that end distinct from the `best` one but within `near_rival_radii` of it,
        refined on (at most `near_rival_passes` times, while each pass brings them closer, until
        within the distinct radius): a start of the best's own basin the quick refine left a few
        degrees short is no rival. Each pose is refined on once; whether any was."""
        c = self.config
        keys = [
            r.start.key
            for r in screened
            if r.start.key in self.refined
            and r.start.key not in self.refined_on
            and 1.0 < radii(self.refined[r.start.key][0], best, c) <= c.near_rival_radii
        ]

        def refine_on(key: tuple) -> tuple[np.ndarray, float]:
            A, score = self.refined[key]
            gap = radii(A, best, c)
            for _ in range(c.near_rival_passes):
                B, s = self._refine((A, None))  # near: the matches decide the tilt too
                nearer = radii(B, best, c)
                if nearer >= gap:
                    break  # settled apart: a rival
                A, score, gap = B, s, nearer
                if gap <= 1.0:
                    break
            return A, score

        for key, r in zip(keys, in_two_threads(refine_on, keys)):
            self.refined[key] = r
        self.refined_on.update(keys)
        return bool(keys)

    def _ranked(self, screened: list[_Screened]) -> list[Hypothesis]:
        """Every screened start as a hypothesis, the refined ones first, best first."""
        results = []
        for r in screened:
            # every refined pose competes, also one refined before more starts came (more rivals)
            A, score = self.refined.get(r.start.key, (r.T, None))
            share = self._share(A, screening=score is None)
            through = self._through(A, screening=score is None)
            results.append(Hypothesis.verified(r.start, A, r.score, score, through, share))
        if not results:
            results.append(Hypothesis.none())
        results.sort(
            key=lambda h: (not h.refined, h.through, -(h.score if h.refined else h.screen_score))
        )
        return results

    def __call__(self, starts: list[Start]) -> tuple[list[Hypothesis], float]:
        screened = self._screen_all(starts)
        # independent ICPs, two at a time (KD-tree queries release the GIL)
        todo = [i for i in self._chosen(screened) if screened[i].start.key not in self.refined]
        jobs = [(screened[i].T, self._axis(screened[i].start)) for i in todo]
        for i, r in zip(todo, in_two_threads(self._refine, jobs)):
            self.refined[screened[i].start.key] = r
        results = self._ranked(screened)
        if results[0].refined and self._near_rivals(screened, results[0].T):
            results = self._ranked(screened)
        clear = None if self.space is None else self.space.config.pose_max_share
        return results, _confidence(results, self.config, clear)
