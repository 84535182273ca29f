"""The settings of a whole run, one TOML file for every stage (a leaf: imports only config modules).

Sections: [align] (pairwise registration, with [align.coarse], [align.judge], [align.stray]: used by
`align`, by register-plot for its pairs and its ALS placement, and by tie-to-als), [posegraph],
[pairs], [register_plot], [tie_to_als], [merge], [report], [read] (how much of a scan registration
holds while reading it). `plotmosaic config --defaults` prints the few a user turns (USER_KEYS),
`--all` every key, the method's calibration too; each run writes every setting it used as
config-used.toml beside its outputs, and that file given back with `--config` repeats the run exactly
(floats are written with repr, which reads back bit for bit).
"""

from __future__ import annotations

import json
import math
import re
import sys
import tomllib
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from plotmosaic.config.align import AlignConfig
from plotmosaic.config.merge import MergeConfig
from plotmosaic.config.reading import ReadingConfig
from plotmosaic.config.register import PairSelection, PoseGraphConfig, RegisterConfig, TieConfig
from plotmosaic.config.report import ReportConfig

# The settings a user turns: `config --defaults` prints these; every other key is the method's
# calibration, printed by `config --all` (docs/method.md#calibration-settings). One place decides.
USER_KEYS = frozenset(
    {
        "align.complexity",
        "align.min_confidence",
        "align.coarse.enabled",
        "pairs.all_pairs_up_to",
        "pairs.neighbours",
        "pairs.max_per_scan",
        "register_plot.max_distance",
        "register_plot.place_on_als",
        "register_plot.als_anchors",
        "tie_to_als.buffer",
        "tie_to_als.plot_voxel",
        "merge.voxel",
        "merge.include_als",
        "merge.bbox",
        "merge.force",
        "merge.skip_missing",
        "merge.tile_memory_mb",
        "merge.tiles",
        "merge.tile_size",
        "report.picture_points",
        "report.view3d_points",
        "report.view3d_total",
        "report.view3d_max_mb",
        "read.max_points_in_memory",
    }
)
CALIBRATION = "calibration: the method's constants (docs/method.md#calibration-settings)"
Tier = Literal["user", "all"]


class Settings(BaseModel):
    """Every setting of every stage."""

    model_config = ConfigDict(extra="forbid")

    align: AlignConfig = Field(
        default_factory=AlignConfig,
        description="pairwise registration: align, register-plot's pairs and ALS placement, tie",
    )
    posegraph: PoseGraphConfig = Field(
        default_factory=PoseGraphConfig, description="pose-graph solve of register-plot and tie"
    )
    pairs: PairSelection = Field(
        default_factory=PairSelection, description="which pairs register-plot registers"
    )
    register_plot: RegisterConfig = Field(
        default_factory=RegisterConfig, description="register-plot"
    )
    tie_to_als: TieConfig = Field(default_factory=TieConfig, description="tie-to-als")
    merge: MergeConfig = Field(default_factory=MergeConfig, description="merge")
    report: ReportConfig = Field(
        default_factory=ReportConfig, description="report of register-plot and tie-to-als"
    )
    read: ReadingConfig = Field(
        default_factory=ReadingConfig,
        description="reading a scan to register it: the memory budget of align, register-plot, tie",
    )

    def align_config(self) -> AlignConfig:
        return self.align.model_copy(deep=True)

    def register_config(self) -> RegisterConfig:
        pairs = self.pairs.model_copy(deep=True)
        return self.register_plot.model_copy(update={**self._shared(), "pairs": pairs}, deep=True)

    def tie_config(self) -> TieConfig:
        return self.tie_to_als.model_copy(update=self._shared(), deep=True)

    def _shared(self) -> dict:
        """Copies of the sections register-plot and tie-to-als share with the other stages."""
        return {
            "align_settings": self.align.model_copy(deep=True),
            "graph": self.posegraph.model_copy(deep=True),
            "report": self.report.model_copy(deep=True),
            "read": self.read,
        }


class SettingsError(ValueError):
    """A settings file or override that cannot be used; the message names the key."""


