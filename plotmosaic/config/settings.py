"""The settings of a whole run, one TOML file for every stage (a leaf: imports only config modules).

Sections: [align] (pairwise registration, with [align.coarse], [align.judge], [align.stray]: used by
`align`, by register-plot for its pairs and its ALS placement, and by tie-to-als), [posegraph],
[pairs], [register_plot], [tie_to_als], [merge], [report], [read] (how much of a scan registration
holds while reading it). `plotmosaic config --defaults` prints them all; each run writes the settings
it used as config-used.toml beside its outputs, and that file given back with `--config` repeats the
run exactly (floats are written with repr, which reads back bit for bit).
"""

from __future__ import annotations

import json
import math
import re
import tomllib
import typing
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from plotmosaic.config.align import AlignConfig
from plotmosaic.config.merge import MergeConfig
from plotmosaic.config.reading import ReadingConfig
from plotmosaic.config.register import (
    PairSelection,
    PoseGraphConfig,
    RegisterConfig,
    RegisterOptions,
    TieConfig,
    TieOptions,
    graph_align_config,
    placement_align_config,
)
from plotmosaic.config.report import ReportConfig


class RegisterSection(RegisterOptions):
    """register-plot's own settings; its pairwise and pose-graph settings are [align], [posegraph]."""

    pair_min_confidence: float = Field(
        graph_align_config().min_confidence,
        ge=0,
        le=1,
        description="judge floor of register-plot's pairs (replaces align.min_confidence there): "
        "unsure pairs still become edges, a loop must confirm them",
    )
    placement_fpfh: bool = Field(
        placement_align_config().coarse.fpfh,
        description="FPFH starts when placing a scan on the ALS tile (off here or in align.coarse "
        "is off): they run only where the cheaper generators have not settled, and a real UAS "
        "strip onto its ALS found its pose only by them",
    )
    placement_settled_generators: int = Field(
        placement_align_config().coarse.settled_generators,
        ge=1,
        le=3,
        description="generators that must agree before a placement's search stops at the first "
        "vertical pair (replaces align.coarse.settled_generators there): a placement is a prior "
        "the pairs verify again, and one clear pose ahead of its rivals is enough",
    )


class TieSection(TieOptions):
    """tie-to-als's own settings; its pairwise and pose-graph settings are [align], [posegraph]."""

    anchor_fpfh: bool = Field(
        AlignConfig().coarse.fpfh,
        description="FPFH starts when registering a plot to the ALS (off here or in align.coarse "
        "is off): they run only where the cheaper generators have not settled, and a real UAS "
        "strip onto its ALS found its pose only by them",
    )


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
    register_plot: RegisterSection = Field(
        default_factory=RegisterSection, description="register-plot"
    )
    tie_to_als: TieSection = Field(default_factory=TieSection, description="tie-to-als")
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
        own = self.register_plot.model_dump(
            exclude={"pair_min_confidence", "placement_fpfh", "placement_settled_generators"}
        )
        pairwise = self.align.model_copy(
            deep=True, update={"min_confidence": self.register_plot.pair_min_confidence}
        )
        return RegisterConfig(
            **own,
            align=pairwise,
            graph=self.posegraph.model_copy(deep=True),
            pairs=self.pairs.model_copy(deep=True),
            placement=self._onto_als(
                self.register_plot.placement_fpfh,
                settled_generators=self.register_plot.placement_settled_generators,
            ),
            report=self.report.model_copy(deep=True),
            read=self.read,
        )

    def _onto_als(self, fpfh: bool, **search: int) -> AlignConfig:
        """[align] for a TLS cloud onto an ALS tile, with its own FPFH switch (off there, or off in
        [align.coarse], is off) and a placement's own coarse-search settings."""
        config = self.align.model_copy(deep=True)
        fpfh = fpfh and config.coarse.fpfh
        config.coarse = config.coarse.model_copy(update={"fpfh": fpfh, **search})
        return config

    def tie_config(self) -> TieConfig:
        return TieConfig(
            **self.tie_to_als.model_dump(exclude={"anchor_fpfh"}),
            align=self._onto_als(self.tie_to_als.anchor_fpfh),
            graph=self.posegraph.model_copy(deep=True),
            report=self.report.model_copy(deep=True),
            read=self.read,
        )

    def merge_config(self) -> MergeConfig:
        return self.merge


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
        if field is None:
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


def settings_from_dict(data: dict, source: str = "settings") -> Settings:
    """Validated settings; SettingsError naming `source` and the first bad key."""
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


def _table(model: BaseModel, name: str, doc: str | None, out: list[str]) -> None:
    fields = type(model).model_fields
    subs = []
    if name:
        out.append("")
        out.extend(_comment(doc))
        out.append(f"[{name}]")
    for key, field in fields.items():
        value = getattr(model, key)
        if isinstance(value, BaseModel):
            subs.append((key, value, field.description))
            continue
        out.extend(_comment(field.description))
        if value is None:
            out.append(f"# {_key(key)} is unset")
        elif isinstance(value, list) and value and isinstance(value[0], (list, BaseModel)):
            out.append(f"{_key(key)} = [")  # one stage (or schedule) a line
            out.extend(f"    {_value(v)}," for v in value)
            out.append("]")
        else:
            out.append(f"{_key(key)} = {_value(value)}")
    for key, value, description in subs:
        _table(value, f"{name}.{_key(key)}" if name else _key(key), description, out)


def dump_settings(settings: Settings, header: str = "") -> str:
    """TOML of every setting, each preceded by its description as a comment."""
    out = _comment(header)
    _table(settings, "", None, out)
    return "\n".join(out).lstrip("\n") + "\n"


def default_toml() -> str:
    return dump_settings(
        Settings(),
        "plotmosaic settings (the defaults). Give a file like this to align, register-plot,\n"
        "tie-to-als or merge with --config; keys left out keep their defaults.",
    )
