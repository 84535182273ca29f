"""The report of a register-plot / tie-to-als run: written by the run, or re-rendered in place from
the folder it wrote (`plotmosaic report DIR`): poses.json, graph.json, and for tie-to-als the ALS
crops under plots/. The run's own settings (config-used.toml) are used when the folder has them."""

from __future__ import annotations

import json
from pathlib import Path

import networkx as nx
import numpy as np

from plotmosaic.config.settings import Settings, SettingsError, load_settings
from plotmosaic.errors import InputError
from plotmosaic.graph.posegraph import graph_from_json
from plotmosaic.graph.prepared import points_reader
from plotmosaic.io.las import read_cloud
from plotmosaic.manifest import load_manifest
from plotmosaic.poses import Poses, load_poses
from plotmosaic.report.register_page import (
    PlotRun,
    RegisterRun,
    render_register,
    write_register_report,
)
from plotmosaic.report.tie_page import (
    TieRun,
    als_near,
    anchor_row,
    render_tie,
    rigid_plots,
    write_tie_report,
)

__all__ = ["rerender", "rigid_plots", "write_register_report", "write_tie_report"]

CONFIG_USED = "config-used.toml"  # what commands/common.py writes beside a run's outputs


def load_graph(path: Path) -> nx.Graph:
    """graph.json as a run wrote it (the pose-graph module's node-link form)."""
    try:
        return graph_from_json(json.loads(path.read_text()))
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, nx.NetworkXError) as exc:
        raise InputError(
            f"{path}: not a register-plot graph.json ({type(exc).__name__}: {exc}); was it written by another version?"
        ) from None


def _settings(directory: Path) -> Settings:
    path = directory / CONFIG_USED
    try:
        return load_settings(path) if path.is_file() else Settings()
    except SettingsError as exc:
        raise InputError(str(exc)) from None


def _scans(directory: Path, G: nx.Graph, poses: Poses, manifest: Path | None):
    """({scan: file}, {plot: [scans]}, manifest or folder name): the manifest if given, else the
    paths and plots graph.json's nodes record."""
    if manifest is not None:
        m = load_manifest(manifest)
        paths = {s.id: m.resolve(s.path) for s in m.scans}
        return paths, {p.id: [s.id for s in p.scans] for p in m.plots}, f"manifest: {m.source}"
    paths, plots = {}, {}
    for n, attrs in G.nodes(data=True):
        if attrs.get("kind") == "als" and "path" not in attrs:
            continue  # tie-to-als's ALS node: the frame, not a scan
        if "path" not in attrs:
            raise InputError(
                f"{directory / 'graph.json'}: node {n!r} has no 'path'; pass --manifest"
            )
        paths[n] = Path(attrs["path"])
        plot = (
            poses.scans[n].plot if n in poses.scans and poses.scans[n].plot else attrs.get("plot")
        )
        plots.setdefault(str(plot), []).append(n)
    return paths, plots, f"folder: {directory} (the scans graph.json records)"


def _reader(directory: Path, poses: Poses, paths: dict[str, Path], settings: Settings):
    """The scans' prepared clouds a register-plot folder keeps (as the run read them), else their
    files within the run's reading budget."""
    recorded_ = poses.extra.get("prepared") or {}
    entries = {
        str(paths[sid]): directory / "prepared" / Path(name).name
        for sid, name in recorded_.items()
        if sid in paths and (directory / "prepared" / Path(name).name).is_file()
    }
    return points_reader(entries, settings.read, settings.align)


def _register_run(directory: Path, G, poses: Poses, paths, plots, source) -> RegisterRun:
    extra = poses.extra.get("plots") or {}
    runs = []
    for plot, ids in plots.items():
        own = extra.get(plot, {})
        placed = {s: poses.scans[s].transform for s in ids if s in poses.scans}
        sigmas = {s: poses.scans[s].sigma for s in placed if poses.scans[s].sigma is not None}
        runs.append(
            PlotRun(
                plot=plot,
                reference=own.get("reference") or ids[0],
                scans=tuple(ids),
                poses=placed,
                sigmas=sigmas,
                dropped=tuple(own.get("dropped") or ()),
                unplaced=tuple(s for s in ids if s not in placed),
            )
        )
    failed = tuple(G.graph.get("failed") or ())
    return RegisterRun(
        out=directory, graph=G, plots=tuple(runs), paths=paths, source=source, failed=failed
    )


def _als(directory: Path, plots: dict[str, list[str]]) -> np.ndarray | None:
    """The ALS crops tie-to-als wrote beside its plot clouds (plots/<plot>_als.laz)."""
    crops = [directory / "plots" / f"{p}_als.laz" for p in plots]
    xyz = [read_cloud(c, attributes=False).xyz for c in crops if c.is_file()]
    return np.vstack(xyz) if xyz else None


def _tie_run(directory: Path, G, poses: Poses, paths, plots, source, margin: float) -> TieRun:
    anchors = poses.extra.get("anchors") or {}
    rows = tuple(anchor_row({**a, "plot": p}) for p, a in anchors.items())
    T = {s: sp.transform for s, sp in poses.scans.items()}
    als = _als(directory, plots)
    return TieRun(
        out=directory,
        graph=G,
        anchors=rows,
        poses=T,
        sigmas={s: sp.sigma for s, sp in poses.scans.items()},
        plots=plots,
        paths=paths,
        offset=np.asarray(poses.extra.get("offset") or [0.0, 0.0, 0.0], float),
        als_xyz=None if als is None else als_near(als, T, margin),
        source=source,
        unplaced=tuple(poses.extra.get("unplaced") or ()),
    )


def rerender(directory: str | Path, manifest: str | Path | None = None, seed: int = 0) -> Path:
    """A run's report.md and report.html (and view3d.html) written again in its folder; returns report.md."""
    directory = Path(directory)
    for name in ("poses.json", "graph.json"):
        if not (directory / name).is_file():
            raise InputError(f"{directory}: no {name}: not a register-plot / tie-to-als folder")
    poses = load_poses(directory / "poses.json")
    G = load_graph(directory / "graph.json")
    paths, plots, source = _scans(directory, G, poses, None if manifest is None else Path(manifest))
    for sid in (s for ids in plots.values() for s in ids):
        if sid in poses.scans and not Path(paths[sid]).is_file():
            raise InputError(f"{directory}: scan {sid!r}: file not found: {paths[sid]}")
    settings = _settings(directory)
    min_conf = settings.posegraph.sure_edge_confidence
    if poses.frame == "crs":
        run = _tie_run(directory, G, poses, paths, plots, source, settings.report.als_margin)
        return render_tie(
            run, settings.report, min_conf, seed, points_reader({}, settings.read, settings.align)
        )
    run = _register_run(directory, G, poses, paths, plots, source)
    return render_register(
        run, settings.report, min_conf, seed, _reader(directory, poses, paths, settings)
    )
