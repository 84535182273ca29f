"""Manifests: a TOML file describing one plot or a region of several plots and ALS tiles.

Two equivalent forms are accepted:

  * one plot:  top-level `[[scans]]` (plus optional `plot_id`, `crs`)
  * a region:  `[[plots]]` each with `id`, optional `crs` and `[[plots.scans]]`

plus optional `[[als]]` tiles in both. Paths are relative to the manifest file.
Errors name the file, plot, scan and field.

A scan may point into an E57 file holding several scans: `path = "plot.e57"` with `scan = 3`
(0-based index) or `scan = "name"` (name or GUID). Loading resolves it to the reference path
`plot.e57#3` (io/e57.py), which every reader takes. `use_pose = true` offers the scan's stored
pose as a prior (`Manifest.stored_poses`), never as the answer. Ids go into file names, so they
are restricted to letters, digits, `-`, `_` and `.` (no `..`).
"""

from __future__ import annotations

import re
import tomllib
from enum import Enum
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pyproj import CRS
from pyproj.exceptions import CRSError

from plotmosaic.config.align import DEFAULT_LEVELS, KINDS, MAX_LEVELS
from plotmosaic.errors import InputError
from plotmosaic.io.e57 import is_e57, list_scans, scan_ref, select_scan, split_scan_ref, stored_pose
from plotmosaic.io.paths import check_input_file, input_problem

_SAFE_ID = re.compile(r"^[\w.-]+$")


def check_id(value: str) -> str:
    """An id that is safe as a file name: letters, digits, `-`, `_`, `.`; not `.`/`..`-like."""
    if not _SAFE_ID.match(value) or ".." in value or value.strip(".") == "":
        raise ValueError(
            f"{value!r} is not allowed: ids become file names, use letters, digits, '-', '_' and '.' (no '..', no '/')"
        )
    return value


def safe_id(text: str) -> str:
    """`text` made into a valid id (other characters become '_')."""
    out = re.sub(r"[^\w.-]", "_", text).replace("..", "_").strip(".")
    return out or "scan"


# the sensor kinds of align/config.py (one list): tls, mls, uls, als
ScanKind = Enum("ScanKind", {k: k for k in KINDS}, type=str)


class _Strict(BaseModel):
    # allow_inf_nan: a NaN position would be silently ignored downstream
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Scan(_Strict):
    id: str = Field(min_length=1)
    path: Path
    kind: ScanKind = ScanKind.tls
    approx_position: tuple[float, float, float] | None = None
    # "crs": easting/northing/height in the plot's CRS; "plot": metres in the plot's own frame
    approx_position_frame: Literal["crs", "plot"] = "plot"
    levels: int | None = Field(default=None, ge=1, le=MAX_LEVELS)
    reference: bool = False
    scan: int | str | None = None  # which scan of an E57 file: 0-based index, or name / GUID
    use_pose: bool = False  # offer the E57's stored pose as the registration's initial guess

    _id = field_validator("id")(classmethod(lambda cls, v: check_id(v)))

    @field_validator("scan")
    @classmethod
    def _scan_selector(cls, value: int | str | None) -> int | str | None:
        if isinstance(value, int) and value < 0:
            raise ValueError("a scan index is 0-based and cannot be negative")
        if isinstance(value, str) and not value:
            raise ValueError("an empty scan name")
        return value

    @property
    def k(self) -> int:
        return self.levels or DEFAULT_LEVELS[self.kind.value]

    @property
    def file(self) -> Path:
        """The file itself (without an E57 reference's `#INDEX`)."""
        return (
            split_scan_ref(self.path)[0]
            if self.path.suffix.lower().startswith(".e57#")
            else self.path
        )


class AlsTile(_Strict):
    path: Path
    levels: int | None = Field(default=None, ge=1, le=MAX_LEVELS)

    @property
    def k(self) -> int:
        return self.levels or DEFAULT_LEVELS["als"]


class Plot(_Strict):
    id: str = Field(min_length=1)
    crs: str | None = None
    scans: list[Scan] = Field(min_length=1)

    _id = field_validator("id")(classmethod(lambda cls, v: check_id(v)))

    @field_validator("crs")
    @classmethod
    def _valid_crs(cls, value: str | None) -> str | None:
        if value is not None:
            try:
                CRS.from_user_input(value)
            except CRSError:
                raise ValueError(f"not a CRS pyproj understands: {value!r}") from None
        return value

    @model_validator(mode="after")
    def _one_reference(self) -> Plot:
        refs = [s.id for s in self.scans if s.reference]
        if len(refs) > 1:
            raise ValueError(f"more than one reference scan: {', '.join(refs)}")
        return self

    @property
    def reference(self) -> Scan:
        return next((s for s in self.scans if s.reference), self.scans[0])