# ---- reading ---------------------------------------------------------------------------------------


def _model_of(annotation: Any) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    return None


def _item_models(annotation: Any) -> tuple[int, type[BaseModel]] | None:
    """(depth, model) of list[model] / list[list[model]] fields."""
    depth = 0
    while typing.get_origin(annotation) is list:
        (annotation,) = typing.get_args(annotation)
        depth += 1
    model = _model_of(annotation)
    return (depth, model) if depth and model else None


def _unknown_keys(model: type[BaseModel], data: Any, loc: str) -> str | None:
    """The first key of `data` that `model` does not have (whether or not it forbids extras)."""
    if not isinstance(data, dict):
        return None
    for key, value in data.items():
        where = f"{loc}.{key}" if loc else key
        field = model.model_fields.get(key)
        if field is None or field.exclude:
            return where
        sub = _model_of(field.annotation)
        if sub is not None:
            found = _unknown_keys(sub, value, where)
            if found:
                return found
        items = _item_models(field.annotation)
        if items is not None:
            depth, sub = items
            stack = [(value, where, depth)]
            while stack:
                v, w, d = stack.pop()
                if not isinstance(v, list):
                    continue
                for i, item in enumerate(v):
                    if d > 1:
                        stack.append((item, f"{w}[{i}]", d - 1))
                    else:
                        found = _unknown_keys(sub, item, f"{w}[{i}]")
                        if found:
                            return found
    return None


def _first_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    loc = ".".join(f"[{p}]" if isinstance(p, int) else str(p) for p in err["loc"]).replace(
        ".[", "["
    )
    msg = err["msg"].removeprefix("Value error, ")
    more = len(exc.errors()) - 1
    tail = f" (and {more} more)" if more else ""
    return f"{loc}: {msg}{tail}" if loc else f"{msg}{tail}"


# old key -> its new name (None: read by nothing, dropped): settings files written before still
# load, with a note
RENAMED = {
    "posegraph.min_confidence": "posegraph.sure_edge_confidence",
    "register_plot.placed_priors.min_confidence": (
        "register_plot.placed_priors.sure_placement_confidence"
    ),
    "align.coarse.stem_linearity_z": None,
}


def _table_key(dotted: str) -> str:
    table, _, key = dotted.rpartition(".")
    return f"[{table}] {key}"


def _renamed(data: dict, source: str, note: Callable[[str], None]) -> dict:
    """`data` with every old key under its new name (or left out), one note for each."""
    for old, new in RENAMED.items():
        *path, key = old.split(".")
        table = data
        for part in path:
            table = table.get(part) if isinstance(table, dict) else None
        if not isinstance(table, dict) or key not in table:
            continue
        new_key = None if new is None else new.rpartition(".")[2]
        if new_key in table:
            raise SettingsError(f"{source}: {old}: give only its new name {new}")
        moved = {(new_key if k == key else k): v for k, v in table.items() if new or k != key}
        data = _replaced(data, path, moved)
        if new is None:
            note(f"note: {_table_key(old)} is no longer read: left out")
        else:
            note(f"note: {_table_key(old)} is now {_table_key(new)}")
    return data


def _replaced(data: dict, path: list[str], table: dict) -> dict:
    """A copy of `data` whose table at `path` is `table` (`data` itself untouched)."""
    if not path:
        return table
    return {**data, path[0]: _replaced(data[path[0]], path[1:], table)}


def _stderr(line: str) -> None:
    print(line, file=sys.stderr)


def settings_from_dict(
    data: dict, source: str = "settings", note: Callable[[str], None] = _stderr
) -> Settings:
    """Validated settings; SettingsError naming `source` and the first bad key. A key renamed since
    the file was written is read under its new name, with one `note` line."""
    data = _renamed(data, source, note)
    unknown = _unknown_keys(Settings, data, "")
    if unknown:
        raise SettingsError(f"{source}: {unknown}: unknown setting")
    try:
        return Settings.model_validate(data)
    except ValidationError as exc:
        raise SettingsError(f"{source}: {_first_error(exc)}") from None


