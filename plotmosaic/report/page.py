"""`plotmosaic report`: pictures of a registration and one index.md that ties them together.

Two inputs:
  * a pair: an `align` RESULT.json plus its two clouds -> before/after views, a slice, the levels;
  * a register-plot / tie-to-als output folder (poses.json + graph.json; the scans' paths are
    recorded in graph.json's nodes, or come from --manifest) -> per plot before/after views,
    a slice, the pose graph with edge residuals, the reference scan's levels.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import networkx as nx
import numpy as np

from plotmosaic.align.prepare import prepare_cloud
from plotmosaic.config.align import AlignConfig, default_levels
from plotmosaic.errors import InputError
from plotmosaic.graph.posegraph import graph_from_json
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.frame import apply_transform
from plotmosaic.io.las import PointCloud, read_cloud
from plotmosaic.manifest import load_manifest
from plotmosaic.poses import load_poses
from plotmosaic.report import runs as graph_report
from plotmosaic.report.build import ReportInput, Stage, build_report
from plotmosaic.report.figures import origin_of, plot_levels, plot_slice, subsample
from plotmosaic.report.pictures import plot_scans
from plotmosaic.report.runs import residual_summary
from plotmosaic.report.views import plot_map


@dataclass
class Report:
    index: Path
    figures: list[Path] = field(default_factory=list)
    html: Path | None = None  # the self-contained page (report.html)


def _read(path: Path) -> np.ndarray:
    return read_cloud(path, attributes=False).xyz


def _levels(
    clouds: dict[str, tuple[np.ndarray, str]], seed: int
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The align pipeline's own levels for each (xyz, kind): what ForestAlign actually matches."""
    cfg = AlignConfig()
    out = {}
    for name, (xyz, kind) in clouds.items():
        p = prepare_cloud(PointCloud(xyz), kind, default_levels(kind), cfg, seed, name)
        out[name] = (p.level_points, p.levels)
    return out


def _figure_lines(figures: list[tuple[str, Path]]) -> list[str]:
    lines = []
    for caption, path in figures:
        lines += [f"### {caption}", "", f"![{caption}]({path.name})", ""]
    return lines


# ---------------------------------------------------------------- a pair


def pair_files(result_path: str | Path) -> tuple[Path, Path]:
    """The two clouds an align RESULT.json names ('source_path', 'target_path'; relative to the JSON's folder)."""
    result_path = Path(result_path)
    try:
        data = json.loads(result_path.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        raise InputError(f"{result_path}: not an align result (a JSON file)") from None
    paths = [
        data.get(k) if isinstance(data, dict) else None for k in ("source_path", "target_path")
    ]
    if not all(isinstance(p, str) and p for p in paths):
        raise InputError(
            f"{result_path}: the result does not name its two clouds ('source_path', 'target_path'); "
            "pass --pair RESULT.json SOURCE TARGET"
        )
    return tuple(p if p.is_absolute() else result_path.parent / p for p in map(Path, paths))


def report_pair(
    result_path: str | Path,
    source_path: str | Path,
    target_path: str | Path,
    out: str | Path,
    points: int = 80_000,
    seed: int = 0,
    levels: bool = True,
) -> Report:
    result_path, out = Path(result_path), Path(out)
    if not result_path.is_file():
        raise InputError(f"{result_path}: result file not found")
    try:
        data = json.loads(result_path.read_text())
        T = np.asarray(data["transform"], dtype=np.float64)
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError):
        raise InputError(
            f"{result_path}: not an align result (JSON with a 4x4 'transform')"
        ) from None
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError(f"{result_path}: 'transform' is not a finite 4x4 matrix")
    src, tgt = Path(source_path), Path(target_path)
    rng = np.random.default_rng(seed)
    src_xyz, tgt_xyz = _read(src), _read(tgt)
    s_small, t_small = subsample(src_xyz, points, rng), subsample(tgt_xyz, points, rng)
    names = (f"source {src.stem}", f"target {tgt.stem}")
    before = {names[0]: s_small, names[1]: t_small}
    after = {names[0]: apply_transform(T, s_small), names[1]: t_small}
    origin = origin_of(after)
    figs = [
        (
            "Before: the two clouds as they lie in their files",
            plot_scans(out / "before.png", before, "before alignment", origin_of(before)),
        ),
        (
            "After: the source moved by the estimated transform",
            plot_scans(out / "after.png", after, "after alignment", origin),
        ),
        (
            "After, a 2 m slice: stems and ground should not be doubled",
            plot_slice(out / "after_slice.png", after, "after alignment", origin=origin),
        ),
    ]
    if levels:
        kinds = (data.get("source_kind", "tls"), data.get("target_kind", "tls"))
        lv = _levels({names[0]: (src_xyz, kinds[0]), names[1]: (tgt_xyz, kinds[1])}, seed)
        figs.append(
            (
                "Structural-complexity levels (the align pipeline's grouping)",
                plot_levels(out / "levels.png", lv, "structural-complexity levels", seed=seed),
            )
        )
    facts = [
        f"- source: `{src}`",
        f"- target: `{tgt}`",
        f"- result: `{result_path}`",
        *(
            f"- {k}: {data[k]:.4f}"
            for k in ("fitness", "inlier_rmse", "overlap", "confidence", "seconds")
            if isinstance(data.get(k), (int, float))
        ),
        "",
        "Transform (source file -> target file):",
        "",
        "```",
        *(" ".join(f"{v: .6f}" for v in row) for row in T),
        "```",
        "",
    ]
    if data.get("levels", {}).get("source"):
        facts += [
            "Levels (from the result):",
            "",
            "```",
            json.dumps(data["levels"], indent=1)[:3000],
            "```",
            "",
        ]
    html_path, html_figs = _pair_html(data, T, src, tgt, names, out, seed)
    facts += [
        f"- one page with the breast-height slice and cloud-to-cloud distances: [report.html]({html_path.name})",
        "",
    ]
    figs += [(caption, png) for _, caption, png in html_figs]
    index = write_text_atomic(
        out / "index.md",
        "\n".join(["# Pair registration report", "", *facts, *_figure_lines(figs)]),
    )
    return Report(index, [p for _, p in figs], html_path)


