"""benchmarks/bench_overlap.py: bins, seeded cuts of real separated views whose measured overlap lies in
their bin, the levelling handed to Sylva, and (slow) one tiny resumable run end to end."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from plotmosaic.bench.overlap_pairs import (
    bin_of,
    build_catalogue,
    candidate,
    cut_candidate,
    load_pair,
    parse_bins,
)
from plotmosaic.bench.peers import levelling, peer_available
from plotmosaic.errors import InputError
from plotmosaic.io.frame import apply_transform

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="module")
def data() -> Path:
    if not (SHARED / "treels" / "pine_plot.laz").is_file():
        pytest.skip("shared/data/treels not present")
    return SHARED


def test_bins_are_half_open_and_the_last_is_closed():
    bins = parse_bins("0.05,0.10,0.15,0.5")
    assert bins == [(0.05, 0.10), (0.10, 0.15), (0.15, 0.5)]
    assert bin_of(0.05, bins) == (0.05, 0.10)
    assert bin_of(0.0999, bins) == (0.05, 0.10)
    assert bin_of(0.10, bins) == (0.10, 0.15)
    assert bin_of(0.5, bins) == (0.15, 0.5)
    assert bin_of(0.049, bins) is None and bin_of(0.51, bins) is None
    for bad in ("0.1", "0.2,0.1", "0,0.1", "0.1,1.5", "a,b"):
        with pytest.raises(InputError):
            parse_bins(bad)


def test_candidates_depend_on_source_seed_and_index_only():
    a = candidate("mls", 0, 7)
    assert a == candidate("mls", 0, 7)
    assert a != candidate("mls", 1, 7) and a != candidate("mls", 0, 8)
    assert candidate("treels", 0, 7) != candidate("mls", 0, 7)
    with pytest.raises(InputError):
        candidate("nowhere", 0, 0)


def test_levelling_turns_up_vertical():
    rng = np.random.default_rng(3)
    for up in [*rng.normal(size=(5, 3)), np.array([0, 0, 1.0]), np.array([0, 0, -1.0])]:
        L = levelling(up)
        assert np.allclose(L[:3, :3] @ (up / np.linalg.norm(up)), [0, 0, 1], atol=1e-9)
        assert np.allclose(L[:3, :3] @ L[:3, :3].T, np.eye(3), atol=1e-9)


def _overlap(a: np.ndarray, b: np.ndarray) -> float:
    d, _ = cKDTree(b).query(a, k=1, distance_upper_bound=0.25)
    return float(np.mean(np.isfinite(d)))


def test_cut_pairs_measure_into_their_bins_and_rerun_from_cache(data, tmp_path):
    bins = [(0.15, 0.30), (0.30, 0.50)]
    cat = build_catalogue("treels", bins, 1, 0, tmp_path, data)
    for b, refs in cat.items():
        assert len(refs) == 1, f"no treels pair in {b}"
        pair = load_pair(refs[0].path)
        aligned = apply_transform(pair.truth, pair.source)
        st, ts = _overlap(aligned, pair.target), _overlap(pair.target, aligned)
        assert b[0] <= max(st, ts) <= b[1], (b, st, ts)
        assert (st, ts) == pytest.approx((refs[0].overlap_st, refs[0].overlap_ts), abs=2e-3)
        # two scanners apart, each in its own frame: the views are separate scans, not crops
        assert refs[0].distance_m > 2.0
        assert np.linalg.norm(pair.truth[:3, 3]) > 2.0
        assert np.linalg.norm(pair.source, axis=1).max() <= refs[0].max_range + 1e-3
    index = tmp_path / "treels-seed0-candidates.json"
    before = index.read_text()
    assert build_catalogue("treels", bins, 1, 0, tmp_path, data) == cat
    assert index.read_text() == before  # nothing cut again
    # the cut is a function of the seed: the same candidate twice gives the same points
    k = int(cat[bins[1]][0].id.split("-c")[1].split("-")[0])
    again = cut_candidate(candidate("treels", 0, k), data)[0]
    assert np.allclose(again.source, load_pair(cat[bins[1]][0].path).source, atol=1e-5)
    assert json.loads(before)[str(k)]["pairs"][0]["overlap"] == [again.overlap_st, again.overlap_ts]


@pytest.mark.slow
def test_bench_overlap_end_to_end_resumes(data, tmp_path):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    try:
        import bench_overlap
    finally:
        sys.path.pop(0)
    # Sylva is a bench extra: run beside the others when it is installed
    methods = ("forestalign", "icp") + (() if peer_available("sylva") else ("sylva-levelled",))
    argv = ["--sources", "treels", "--bins", "0.30,0.50", "--n", "2", "--pairs", "1"]
    argv += ["--methods", ",".join(methods), "--out", str(tmp_path)]
    assert bench_overlap.main(argv) == 0
    rows = [json.loads(line) for line in (tmp_path / "trials.jsonl").read_text().splitlines()]
    assert sorted((r["trial"], r["method"]) for r in rows) == sorted(
        (t, m) for t in (0, 1) for m in methods
    )
    assert all(
        r["source"] == "treels" and 0.30 <= max(r["overlap_st"], r["overlap_ts"]) for r in rows
    )
    assert not [
        r for r in rows if r["method"] == "forestalign" and not r["failed"] and not r["success"]
    ]
    assert (tmp_path / "overlap.png").stat().st_size > 10_000
    assert "| **all** | [0.30, 0.50] | 1 | 2 |" in (tmp_path / "table.md").read_text()
    assert bench_overlap.main(argv) == 0  # resumed: nothing new to run
    assert len((tmp_path / "trials.jsonl").read_text().splitlines()) == len(rows)
