"""The space a scanner saw through (align/freespace.py): a pose that puts points there is ruled out,
whatever its matches; the thin real pair whose wrong rivals outscore the truth until they are."""

import numpy as np
import pytest

from plotmosaic.align.floors import check_quality
from plotmosaic.align.freespace import FreeSpace, scanner, seen_through
from plotmosaic.align.pair import register_prepared
from plotmosaic.align.prepare import prepare_cloud
from plotmosaic.align.result import PairResult
from plotmosaic.bench.overlap_pairs import PairRef, candidate, cut_candidate, save_pair
from plotmosaic.bench.overlap_suite import Job, run_trial
from plotmosaic.bench.protocol import params_to_matrix
from plotmosaic.bench.real_suite import draw
from plotmosaic.config.align import AlignConfig, default_levels
from plotmosaic.config.freespace import FreeSpaceConfig
from plotmosaic.errors import RegistrationFailed
from plotmosaic.io.frame import apply_transform, pose_error
from plotmosaic.io.las import PointCloud


def _wall(x: float, n: int = 2000, seed: int = 0) -> np.ndarray:
    """A wall across +x at distance `x`, 10 m wide and 4 m high."""
    rng = np.random.default_rng(seed)
    return np.column_stack([np.full(n, x), rng.uniform(-5, 5, n), rng.uniform(-2, 2, n)])


def test_points_in_front_of_what_the_scanner_hit_are_seen_through_behind_it_are_not():
    config = FreeSpaceConfig()
    s = scanner(_wall(10.0), np.zeros(3), config)
    eye = np.eye(4)
    # the same wall lies on what was hit, a wall behind it is hidden: nothing seen through
    assert seen_through(_wall(10.0, seed=1), np.zeros((0, 3)), eye, None, s, 0.4, config) == 0.0
    assert seen_through(_wall(14.0, seed=1), np.zeros((0, 3)), eye, None, s, 0.4, config) == 0.0
    # in the space the beams crossed on their way to the wall: all of it
    assert seen_through(_wall(6.0, seed=1), np.zeros((0, 3)), eye, None, s, 0.4, config) == 1.0
    # within the margin of the wall: not yet
    assert seen_through(_wall(9.8, seed=1), np.zeros((0, 3)), eye, None, s, 0.4, config) == 0.0
    # where the scanner had no return (behind it): it could not see them, so no figure
    assert seen_through(_wall(-6.0, seed=1), np.zeros((0, 3)), eye, None, s, 0.4, config) is None


def test_both_scanners_speak_and_a_pose_moves_the_points_into_the_other_frame():
    config = FreeSpaceConfig()
    tgt = scanner(_wall(10.0), np.zeros(3), config)
    src = scanner(_wall(10.0), np.zeros(3), config)
    T = np.eye(4)
    T[0, 3] = -4.0  # the source's wall lands 6 m from the target scanner: seen through
    a, b = _wall(10.0, seed=2), _wall(10.0, seed=3)
    # what the target scanner could see of the source's wall is all seen through
    assert seen_through(a, b, T, None, tgt, 0.4, config) == 1.0
    # the target's wall, in source coordinates, lies 14 m out: behind the source's, hidden
    assert seen_through(a, b, T, src, None, 0.4, config) == 0.0
    # both: the share of everything either could see (the part of the source's wall inside the
    # target's view, about 0.6 x 0.6 of it, against all of the target's wall)
    assert seen_through(a, b, T, src, tgt, 0.4, config) == pytest.approx(0.36 / 1.36, abs=0.02)
    space = FreeSpace(source=src, target=tgt, config=config)
    assert space.beyond(space.share(a, b, T))
    assert not space.beyond(space.share(a, b, np.eye(4)))


def _register(moved, scanner_at, target, config: AlignConfig):
    """As bench_overlap runs a trial: each scan's scanner known, as a TLS file records it."""
    levels = default_levels("tls")
    src = prepare_cloud(moved, "tls", levels, config, 3, "source", scanner=scanner_at)
    tgt = prepare_cloud(target, "tls", levels, config, 1, "target", scanner=np.zeros(3))
    return register_prepared(src, tgt, config, seed=3)


@pytest.mark.slow
def test_a_thin_real_pair_is_found_once_its_rivals_are_ruled_out_by_free_space(spanner_dir):
    """Two views of the MLS clip 11 m apart sharing 0.12 / 0.11 (bench_overlap's mls candidate 23),
    each in its own scanner frame as a TLS file is. Wrong poses overlap more of the two views than
    the right one and win the search and the judge's margin, so the pair is refused; they push
    stems into the gaps the other scanner looked through, and ruled out they leave the truth."""
    pair = cut_candidate(candidate("mls", 0, 23), spanner_dir.parent)[0]
    assert max(pair.overlap_st, pair.overlap_ts) < 0.15
    # the bench's trial 3 of that bin: the source moved from anywhere (`paper`)
    aligned = apply_transform(pair.truth, pair.source)
    P = params_to_matrix(draw("paper", 0, "mls:0.10-0.15", 3), aligned.mean(axis=0))
    moved = PointCloud(apply_transform(P, aligned))
    scanner_at = apply_transform(P, pair.truth[:3, 3][None])[0]
    target = PointCloud(pair.target)
    result = _register(moved, scanner_at, target, AlignConfig())
    deg, m = pose_error(result.transform, np.linalg.inv(P))
    assert m < 0.05 and deg < 0.2, (m, deg)
    assert result.judge["seen_through"] < AlignConfig().free_space.max_share
    assert any("seen_through" in row for row in result.judge["rivals"])
    blind = AlignConfig().model_copy(update={"free_space": FreeSpaceConfig(enabled=False)})
    with pytest.raises(RegistrationFailed):
        _register(moved, scanner_at, target, blind)


def _result(fitness: float, reverse: float | None) -> PairResult:
    return PairResult(
        transform=np.eye(4),
        fitness=fitness,
        fitness_reverse=reverse,
        inlier_rmse=0.1,
        overlap=0.15,
        information=np.eye(6),
        levels={},
        seconds=1.0,
    )


def test_the_fitness_floor_holds_either_way():
    """A thin pair's smaller view shares less than a tenth of itself at the right pose (0.093 / 0.19
    on the MLS clip): the floor asks one of the two directions to clear it, not the source's."""
    config = AlignConfig()
    check_quality(_result(0.09, 0.19), config)  # the target's share clears it
    with pytest.raises(RegistrationFailed, match="fitness 0.090"):
        check_quality(_result(0.09, 0.05), config)
    with pytest.raises(RegistrationFailed, match="fitness 0.090"):
        check_quality(_result(0.09, None), config)  # a result made before the reverse share


@pytest.mark.slow
def test_a_blunt_pose_near_the_limit_gains_nothing_from_its_rivals_exclusion(spanner_dir, tmp_path):
    """MLS views sharing 0.06 / 0.06 (bench_overlap's mls candidate 5), paper draw 16: a pose far
    off, itself 0.087 of the way seen through at sharpness 0.030, lost its rivals (0.12-0.14) to the
    free space and passed as a clear winner. The free space speaks only for a sharp pose it clearly
    allows, so that pose keeps its rivals and the pair is refused."""
    pair = cut_candidate(candidate("mls", 0, 5), spanner_dir.parent)[0]
    path = save_pair(tmp_path / "pair.npz", pair)
    ref = PairRef("mls-c5-p0", str(path), pair.overlap_st, pair.overlap_ts, 0.0, 0.0, 0.0)
    row = run_trial(Job("mls", (0.05, 0.10), 16, ref, ("forestalign",), 0))[0]
    assert row["outcome"] == "refused", row
