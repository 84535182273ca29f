"""A pair job's key: made in one function (graph/jobs.py) and unchanged from the keys cached runs hold."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from pydantic import BaseModel

import plotmosaic
from plotmosaic.config.align import AlignConfig
from plotmosaic.config.reading import ReadingConfig
from plotmosaic.graph import jobs as jobs_module
from plotmosaic.graph.jobs import JobSettings, ScanFile, pair_job, with_stored_poses

INIT = ((1.0, 0.0), (0.0, 1.0))


class Voxel(BaseModel):  # settings whose JSON stays put, whatever the align settings become
    voxel: float = 0.05


# computed with the code before the job had one home (pair_key, with_reading, with_stored_poses)
# for the files b"scan a" and b"scan b", version "0.0-test", seed 7: runs resumed on older output
# folders hit their cache only while these stay. The default AlignConfig's JSON is part of the key:
# it moves when the method does (so a cached pair of the older method is recomputed), last when the
# search and the judge took the space a known scanner saw through (align/freespace.py)
KNOWN = {
    "voxel": "a3027940498eda0c24be8825f60d8d58",
    "align": "87a36106c7e471b1a39caaa911a8e1a8",
}


@pytest.fixture
def sides(tmp_path, monkeypatch) -> tuple[ScanFile, ScanFile]:
    monkeypatch.setattr(jobs_module, "__version__", "0.0-test")
    # b.laz thins under any budget below the default (its header is not read: it has none)
    monkeypatch.setattr(
        jobs_module,
        "over_budget",
        lambda path, reading: path.endswith("b.laz") and reading.max_points_in_memory < 20_000_000,
    )
    (tmp_path / "a.laz").write_bytes(b"scan a")
    (tmp_path / "b.laz").write_bytes(b"scan b")
    return (
        ScanFile("s1", str(tmp_path / "a.laz"), "tls", 3),
        ScanFile("s0", str(tmp_path / "b.laz"), "tls", None),
    )


@pytest.mark.parametrize("name, config", [("voxel", Voxel()), ("align", AlignConfig())])
def test_the_key_of_a_known_job_is_unchanged(sides, name, config):
    base = KNOWN[name]
    plain = JobSettings(config, 7)
    thin = JobSettings(config, 7, reading=ReadingConfig(max_points_in_memory=10_000))
    assert pair_job(plain, *sides, INIT).key == base
    assert pair_job(thin, *sides, INIT).key == f"{base}-read-e5f6d6730fb3"
    assert (
        pair_job(thin, *sides, INIT, "stored").key
        == f"{base}-read-e5f6d6730fb3-stored-4822098b61ed"
    )
    assert pair_job(plain, *sides, INIT, "only").key == f"{base}-stored-only-4822098b61ed"


def test_a_job_asked_for_again_is_the_job_asked_for_so(sides):
    settings = JobSettings(Voxel(), 7, "prepared")
    job = pair_job(settings, *sides, INIT)
    (marked,) = with_stored_poses([job], {"s0", "s1"}, start="only")
    assert marked == pair_job(settings, *sides, INIT, "only") and marked.start == "only"
    assert with_stored_poses([marked], {"s0", "s1"}) == [marked]  # marked already: kept
    assert with_stored_poses([job], {"s1"}) == [job]  # one scan without a verified pose


def test_only_the_one_constructor_makes_a_pair_job():
    root = Path(plotmosaic.__file__).parent
    made = [
        str(p.relative_to(root))
        for p in root.rglob("*.py")
        if re.search(r"\bPairJob\(", p.read_text()) or re.search(r"-stored-|-read-", p.read_text())
    ]
    assert made == ["graph/jobs.py"]
