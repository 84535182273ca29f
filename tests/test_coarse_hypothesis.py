"""The coarse stage's typed hand-overs: starts merged into their first near-duplicate, a verified
hypothesis as its RESULT.json row, and verification computing each start once."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import numpy as np
import pytest

from plotmosaic.align.coarse import clouds
from plotmosaic.align.coarse import verify as verification
from plotmosaic.align.coarse.clouds import CoarseCloud, Levels, remembered
from plotmosaic.align.coarse.hypothesis import Hypothesis, Start
from plotmosaic.align.coarse.verify import Verifier, support, unique_starts
from plotmosaic.align.levelling import Vertical
from plotmosaic.align.memo import CloudMemo
from plotmosaic.config.coarse import CoarseConfig
from plotmosaic.io.frame import pose_error


def _pose(yaw_deg: float, x: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3] = x
    return T


def test_near_duplicate_starts_merge_into_the_first_and_the_prior_never_does():
    config = CoarseConfig()
    first = Start(T=_pose(10.0, 1.0), generator="raster", vertical="a/b", score=0.5, yaw=0.17)
    copy = Start(
        T=_pose(10.0, 1.0 + 0.1 * config.start_duplicate_m), generator="stems", vertical="c/d"
    )
    other = Start(T=_pose(100.0, 5.0), generator="fpfh", vertical="a/b", votes=7)
    prior = Start(T=first.T.copy(), generator="prior", vertical="prior", prior=True)
    out = unique_starts([first, copy, other, prior], config)
    assert [s.generator for s in out] == ["raster", "fpfh", "prior"]
    assert (
        out[0].agree == ("stems:c/d",) and first.agree == ()
    )  # a new start, the old one untouched
    assert out[0].key == first.key  # verification still finds what it computed for it
    again = unique_starts(
        [*out, Start(T=_pose(100.0, 5.0), generator="stems", vertical="x/y")], config
    )
    assert again[0] is out[0] and again[1].agree == ("stems:x/y",)


def test_support_counts_the_generators_that_agreed_with_the_best_pose():
    config = CoarseConfig()
    merged = Start(T=_pose(0.0, 0.0), generator="raster", vertical="a/b", agree=("fpfh:a/b",))
    best = Hypothesis.verified(merged, merged.T, 0.6, 0.7)
    far = Hypothesis.verified(
        Start(T=_pose(90.0, 9.0), generator="stems", vertical="a/b"), _pose(90.0, 9.0), 0.5, None
    )
    prior = Hypothesis.verified(
        Start(T=_pose(0.0, 0.0), generator="prior", vertical="prior", prior=True),
        _pose(0.0, 0.0),
        0.6,
        None,
    )
    assert support([best, far, prior], best, config) == {"raster", "fpfh"}


@pytest.mark.parametrize(
    ("measured", "extra"),
    [
        ({"generator": "raster", "score": 0.4, "yaw": 0.5, "overlap": 0.8}, set()),
        ({"generator": "fpfh", "votes": 12}, {"votes"}),
        (
            {"generator": "slices", "slice_score": 0.3, "yaw": 0.5, "agree": ("stems:a/b",)},
            {"agree", "slice_score"},
        ),
    ],
)
def test_a_hypothesis_row_names_only_what_its_generator_measured(measured, extra):
    start = Start(T=_pose(30.0, 2.0), vertical="a/b", **measured)
    row = Hypothesis.verified(start, start.T, 0.25, None).to_dict()
    base = (
        "refined score screen_score raster_score yaw_deg overlap prior generator vertical".split()
    )
    assert list(row)[: len(base)] == base and list(row)[-1] == "transform"
    assert set(row) - set(base) - {"transform"} == extra
    assert row["refined"] is False and row["score"] is None and row["screen_score"] == 0.25
    assert row["raster_score"] == start.score and row["overlap"] == start.overlap
    # a heading measured by the generator, else read from the pose
    assert row["yaw_deg"] == pytest.approx(np.degrees(start.yaw) if start.yaw is not None else 30.0)
    assert np.array_equal(np.asarray(row["transform"]), start.T)
    json.dumps(row, allow_nan=False)


def test_an_empty_search_reports_the_identity():
    row = Hypothesis.none().to_dict()
    assert row["generator"] == "none" and row["refined"] is True and row["score"] == 0.0
    assert np.array_equal(np.asarray(row["transform"]), np.eye(4))


def _stand(rng: np.random.Generator) -> CoarseCloud:
    """Ground and a dozen upright stems, with their normals."""
    ground = np.column_stack([rng.uniform(-10, 10, (4000, 2)), rng.normal(0, 0.01, 4000)])
    parts, normals = [ground], [np.tile([0.0, 0.0, 1.0], (4000, 1))]
    for x, y in rng.uniform(-8, 8, (12, 2)):
        a, z = rng.uniform(0, 2 * np.pi, 400), rng.uniform(0, 6, 400)
        radial = np.column_stack([np.cos(a), np.sin(a), np.zeros(400)])
        parts.append(np.column_stack([x + 0.2 * radial[:, 0], y + 0.2 * radial[:, 1], z]))
        normals.append(radial)
    up = Vertical(up=np.array([0.0, 0.0, 1.0]), name="normals")
    return CoarseCloud(
        points=np.vstack(parts), normals=np.vstack(normals), verticals=(up,), info={}
    )


def test_verification_keeps_a_start_s_results_when_other_generators_agree_with_it(monkeypatch):
    """A start merged with a later near-duplicate is a new Start; its screening and refinement are
    not run again, and its row names the generator that agreed."""
    config = CoarseConfig()
    cloud = _stand(np.random.default_rng(5))
    verifier = Verifier(cloud, Levels(cloud), False, config, np.random.default_rng(0))
    icps = []
    real = verification._refine
    monkeypatch.setattr(verification, "_refine", lambda *args: icps.append(args[2]) or real(*args))
    right = Start(T=_pose(3.0, 0.3), generator="raster", vertical="normals/normals", yaw=0.05)
    wrong = Start(T=_pose(120.0, 4.0), generator="fpfh", vertical="normals/normals", votes=9)
    first, _ = verifier([right, wrong])
    ran = len(icps)
    assert first[0].refined and first[0].generator == "raster"
    assert pose_error(first[0].T, np.eye(4))[0] < 0.5
    again = unique_starts(
        [right, wrong, Start(T=_pose(3.2, 0.3), generator="stems", vertical="normals/normals")],
        config,
    )
    second, _ = verifier(again)
    assert len(icps) == ran  # nothing screened or refined twice
    assert second[0].agree == ("stems:normals/normals",)
    assert [h.T.tobytes() for h in second] == [h.T.tobytes() for h in first]


def test_a_cloud_s_levelled_form_and_stem_map_are_made_once_for_every_thread_that_asks(monkeypatch):
    """The levelled forms live in the memo that owns the cloud: four threads asking for one stem
    map level the cloud once and share one map."""
    config = CoarseConfig()
    levels = Levels(_stand(np.random.default_rng(5)))
    made = []
    real = clouds.levelled
    monkeypatch.setattr(clouds, "levelled", lambda *args: made.append(args[1].name) or real(*args))
    up = levels.cloud.verticals[0]
    with ThreadPoolExecutor(4) as pool:
        maps = list(pool.map(lambda _: levels.stems(up, config), range(4)))
    assert made == ["normals"]
    assert all(m is maps[0] for m in maps)
    assert levels.level(up, config) is levels.level(up, config) and made == ["normals"]


def test_a_cloud_memo_keeps_one_coarse_sample_per_key():
    """The same cloud, seed and settings: the kept sample and its levelled forms; another seed
    replaces them."""
    config = CoarseConfig(max_points=2000)
    cloud = SimpleNamespace(points=_stand(np.random.default_rng(5)).points)  # a cloud's points
    memo = CloudMemo()
    first = remembered(cloud, config, 0, False, False, 2, memo)
    assert remembered(cloud, config, 0, False, False, 2, memo) is first
    other = remembered(cloud, config, 1, False, False, 2, memo)
    assert other is not first and remembered(cloud, config, 1, False, False, 2, memo) is other


def test_a_start_of_the_best_pose_s_own_basin_left_short_is_refined_on_and_no_rival(monkeypatch):
    """A quick refine that stops short (here each ICP halves a pose's heading and shift) leaves a
    start of the best pose's own basin distinct from it: near the best, it is refined on until it
    joins it and is no rival of the confidence; a pose far off is not refined on and stays one."""
    cloud = _stand(np.random.default_rng(5))

    def halfway(points, tgt, T, *args):
        return _pose(np.degrees(np.arctan2(T[1, 0], T[0, 0])) / 2, T[0, 3] / 2)

    monkeypatch.setattr(verification, "_refine", halfway)
    starts = [
        Start(T=_pose(1.0, 0.1), generator="raster", vertical="normals/normals", yaw=0.02),
        Start(T=_pose(64.0, 4.0), generator="fpfh", vertical="normals/normals", votes=9),
        Start(T=_pose(170.0, 16.0), generator="stems", vertical="normals/normals", votes=3),
    ]

    def verify(passes: int) -> tuple[dict[str, Hypothesis], float]:
        config = CoarseConfig(near_rival_passes=passes)
        verifier = Verifier(cloud, Levels(cloud), False, config, np.random.default_rng(0))
        results, confidence = verifier(starts)
        assert results[0].generator == "raster"
        return {h.generator: h for h in results}, confidence

    config = CoarseConfig()
    (short, short_conf), (on, on_conf) = verify(0), verify(4)
    assert 1.0 < verification.radii(short["fpfh"].T, short["raster"].T, config) <= 3.0
    assert verification.radii(on["fpfh"].T, on["raster"].T, config) <= 1.0  # joined the best
    assert np.allclose(on["stems"].T, short["stems"].T)  # far: not refined on, still a rival
    assert verification.distinct(on["stems"].T, on["raster"].T, config)
    assert on_conf > short_conf
