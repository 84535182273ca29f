"""The ALS placements of a plot's scans share the tile's work: a worker keeps the tile's memo (the
run's, graph/executor.py) from one placement to the next. Each placement must come out the same to
the bit as a registration that shares nothing, whichever placement ran before it."""

import numpy as np
import pytest

from plotmosaic.align.memo import PairMemo, RunMemo
from plotmosaic.align.pair import register_prepared
from plotmosaic.config.register import RegisterConfig
from plotmosaic.graph.jobs import JobSettings, PairJob, prepare_jobs_for
from plotmosaic.graph.placement import ALS_ID, placement_jobs
from plotmosaic.graph.prepared import get_prepared
from plotmosaic.manifest import load_manifest


@pytest.fixture(scope="module")
def placements(small_sim, tmp_path_factory) -> list[PairJob]:
    """Two scans of the small plot -> its ALS tile, as register-plot builds the jobs."""
    manifest = load_manifest(small_sim.manifest_path)
    config = RegisterConfig()
    folder = str(tmp_path_factory.mktemp("prepared"))
    settings = JobSettings(config.placement, 0, folder, config.read, config.align)
    return placement_jobs(manifest, manifest.plots[0], settings)[:2]


def _register(job: PairJob, memo: PairMemo):
    ps, pt = prepare_jobs_for(job)
    src, tgt = get_prepared(ps)[0], get_prepared(pt)[0]
    return register_prepared(src, tgt, job.config, None, job.seed, memo=memo)


def test_placements_sharing_the_tile_are_bit_identical(placements):
    assert [j.target for j in placements] == [ALS_ID, ALS_ID]
    keys = [prepare_jobs_for(j) for j in placements]
    assert keys[0][1].key == keys[1][1].key  # one tile: one prepared cloud
    assert keys[0][0].key != keys[1][0].key
    run = RunMemo()
    memos = [run.pair(ps.key, pt.key) for ps, pt in keys]
    assert memos[0].target is memos[1].target  # the tile's figures are the run's, not the pair's
    # each placement run first (on a fresh memo: nothing shared) and second, on the tile memo the
    # other one filled
    results = {}
    for order in ((0, 1), (1, 0)):
        run = RunMemo()
        for rank, i in enumerate(order):
            results[i, rank] = _register(placements[i], run.pair(*(pj.key for pj in keys[i])))
    for i in (0, 1):
        alone, shared = results[i, 0], results[i, 1]
        assert np.array_equal(shared.transform, alone.transform)
        assert shared.confidence == alone.confidence
        clock = ("seconds", "timing")  # the only figures of the search that are not its result
        assert {k: v for k, v in shared.coarse.items() if k not in clock} == {
            k: v for k, v in alone.coarse.items() if k not in clock
        }