def _pair_html(
    data: dict, T: np.ndarray, src: Path, tgt: Path, names: tuple[str, str], out: Path, seed: int
):
    """report.html of one pair: the source placed by the transform, the target as it is."""
    G = nx.Graph()
    G.add_node(names[0], kind=data.get("source_kind", "tls"))
    G.add_node(names[1], kind=data.get("target_kind", "tls"))
    G.add_edge(
        names[0],
        names[1],
        source=names[0],
        target=names[1],
        transform=T,
        **{k: data.get(k) for k in ("fitness", "inlier_rmse", "overlap", "confidence", "seconds")},
    )
    stages = [
        Stage(k, float(v), "align")
        for k, v in (data.get("timings") or {}).items()
        if isinstance(v, (int, float))
    ]
    if isinstance(data.get("seconds"), (int, float)):
        stages.append(Stage("align, whole pair", float(data["seconds"]), "reading included"))
    facts = [f"source: {src}", f"target: {tgt}"] + [
        f"{k}: {data[k]:.4f}"
        for k in ("fitness", "inlier_rmse", "overlap", "confidence")
        if isinstance(data.get(k), (int, float))
    ]
    inp = ReportInput(
        title=f"pair report: {src.name} -> {tgt.name}",
        out=out,
        graph=G,
        poses={names[0]: T, names[1]: np.eye(4)},
        paths={names[0]: src, names[1]: tgt},
        plots={"pair": list(names)},
        reader=_read,
        stages=stages,
        facts=facts,
    )
    return build_report(inp, seed=seed)


# ---------------------------------------------------------------- a register-plot / tie-to-als folder


def _load_graph(path: Path):
    """graph.json as register-plot wrote it (plotmosaic.graph.posegraph's node-link form)."""
    try:
        return graph_from_json(json.loads(path.read_text()))
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, nx.NetworkXError) as exc:
        raise InputError(
            f"{path}: not a register-plot graph.json ({type(exc).__name__}: {exc}); was it written by another version?"
        ) from None


def _scan_table(directory: Path, manifest_path: str | Path | None):
    """{scan id: (path, kind, plot)} from the manifest if given, else from graph.json's nodes."""
    if manifest_path is not None:
        m = load_manifest(manifest_path)
        return {s.id: (m.resolve(s.path), s.kind.value, m.plot_of(s.id).id) for s in m.scans}, m
    graph = directory / "graph.json"
    if not graph.is_file():
        raise InputError(f"{directory}: no graph.json recording the scans' files; pass --manifest")
    G = _load_graph(graph)
    table = {}
    for n, attrs in G.nodes(data=True):
        if "path" not in attrs and attrs.get("kind") == "als":
            continue  # tie-to-als's ALS node: the frame, not a scan
        if "path" not in attrs:
            raise InputError(f"{graph}: node {n!r} has no 'path'; pass --manifest")
        table[n] = (Path(attrs["path"]), attrs.get("kind", "tls"), attrs.get("plot"))
    return table, None


