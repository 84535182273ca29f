"""Settings in two tiers: `config --defaults` the few a user turns, `config --all` every key with its
reason; keys renamed or dropped since a file was written still load, with one note each."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from helpers import assert_one_line_error, invoke
from pydantic import BaseModel

from plotmosaic.config.settings import (
    RENAMED,
    USER_KEYS,
    Settings,
    dump_settings,
    load_settings,
    settings_from_dict,
)


def _leaf_keys(model: type[BaseModel], table: str = "") -> set[str]:
    """Every key of the settings file under `model` (dotted), the shared sections left out."""
    out = set()
    for key, field in model.model_fields.items():
        if field.exclude:
            continue
        where = f"{table}.{key}" if table else key
        sub = field.annotation
        if isinstance(sub, type) and issubclass(sub, BaseModel):
            out |= _leaf_keys(sub, where)
        else:
            out.add(where)
    return out


def _printed(text: str) -> dict[str, list[str]]:
    """Dotted key -> the comment lines just above it, for every key of a printed settings file
    (an unset key is printed as `# key is unset`)."""
    out, table, comments = {}, "", []
    for line in text.splitlines():
        if line.startswith("["):
            table, comments = line.strip("[]"), []
        elif line.startswith("# ") and line.endswith(" is unset"):
            out[f"{table}.{line[2:].split()[0]}"] = comments
            comments = []
        elif line.startswith("#"):
            comments.append(line)
        elif " = " in line and not line.startswith(" "):
            out[f"{table}.{line.split(' = ')[0]}"] = comments
            comments = []
        elif not line.strip():
            comments = []
    return out


ALL_KEYS = _leaf_keys(Settings)


def test_user_keys_are_keys_of_the_settings_file():
    assert USER_KEYS <= ALL_KEYS, sorted(USER_KEYS - ALL_KEYS)


def test_defaults_print_the_user_tier_each_with_its_comment():
    res = invoke("config", "--defaults")
    assert res.exit_code == 0, res.output
    printed = _printed(res.output)
    assert set(printed) == USER_KEYS
    assert len(printed) <= 30
    assert all(printed.values()), [k for k, c in printed.items() if not c]
    assert settings_from_dict(tomllib.loads(res.output)) == Settings()


@pytest.mark.parametrize("args", [["--all"], ["--defaults", "--all"]])
def test_all_prints_every_key_with_its_reason_and_the_calibration_pointer(args):
    res = invoke("config", *args)
    assert res.exit_code == 0, res.output
    printed = _printed(res.output)
    assert set(printed) == ALL_KEYS
    assert all(printed.values()), [k for k, c in printed.items() if not c]
    assert "docs/method.md#calibration-settings" in res.output
    # a table's calibration comes after its user keys, under the pointer to docs/method.md
    align = list(printed)[: list(printed).index("align.voxel") + 1]
    assert set(align[:-1]) == {k for k in USER_KEYS if k.startswith("align.") and k.count(".") == 1}
    assert "docs/method.md#calibration-settings" in printed["align.voxel"][0]


def test_the_shared_sections_are_no_keys_of_the_stages_own_tables():
    for table, key in [("register_plot", "graph"), ("tie_to_als", "align_settings")]:
        with pytest.raises(ValueError, match=f"{table}.{key}: unknown setting"):
            settings_from_dict({table: {key: {}}})


def test_renamed_keys_keep_their_table_and_are_gone_from_the_file():
    for old, new in RENAMED.items():
        assert old not in ALL_KEYS, old
        if new is not None:
            assert new in ALL_KEYS and new.rpartition(".")[0] == old.rpartition(".")[0], new


def test_a_file_with_old_keys_loads_under_the_new_names_with_one_note_each(tmp_path):
    old = tmp_path / "old.toml"
    old.write_text(
        "[posegraph]\nmin_confidence = 0.3\n"
        "[register_plot.placed_priors]\nmin_confidence = 0.7\n"
        "[align.coarse]\nstem_linearity_z = 0.8\n"
    )
    notes: list[str] = []
    settings = settings_from_dict(tomllib.loads(old.read_text()), note=notes.append)
    assert settings.posegraph.sure_edge_confidence == 0.3
    assert settings.register_plot.placed_priors.sure_placement_confidence == 0.7
    assert settings.register_config().graph.sure_edge_confidence == 0.3
    assert notes == [
        "note: [posegraph] min_confidence is now [posegraph] sure_edge_confidence",
        "note: [register_plot.placed_priors] min_confidence is now "
        "[register_plot.placed_priors] sure_placement_confidence",
        "note: [align.coarse] stem_linearity_z is no longer read: left out",
    ]
    # as a user runs it: the notes on stderr, the check on stdout
    argv = [sys.executable, "-m", "plotmosaic", "config", "--check", str(old)]
    run = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stderr.splitlines() == notes
    assert "2 settings differ" in run.stdout
    # written again, it holds only the new names and loads without a note
    again = tmp_path / "again.toml"
    again.write_text(dump_settings(settings))
    quiet: list[str] = []
    assert settings_from_dict(tomllib.loads(again.read_text()), note=quiet.append) == settings
    assert quiet == [] and load_settings(again) == settings


def test_an_old_key_beside_its_new_name_is_refused(tmp_path):
    both = tmp_path / "both.toml"
    both.write_text("[posegraph]\nmin_confidence = 0.3\nsure_edge_confidence = 0.4\n")
    assert_one_line_error(
        invoke("config", "--check", both), str(both), "posegraph.min_confidence", code=2
    )


def test_formats_md_lists_the_user_tier():
    """docs/formats.md's table of settings names every user key and no other."""
    text = (Path(__file__).resolve().parents[1] / "docs" / "formats.md").read_text()
    rows = text.split("| setting | default | what it turns |")[1].split("\n\n")[0].splitlines()
    listed = set()
    for row in rows[2:]:
        cell = row.split(" | ")[0]
        table = re.search(r"\[([\w.]+)\]", cell).group(1)
        names = re.findall(r"`(?:\[[\w.]+\] )?(\w+)`", cell)
        listed |= {f"{table}.{name}" for name in names}
    assert listed == USER_KEYS