class Manifest(_Strict):
    version: int = 1
    name: str | None = None
    plots: list[Plot] = Field(min_length=1)
    als: list[AlsTile] = Field(default_factory=list)
    source: Path | None = None  # the manifest file; paths are resolved against its folder

    @property
    def root(self) -> Path:
        return self.source.parent if self.source else Path(".")

    def resolve(self, path: Path) -> Path:
        return path if path.is_absolute() else self.root / path

    @property
    def scans(self) -> list[Scan]:
        return [s for p in self.plots for s in p.scans]

    def scan(self, scan_id: str) -> Scan:
        for s in self.scans:
            if s.id == scan_id:
                return s
        raise InputError(f"{self.source}: no scan with id {scan_id!r}")

    def stored_pose(self, scan_id: str) -> np.ndarray | None:
        """The stored pose (4x4, scan -> file frame) of a scan with `use_pose = true`, else None."""
        scan = self.scan(scan_id)
        path = self.resolve(scan.path)
        return stored_pose(path) if scan.use_pose and is_e57(path) else None

    def stored_poses(self) -> dict[str, np.ndarray]:
        """Stored poses (file frame) of the scans with `use_pose = true`, by scan id: what
        graph.pipeline.plan_jobs takes as `placed`. A plot whose stored poses are all identity gives
        none (what many exports write when they know nothing)."""
        out: dict[str, np.ndarray] = {}
        for plot in self.plots:
            poses = {s.id: T for s in plot.scans if (T := self.stored_pose(s.id)) is not None}
            if not all(np.allclose(T, np.eye(4)) for T in poses.values()):
                out.update(poses)
        return out

    def plot_of(self, scan_id: str) -> Plot:
        for p in self.plots:
            if any(s.id == scan_id for s in p.scans):
                return p
        raise InputError(f"{self.source}: no scan with id {scan_id!r}")


def _location(data: dict, loc: tuple) -> str:
    """Readable location of a pydantic error, naming plot and scan ids where possible."""
    parts: list[str] = []
    node = data
    i = 0
    while i < len(loc):
        key = loc[i]
        if key in ("plots", "scans", "als") and i + 1 < len(loc) and isinstance(loc[i + 1], int):
            idx = loc[i + 1]
            item = node.get(key, [])[idx] if isinstance(node, dict) else None
            label = {"plots": "plot", "scans": "scan", "als": "als tile"}[key]
            ident = item.get("id") or item.get("path") if isinstance(item, dict) else None
            parts.append(f"{label} {ident!r}" if ident else f"{label} #{idx + 1}")
            node = item if isinstance(item, dict) else {}
            i += 2
            continue
        parts.append(f"field '{key}'")
        node = node.get(key, {}) if isinstance(node, dict) else {}
        i += 1
    return ", ".join(parts)


def _normalise(data: dict) -> dict:
    """Turn the one-plot form into the region form."""
    if "scans" in data:
        if "plots" in data:
            raise ValueError(
                "give either top-level [[scans]] (one plot) or [[plots]] (a region), not both"
            )
        data = dict(data)
        plot = {"id": data.pop("plot_id", "plot"), "scans": data.pop("scans")}
        if "crs" in data:
            plot["crs"] = data.pop("crs")
        data["plots"] = [plot]
    return data


def load_manifest(path: str | Path, check_files: bool = True) -> Manifest:
    path = Path(path)
    check_input_file(path, "manifest")
    try:  # utf-8-sig: editors on Windows start files with a byte-order mark
        data = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not valid TOML ({exc})") from None
    one_plot = "scans" in data and "plot_id" in data
    try:
        data = _normalise(data)
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None
    try:
        manifest = Manifest.model_validate({**data, "source": path})
    except ValidationError as exc:
        err = exc.errors()[0]
        where = _location(data, tuple(err["loc"]))
        if one_plot and tuple(err["loc"])[:3] == ("plots", 0, "id"):
            where = "field 'plot_id'"
        more = f" (+{exc.error_count() - 1} more problems)" if exc.error_count() > 1 else ""
        raise InputError(f"{path}: {where}: {err['msg']}{more}") from None
    _check_unique(manifest, path)
    if check_files:
        _check_paths(manifest, path)
    return _resolve_e57(manifest, path, check_files)