def report_dir(
    directory: str | Path,
    out: str | Path | None = None,
    manifest: str | Path | None = None,
    points: int = 40_000,
    seed: int = 0,
    levels: bool = True,
) -> Report:

    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(f"{directory}: not a folder")
    out = Path(out) if out else directory / "report"
    poses = load_poses(directory / "poses.json")
    table, _ = _scan_table(directory, manifest)
    G = _load_graph(directory / "graph.json") if (directory / "graph.json").is_file() else None
    for sid, (path, _, _) in table.items():
        if not Path(path).is_file():
            raise InputError(f"{directory}: scan {sid!r}: file not found: {path}")
    plots: dict[str, list[str]] = {}
    for sid, (_, _, plot) in table.items():
        plots.setdefault(
            str(poses.scans[sid].plot if sid in poses.scans and poses.scans[sid].plot else plot), []
        ).append(sid)
    rng = np.random.default_rng(seed)
    lines = [
        "# Registration report",
        "",
        f"- folder: `{directory}`",
        f"- frame: {poses.frame}" + (" (CRS)" if poses.crs else ""),
        "",
    ]
    if (directory / "report.md").is_file():
        rel = os.path.relpath(directory / "report.md", out)
        lines += [f"- the registration's own tables: [report.md]({rel})", ""]
    all_figs: list[Path] = []
    for plot, ids in plots.items():
        raw = {sid: subsample(_read(table[sid][0]), points, rng) for sid in ids}
        placed = {
            sid: apply_transform(poses.scans[sid].transform, xyz)
            for sid, xyz in raw.items()
            if sid in poses.scans
        }
        unplaced = [sid for sid in ids if sid not in poses.scans]
        figs = [
            (
                f"Plot {plot}, before: each scan in its own file coordinates",
                plot_scans(
                    out / f"{plot}_before.png",
                    raw,
                    f"plot {plot}: before (file coordinates)",
                    origin_of(raw),
                ),
            )
        ]
        if placed:
            origin = origin_of(placed)
            figs.append(
                (
                    f"Plot {plot}, after: scans placed by poses.json",
                    plot_scans(
                        out / f"{plot}_after.png",
                        placed,
                        f"plot {plot}: after ({poses.frame} frame)",
                        origin,
                    ),
                )
            )
            figs.append(
                (
                    f"Plot {plot}, after, a 2 m slice",
                    plot_slice(
                        out / f"{plot}_slice.png", placed, f"plot {plot}: after", origin=origin
                    ),
                )
            )
        if G is not None:
            sub = G.subgraph([s for s in ids if s in G])
            T = {sid: poses.scans[sid].transform for sid in ids if sid in poses.scans}
            figs.append(
                (
                    f"Plot {plot}, pose graph (edge label = residual after optimisation)",
                    plot_map(
                        out / f"{plot}_graph.png",
                        sub,
                        {k: v[:3, 3] for k, v in T.items()},
                        None,
                        f"plot {plot}: pose graph",
                        origin_of({k: v[None, :3, 3] for k, v in T.items()}) if T else np.zeros(3),
                    ),
                )
            )
        if levels:
            ref = ids[0]
            path, kind, _ = table[ref]
            lv = _levels({f"{ref} ({kind})": (_read(path), kind)}, seed)
            figs.append(
                (
                    f"Plot {plot}, structural-complexity levels of {ref}",
                    plot_levels(
                        out / f"{plot}_levels.png",
                        lv,
                        f"{ref}: structural-complexity levels",
                        seed=seed,
                    ),
                )
            )
        lines += [
            f"## Plot {plot}",
            "",
            f"Scans: {', '.join(ids)}."
            + (f" Not placed: **{', '.join(unplaced)}**." if unplaced else ""),
            "",
        ]
        if G is not None:
            lines += graph_report.edge_table(G.subgraph(ids)) + [""]
        lines += _figure_lines(figs)
        all_figs += [p for _, p in figs]
    html_path, html_figs = _dir_html(directory, out, poses, table, G, plots, seed)
    lines[2:2] = [
        f"- one page with the breast-height slice, cloud-to-cloud distances and a map: [report.html]({html_path.name})"
    ]
    lines += ["## Breast-height slice, distances, map", ""] + _figure_lines(
        [(c, p) for _, c, p in html_figs]
    )
    all_figs += [p for _, _, p in html_figs]
    index = write_text_atomic(out / "index.md", "\n".join(lines))
    return Report(index, all_figs, html_path)


def _dir_html(
    directory: Path, out: Path, poses, table: dict, G, plots: dict[str, list[str]], seed: int
):

    if G is None:
        G = nx.Graph()
        G.add_nodes_from(table)
    T = {sid: poses.scans[sid].transform for sid in table if sid in poses.scans}
    tables = [
        (f"Plot {p}: edges", graph_report.edge_table(G.subgraph(ids))) for p, ids in plots.items()
    ]
    tables += [
        (
            f"Plot {p}: poses",
            graph_report.pose_table(
                ids, T, {s: poses.scans[s].sigma for s in ids if s in poses.scans}
            ),
        )
        for p, ids in plots.items()
    ]
    inp = ReportInput(
        title=f"registration report: {directory.name}",
        out=out,
        graph=G,
        poses=T,
        paths={sid: Path(v[0]) for sid, v in table.items()},
        plots=plots,
        reader=_read,
        unplaced=[s for ids in plots.values() for s in ids if s not in T],
        tables_md=tables,
        facts=[f"folder: {directory}", f"frame: {poses.frame}"],
        bundle=residual_summary(G),
    )
    return build_report(inp, seed=seed)
