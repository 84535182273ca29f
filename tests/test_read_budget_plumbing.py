"""A user's `[read]` settings reach every scan register-plot and tie-to-als read (io/bounded.py)."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from plotmosaic.cli import app
from plotmosaic.config.reading import ReadingConfig
from plotmosaic.config.register import RegisterConfig, TieConfig
from plotmosaic.config.settings import load_settings
from plotmosaic.graph.jobs import prepare_jobs_for
from plotmosaic.graph.prepared import load_prepared, prepared_key
from plotmosaic.io.las import read_header_info
from plotmosaic.manifest import dump_manifest, load_manifest
from plotmosaic.poses import load_poses
from plotmosaic.stages.register_plot.pairs import pair_settings
from plotmosaic.stages.register_plot.plan import _signature_jobs, plan_jobs
from plotmosaic.stages.tie_to_als.clouds import plot_cloud

# thins the small plot's scans (about 50k points each), not its 35k-point plot cloud: thinned to
# the 80 cm cells its sparse canopy would need, a plot no longer shows stems to the scene check
BUDGET = 40_000


@pytest.fixture
def user_settings(tmp_path):
    path = tmp_path / "settings.toml"
    path.write_text(f"[read]\nmax_points_in_memory = {BUDGET}\n")
    return path


def two_scans(sim, folder):
    """The simulator's manifest cut to its first two scans, paths made absolute."""
    m = load_manifest(sim.manifest_path)
    plot = m.plots[0]
    scans = [s.model_copy(update={"path": m.resolve(s.path).resolve()}) for s in plot.scans[:2]]
    als = [t.model_copy(update={"path": m.resolve(t.path).resolve()}) for t in m.als]
    sub = m.model_copy(update={"plots": [plot.model_copy(update={"scans": scans})], "als": als})
    path = folder / "manifest.toml"
    path.write_text(dump_manifest(sub))
    return path


def notes(err: str) -> list[str]:
    return [line for line in err.splitlines() if "thinned on reading" in line]


def test_the_read_section_reaches_register_plot_and_tie(user_settings):
    settings = load_settings(user_settings)
    assert settings.register_config().read == ReadingConfig(max_points_in_memory=BUDGET)
    assert settings.tie_config().read == ReadingConfig(max_points_in_memory=BUDGET)
    assert RegisterConfig().read == TieConfig().read == ReadingConfig()


def test_register_plot_jobs_carry_the_budget_and_key_what_it_thins(small_sim, tmp_path):
    manifest = load_manifest(small_sim.manifest_path)
    small = RegisterConfig(read=ReadingConfig(max_points_in_memory=BUDGET))
    default = plan_jobs(manifest, RegisterConfig(), pair_settings(RegisterConfig(), 0, tmp_path))
    thinned = plan_jobs(manifest, small, pair_settings(small, 0, tmp_path))
    assert [j.source for j in default] == [j.source for j in thinned]
    for before, job in zip(default, thinned):
        assert job.reading == small.read and before.reading == ReadingConfig()
        assert job.key != before.key  # another budget thinning a scan: another pair result
        for pj in prepare_jobs_for(job):
            assert pj.reading == small.read
            assert pj.key == prepared_key(pj.path, pj.kind, pj.levels, small.align, 0, small.read)
    # a budget the scans fit in keys the pairs and scans as the default does
    roomy = RegisterConfig(read=ReadingConfig(max_points_in_memory=1_000_000))
    roomy = plan_jobs(manifest, roomy, pair_settings(roomy, 0, tmp_path))
    assert [j.key for j in roomy] == [j.key for j in default]
    signature = _signature_jobs(manifest, small, 0, tmp_path, manifest.plots)
    assert {j.prepare.reading for j in signature.values()} == {small.read}
    prepared = {pj.key for job in thinned for pj in prepare_jobs_for(job)}
    assert {j.prepare.key for j in signature.values()} == prepared


def test_tie_reads_a_scan_without_a_prepared_cloud_within_the_budget(small_sim, capsys):
    manifest = load_manifest(small_sim.manifest_path)
    truth = load_poses(small_sim.ground_truth_path)
    plot = manifest.plots[0].model_copy(update={"scans": manifest.plots[0].scans[:2]})
    config = TieConfig(read=ReadingConfig(max_points_in_memory=BUDGET))
    cloud = plot_cloud(manifest, plot, truth, config)
    err = capsys.readouterr().err
    assert len(notes(err)) == 2, err
    whole = plot_cloud(manifest, plot, truth, TieConfig())
    assert not notes(capsys.readouterr().err)
    assert 0 < len(cloud) < len(whole)
    # the thinned plot spans the whole one: every point of it is a point of the plot's surfaces
    lo, hi = whole.xyz.min(axis=0), whole.xyz.max(axis=0)
    assert np.all(cloud.xyz.min(axis=0) - lo < 0.2) and np.all(hi - cloud.xyz.max(axis=0) < 0.2)


@pytest.mark.slow
def test_register_plot_and_tie_to_als_honour_the_users_budget(small_sim, tmp_path, user_settings):
    manifest = two_scans(small_sim, tmp_path)
    out, tied = tmp_path / "out", tmp_path / "tied"
    common = ["--jobs", "1", "--config", str(user_settings)]
    run = CliRunner().invoke(app, ["register-plot", str(manifest), "--out", str(out), *common])
    assert run.exit_code == 0, run.output
    scans = load_manifest(manifest).plots[0].scans
    for scan in scans:
        assert any(f"note: {scan.path}: " in line for line in notes(run.stderr)), run.stderr
    recorded = json.loads((out / "poses.json").read_text())["prepared"]
    register = load_settings(user_settings).register_config()
    for scan in scans:
        key = prepared_key(scan.path, "tls", scan.k, register.align, 0, register.read)
        assert recorded[scan.id] == f"{key}.npz"
        assert load_prepared(out / "prepared" / recorded[scan.id]).input_points <= BUDGET
        assert read_header_info(scan.path).point_count > BUDGET
    assert all("-read-" in p.stem for p in (out / "pairs").glob("*.json"))
    tie = CliRunner().invoke(
        app,
        ["tie-to-als", str(manifest), "--poses", str(out / "poses.json"), "--out", str(tied)]
        + common,
    )
    assert tie.exit_code == 0, tie.output
    # the plot -> ALS pair is keyed apart exactly when the budget thins one of its two clouds
    over = any(
        read_header_info(tied / "plots" / name).point_count > BUDGET
        for name in ("P1.laz", "P1_als.laz")
    )
    keys = [p.stem for p in (tied / "pairs").glob("*.json")]
    assert keys and all(("-read-" in k) == over for k in keys)


@pytest.mark.slow
def test_align_honours_the_users_budget(small_sim, tmp_path, user_settings):
    m = load_manifest(small_sim.manifest_path)
    src, tgt = (m.resolve(s.path) for s in m.plots[0].scans[:2])
    out = tmp_path / "pair"
    args = ["align", str(src), str(tgt), "--out", str(out), "--config", str(user_settings)]
    result = CliRunner().invoke(app, args)
    assert result.exit_code in (0, 3), result.output
    assert len(notes(result.output)) == 2  # both clouds read within the budget, each said once