def _resolve_e57(manifest: Manifest, path: Path, check_files: bool) -> Manifest:
    """E57 scans -> reference paths `FILE.e57#INDEX` (scans chosen by index, name or GUID)."""
    listed: dict[Path, list] = {}
    plots = []
    for plot in manifest.plots:
        scans = []
        for scan in plot.scans:
            where = f"{path}: plot {plot.id!r}, scan {scan.id!r}"
            if scan.path.suffix.lower() != ".e57":
                if scan.scan is not None or scan.use_pose:
                    field = "scan" if scan.scan is not None else "use_pose"
                    raise InputError(
                        f"{where}, field '{field}': only for E57 files, {scan.path} is not one"
                    )
                scans.append(scan)
                continue
            if isinstance(scan.scan, int) and not check_files:
                scans.append(scan.model_copy(update={"path": scan_ref(scan.path, scan.scan)}))
                continue
            if not check_files:
                scans.append(scan)
                continue
            file = manifest.resolve(scan.path)
            try:
                if file not in listed:
                    listed[file] = list_scans(file)
                chosen = select_scan(file, scan.scan, listed[file])
            except InputError as exc:
                raise InputError(f"{where}: {exc}") from None
            scans.append(scan.model_copy(update={"path": scan_ref(scan.path, chosen.index)}))
        plots.append(plot.model_copy(update={"scans": scans}))
    return manifest.model_copy(update={"plots": plots})


def _check_unique(manifest: Manifest, path: Path) -> None:
    seen: dict[str, str] = {}
    for plot in manifest.plots:
        for scan in plot.scans:
            if scan.id in seen:
                raise InputError(
                    f"{path}: plot {plot.id!r}: duplicate scan id {scan.id!r} (also in plot {seen[scan.id]!r})"
                )
            seen[scan.id] = plot.id
    plot_ids = [p.id for p in manifest.plots]
    dupes = sorted({p for p in plot_ids if plot_ids.count(p) > 1})
    if dupes:
        raise InputError(f"{path}: duplicate plot id {dupes[0]!r}")


def _check_paths(manifest: Manifest, path: Path) -> None:
    for plot in manifest.plots:
        for scan in plot.scans:
            problem = input_problem(manifest.resolve(scan.file))
            if problem:
                raise InputError(
                    f"{path}: plot {plot.id!r}, scan {scan.id!r}, field 'path': {problem}: {scan.path}"
                )
    for tile in manifest.als:
        problem = input_problem(manifest.resolve(tile.path))
        if problem:
            raise InputError(f"{path}: als tile, field 'path': {problem}: {tile.path}")


def dump_manifest(manifest: Manifest) -> str:
    """TOML text for a manifest (region form), paths as given."""
    lines = [f"version = {manifest.version}"]
    if manifest.name:
        lines.append(f"name = {_toml(manifest.name)}")
    for tile in manifest.als:
        lines += ["", "[[als]]", f"path = {_toml(tile.path.as_posix())}"]
        if tile.levels:
            lines.append(f"levels = {tile.levels}")
    for plot in manifest.plots:
        lines += ["", "[[plots]]", f"id = {_toml(plot.id)}"]
        if plot.crs:
            lines.append(f"crs = {_toml(plot.crs)}")
        for scan in plot.scans:
            lines += [
                "",
                "[[plots.scans]]",
                f"id = {_toml(scan.id)}",
                f"path = {_toml(scan.file.as_posix())}",
                f'kind = "{scan.kind.value}"',
            ]
            if scan.scan is not None or scan.file != scan.path:
                selector = (
                    scan.scan if scan.scan is not None else int(str(scan.path).rsplit("#", 1)[1])
                )
                lines.append(f"scan = {_toml(selector) if isinstance(selector, str) else selector}")
            if scan.use_pose:
                lines.append("use_pose = true")
            if scan.approx_position is not None:
                lines.append(
                    "approx_position = ["
                    + ", ".join(f"{v:.3f}" for v in scan.approx_position)
                    + "]"
                )
                lines.append(f'approx_position_frame = "{scan.approx_position_frame}"')
            if scan.levels:
                lines.append(f"levels = {scan.levels}")
            if scan.reference:
                lines.append("reference = true")
    return "\n".join(lines) + "\n"


def _toml(value: str) -> str:
    return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
