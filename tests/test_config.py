"""One settings file for every stage: --config, config-used.toml, `config --defaults`, named errors."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
import typing

import numpy as np
import pytest
from helpers import assert_one_line_error, invoke
from pydantic import BaseModel

from plotmosaic.commands.common import run_settings
from plotmosaic.config.align import MAX_LEVELS
from plotmosaic.config.merge import MergeConfig
from plotmosaic.config.register import RegisterConfig, TieConfig
from plotmosaic.config.settings import Settings, dump_settings, load_settings, settings_from_dict
from plotmosaic.errors import InputError
from plotmosaic.manifest import Scan
from plotmosaic.poses import load_poses

FAST = """
[align]
voxel = 0.1
final_voxel = 0.05
complexity = "vmf"

[align.coarse]
enabled = true
"""


@pytest.fixture(scope="module")
def pair(small_sim, tmp_path_factory):
    """Two scans of the small plot and a start 0.4 m off the truth (ICP only: fast)."""
    truth = load_poses(small_sim.ground_truth_path)
    T = np.linalg.inv(truth.transform("P1-S0")) @ truth.transform("P1-S1")
    T[:3, 3] += [0.3, -0.2, 0.1]
    folder = tmp_path_factory.mktemp("config")
    (folder / "init.json").write_text(json.dumps({"transform": T.tolist()}))
    (folder / "fast.toml").write_text(FAST)
    return small_sim.scan_paths["P1-S1"], small_sim.scan_paths["P1-S0"], folder


def _align_process(*args) -> subprocess.CompletedProcess:
    """`plotmosaic align` as a user runs it: a process of its own, with nothing run before it."""
    argv = [sys.executable, "-m", "plotmosaic", "align", *map(str, args)]
    return subprocess.run(argv, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_config_used_given_back_repeats_align_bit_for_bit(pair, tmp_path):
    src, tgt, folder = pair
    init, fast = folder / "init.json", folder / "fast.toml"
    first = _align_process(
        src, tgt, "--init", init, "--config", fast, "--no-coarse", "--out", tmp_path / "a.json"
    )
    assert first.returncode == 0, first.stderr
    used = tmp_path / "a.config-used.toml"
    settings = load_settings(used)
    # the option beat the file, the file's other keys stayed, the rest kept its defaults
    assert settings.align.coarse.enabled is False
    assert settings.align.complexity == "vmf" and settings.align.voxel == 0.1
    assert settings.align.judge == Settings().align.judge

    again = _align_process(src, tgt, "--init", init, "--config", used, "--out", tmp_path / "b.json")
    assert again.returncode == 0, again.stderr
    a, b = (json.loads((tmp_path / n).read_text()) for n in ("a.json", "b.json"))
    assert a["transform"] == b["transform"]  # floats from JSON: bit for bit
    for key in ("fitness", "inlier_rmse", "overlap", "information", "levels", "confidence"):
        assert a.get(key) == b.get(key), key
    assert load_settings(tmp_path / "b.config-used.toml") == settings


BAD = [
    ("[align.judge]\nfoo = 1\n", "align.judge.foo", "unknown"),  # JudgeConfig allows extras itself
    ("[merge]\nvoxle = 0.1\n", "merge.voxle", "unknown"),
    ("[nosuch]\n", "nosuch", "unknown"),
    ("[align.coarse]\ncell = 0\n", "align.coarse.cell", "greater than 0"),
    ("[register_plot]\nmax_distance = -5\n", "register_plot.max_distance", "greater than 0"),
    ("[align]\nlevel_schedule = [[{max_distance = 1.0}]]\n", "level_schedule[0][0].iterations", ""),
    ("[align\n", "not valid TOML", ""),
]


@pytest.mark.parametrize("text, key, why", BAD)
@pytest.mark.parametrize(
    "command",
    [
        ["align", "a.laz", "b.laz"],
        ["register-plot", "m.toml", "--out", "o"],
        ["tie-to-als", "m.toml", "--poses", "p.json", "--out", "o"],
        ["merge", "m.toml", "--poses", "p.json", "--out", "o.laz"],
        ["config", "--check"],
    ],
    ids=lambda c: c[0] if isinstance(c, list) else None,
)
def test_bad_settings_file_exits_2_naming_the_key(tmp_path, monkeypatch, command, text, key, why):
    monkeypatch.chdir(tmp_path)  # nothing may be written: the settings are checked before any work
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    args = [*command, bad] if command[0] == "config" else [*command, "--config", bad]
    assert_one_line_error(invoke(*args), str(bad), key, why, code=2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml"]


@pytest.mark.parametrize("tier", ["--defaults", "--all"])
def test_defaults_print_and_load_back_equal(tmp_path, tier):
    res = invoke("config", tier)
    assert res.exit_code == 0, res.output
    text = res.output
    # each key with its description
    assert "# least judge confidence (margin over the best distinct rival)" in text
    assert ("# delta0: voxel (m) of the working clouds" in text) == (tier == "--all")
    loaded = settings_from_dict(tomllib.loads(text))
    assert loaded == Settings()
    # the sections build exactly the stages' own defaults
    assert loaded.register_config() == RegisterConfig()
    assert loaded.tie_config() == TieConfig()
    assert loaded.merge == MergeConfig()
    path = tmp_path / "d.toml"
    path.write_text(text)
    ok = invoke("config", "--check", path)
    assert ok.exit_code == 0 and "0 settings differ" in ok.output, ok.output


def test_floats_round_trip_exactly():
    awkward = {
        "align": {"voxel": 0.1 + 0.2, "min_confidence": 1 / 3, "level_tol": 1e-300},
        "posegraph": {"outlier_chi2": 1e300, "robust_k": 2.0000000000000004},
        "merge": {"bbox": [0.1, -0.7, 1e5 + 0.3, 2.5]},
        "register_plot": {"max_distance": 59.99999999999999},
    }
    settings = settings_from_dict(awkward)
    back = settings_from_dict(tomllib.loads(dump_settings(settings)))
    assert back == settings
    assert back.align.voxel == 0.1 + 0.2 and back.posegraph.robust_k == 2.0000000000000004


def test_options_override_the_file_and_unset_options_keep_it(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(
        "[register_plot]\nmax_distance = 30.0\nplace_on_als = false\n[tie_to_als]\nbuffer = 5.0\n"
    )
    s = run_settings(path, {"register_plot": {"max_distance": 45.0, "place_on_als": None}})
    assert s.register_plot.max_distance == 45.0  # given on the command line
    assert s.register_plot.place_on_als is False  # not given: the file's
    assert s.tie_to_als.buffer == 5.0
    r = s.register_config()
    assert r.max_distance == 45.0 and r.place_on_als is False
    assert r.align.min_confidence == 0.0 and r.placement.min_confidence == 0.25
    assert s.tie_config().buffer == 5.0
    with pytest.raises(InputError, match="register_plot.max_distance"):
        run_settings(path, {"register_plot": {"max_distance": -1.0}})


def test_one_levels_limit_for_manifest_and_cli(tmp_path):
    assert Scan(id="s", path="s.laz", levels=MAX_LEVELS).levels == MAX_LEVELS
    with pytest.raises(ValueError):
        Scan(id="s", path="s.laz", levels=MAX_LEVELS + 1)
    res = invoke("align", "a.laz", "b.laz", "--levels-source", MAX_LEVELS + 1)
    assert_one_line_error(res, "--levels-source", f"1 to {MAX_LEVELS}", code=2)


def _models(model: type[BaseModel], seen: dict[str, type[BaseModel]]) -> dict:
    """Every settings model reachable from `model` (fields, lists of models)."""
    if model.__name__ in seen:
        return seen
    seen[model.__name__] = model
    for field in model.model_fields.values():
        inner = field.annotation
        while typing.get_origin(inner) is list:
            (inner,) = typing.get_args(inner)
        if isinstance(inner, type) and issubclass(inner, BaseModel):
            _models(inner, seen)
    return seen


MODELS = _models(Settings, {})


@pytest.mark.parametrize("name", sorted(MODELS))
def test_every_model_forbids_extras_and_every_field_is_described_and_bounded(name):
    model = MODELS[name]
    assert model.model_config.get("extra") == "forbid", name
    for key, field in model.model_fields.items():
        assert field.description, f"{name}.{key}: no description"
        numeric = field.annotation in (int, float) or field.annotation in (int | None, float | None)
        bounded = any(type(m).__name__ in ("Gt", "Ge", "Lt", "Le") for m in field.metadata)
        assert bounded or not numeric, f"{name}.{key}: no bounds"


def test_merge_config_used_repeats_the_merge_byte_for_byte(small_sim, tmp_path):
    m, poses = small_sim.manifest_path, small_sim.ground_truth_path
    first = invoke("merge", m, "--poses", poses, "--out", tmp_path / "a.laz", "--voxel", "0.05")
    assert first.exit_code == 0, first.output
    used = tmp_path / "a.config-used.toml"  # beside the output, named after it
    assert load_settings(used).merge.voxel == 0.05
    again = invoke("merge", m, "--poses", poses, "--out", tmp_path / "b.laz", "--config", used)
    assert again.exit_code == 0, again.output
    assert (tmp_path / "a.laz").read_bytes() == (tmp_path / "b.laz").read_bytes()


def test_config_needs_exactly_one_of_defaults_or_check(tmp_path):
    assert_one_line_error(invoke("config"), "--defaults", "--check", code=2)
    assert_one_line_error(invoke("config", "--defaults", "--check", tmp_path / "x.toml"), code=2)
    assert_one_line_error(invoke("config", "--all", "--check", tmp_path / "x.toml"), code=2)


def test_pairs_onto_the_als_keep_fpfh_unless_turned_off():
    # a real UAS strip onto its ALS found its pose only by FPFH: placements and anchors keep it
    assert RegisterConfig().align.coarse.fpfh
    assert RegisterConfig().placement.coarse.fpfh and TieConfig().align.coarse.fpfh
    defaults = settings_from_dict({})
    assert defaults.register_config().placement.coarse.fpfh
    assert defaults.tie_config().align == TieConfig().align
    off = settings_from_dict(
        {"register_plot": {"placement_fpfh": False}, "tie_to_als": {"anchor_fpfh": False}}
    )
    assert (
        not off.register_config().placement.coarse.fpfh and not off.tie_config().align.coarse.fpfh
    )
    assert off.register_config().align.coarse.fpfh  # scan pairs keep it
    everywhere = settings_from_dict({"align": {"coarse": {"fpfh": False}}})
    assert not everywhere.register_config().placement.coarse.fpfh
    assert not everywhere.tie_config().align.coarse.fpfh


def test_placements_settle_on_one_generator_pairs_and_anchors_on_two():
    # a placement is a prior the pairs verify again; scan pairs and plot -> ALS anchors are results
    assert RegisterConfig().placement.coarse.settled_generators == 1
    assert RegisterConfig().align.coarse.settled_generators == 2
    assert TieConfig().align.coarse.settled_generators == 2
    defaults = settings_from_dict({})
    assert defaults.register_config().placement == RegisterConfig().placement
    two = settings_from_dict({"register_plot": {"placement_settled_generators": 2}})
    assert two.register_config().placement.coarse.settled_generators == 2
    assert two.register_config().align.coarse.settled_generators == 2