def load_settings(path: str | Path) -> Settings:
    """Settings from a TOML file: missing keys take their defaults."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise SettingsError(f"{path}: cannot read: {reason}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SettingsError(f"{path}: not valid TOML: {exc}") from None
    return settings_from_dict(data, str(path))


def _merge(base: dict, update: dict) -> dict:
    out = dict(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def with_overrides(settings: Settings, overrides: dict, source: str = "option") -> Settings:
    """`settings` with nested `overrides` ({"register_plot": {"max_distance": 40.0}}), validated again.

    None values are skipped: an option left unset keeps the file's (or the default) value.
    """

    def drop_none(d: dict) -> dict:
        return {
            k: drop_none(v) if isinstance(v, dict) else v for k, v in d.items() if v is not None
        }

    overrides = drop_none(overrides)
    if not overrides:
        return settings
    return settings_from_dict(_merge(settings.model_dump(), overrides), source)


# ---- writing ---------------------------------------------------------------------------------------

_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def _key(name: str) -> str:
    return name if _BARE_KEY.match(name) else json.dumps(name)


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)  # the shortest text that reads back to the same float
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, BaseModel):
        return _inline(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(str(k))} = {_value(x)}" for k, x in v.items()) + "}"
    if hasattr(v, "value"):  # an Enum
        return _value(v.value)
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _inline(model: BaseModel) -> str:
    parts = [
        f"{_key(k)} = {_value(getattr(model, k))}"
        for k in type(model).model_fields
        if getattr(model, k) is not None
    ]
    return "{" + ", ".join(parts) + "}"


def _comment(text: str | None) -> list[str]:
    return [f"# {line}" for line in (text or "").splitlines() if line.strip()]


def _table(model: BaseModel, name: str, doc: str | None, out: list[str], tier: Tier) -> None:
    """`model`'s keys of `tier` as TOML: a table's user keys first, then its calibration."""
    rows, subs = [], []
    for key, field in type(model).model_fields.items():
        value = getattr(model, key)
        if field.exclude:
            continue
        if isinstance(value, BaseModel):
            subs.append((key, value, field.description))
        else:
            rows.append((key, value, field.description))
    user = [row for row in rows if _dotted(name, row[0]) in USER_KEYS]
    calibration = [r for r in rows if tier == "all" and _dotted(name, r[0]) not in USER_KEYS]
    if name and (user or calibration):
        out.append("")
        out.extend(_comment(doc))
        out.append(f"[{name}]")
    for i, (key, value, description) in enumerate(user + calibration):
        if i == len(user):
            out.append(f"# --- {CALIBRATION}")
        out.extend(_comment(description))
        if value is None:
            out.append(f"# {_key(key)} is unset")
        elif isinstance(value, list) and value and isinstance(value[0], (list, BaseModel)):
            out.append(f"{_key(key)} = [")  # one stage (or schedule) a line
            out.extend(f"    {_value(v)}," for v in value)
            out.append("]")
        else:
            out.append(f"{_key(key)} = {_value(value)}")
    for key, value, description in subs:
        _table(value, f"{name}.{_key(key)}" if name else _key(key), description, out, tier)


def _dotted(table: str, key: str) -> str:
    return f"{table}.{key}" if table else key


def dump_settings(settings: Settings, header: str = "", tier: Tier = "all") -> str:
    """TOML of the settings of `tier` ("all": every key), each preceded by its description."""
    out = _comment(header)
    _table(settings, "", None, out, tier)
    return "\n".join(out).lstrip("\n") + "\n"


def default_toml(tier: Tier = "user") -> str:
    more = {
        "user": "the settings a user turns. `plotmosaic config --all` adds the method's "
        "calibration.",
        "all": "every setting: each table's user keys, then its calibration.",
    }[tier]
    return dump_settings(
        Settings(),
        f"plotmosaic settings at their defaults: {more}\n"
        "Give a file like this to align, register-plot, tie-to-als or merge with --config; keys\n"
        "left out keep their defaults. Jobs, seeds, sensor kinds and levels are command-line\n"
        "options and manifest fields.",
        tier,
    )
