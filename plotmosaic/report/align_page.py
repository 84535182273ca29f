"""The report of one `align` run (report.md and report.html beside it): the transform in words a
user reads (rotation angle, motion of the source's centre, the matrix and its direction), the
clouds before and after, a slice, the cloud-to-cloud distances and the levels."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import networkx as nx
import numpy as np

from plotmosaic.align.prepare import prepare_cloud
from plotmosaic.config.align import AlignConfig, default_levels
from plotmosaic.config.report import ReportConfig
from plotmosaic.errors import InputError
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.frame import apply_transform
from plotmosaic.io.las import PointCloud
from plotmosaic.report import html as H
from plotmosaic.report.build import build_report
from plotmosaic.report.collect import read_scan
from plotmosaic.report.figures import origin_of, plot_levels, plot_slice, subsample
from plotmosaic.report.model import Figure, ReportInput, Stage
from plotmosaic.report.pictures import plot_scans
from plotmosaic.report.tables import md_figures

QUALITY = ("fitness", "inlier_rmse", "overlap", "confidence")
NOT_SECONDS = ("_deg", "_m", "iterations")  # older results kept measures among their timings


@dataclass(frozen=True, kw_only=True)
class Motion:
    """What a 4x4 does to the source, in a user's words."""

    angle_deg: float  # rotation angle about `axis`
    axis: np.ndarray
    centre: np.ndarray  # the source's bounding-box centre (source file coordinates)
    moves: np.ndarray  # where that centre goes minus where it was (m)


def source_centre(data: dict, source_xyz: np.ndarray) -> np.ndarray:
    """The centre `align` measured the motion at (stray points left out), else the points' box centre
    (a result written before RESULT.json carried it)."""
    if data.get("source_centre") is not None:
        return np.asarray(data["source_centre"], dtype=float)
    return (source_xyz.min(axis=0) + source_xyz.max(axis=0)) / 2


def motion_of(T: np.ndarray, centre: np.ndarray) -> Motion:
    R = T[:3, :3]
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    axis = w / np.linalg.norm(w) if np.linalg.norm(w) > 1e-12 else np.array([0.0, 0.0, 1.0])
    return Motion(angle_deg=angle, axis=axis, centre=centre, moves=R @ centre + T[:3, 3] - centre)


def transform_lines(T: np.ndarray, m: Motion) -> list[str]:
    dx, dy, dz = m.moves
    ax, ay, az = m.axis
    return [
        f"rotation: {m.angle_deg:.4f} deg about the axis ({ax:+.3f}, {ay:+.3f}, {az:+.3f})",
        f"the source's centre moves by ({dx:+.4f}, {dy:+.4f}, {dz:+.4f}) m, "
        f"{np.linalg.norm(m.moves):.4f} m in all",
        "the 4x4 maps a point of the source file to the target file: p_target = T p_source "
        "(CloudCompare's convention: apply it to the source)",
    ]


def _transform_block(T: np.ndarray, m: Motion) -> str:
    matrix = "\n".join(" ".join(f"{v: .9f}" for v in row) for row in T)
    return H.bullets(transform_lines(T, m)) + f"<pre>{H.esc(matrix)}</pre>"


def read_result(result_path: Path) -> tuple[dict, np.ndarray]:
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
    return data, T


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


def _stages(data: dict) -> tuple[Stage, ...]:
    timings = data.get("timings") or {}
    stages = [
        Stage(k, float(v), "align")
        for k, v in timings.items()
        if isinstance(v, (int, float)) and not k.endswith(NOT_SECONDS)
    ]
    if isinstance(data.get("seconds"), (int, float)):
        stages.append(Stage("align, whole pair", float(data["seconds"]), "reading included"))
    return tuple(stages)


def _pictures(data, T, clouds, names, out, points, seed, levels) -> list[Figure]:
    src_xyz, tgt_xyz = clouds
    rng = np.random.default_rng(seed)
    s_small, t_small = subsample(src_xyz, points, rng), subsample(tgt_xyz, points, rng)
    before = {names[0]: s_small, names[1]: t_small}
    after = {names[0]: apply_transform(T, s_small), names[1]: t_small}
    origin = origin_of(after)
    figs = [
        Figure(
            plot="",
            caption="Before: the two clouds as they lie in their files",
            png=plot_scans(out / "before.png", before, "before alignment", origin_of(before)),
            read="Where the clouds start: far apart or turned when the files share no frame.",
        ),
        Figure(
            plot="",
            caption="After: the source moved by the estimated transform",
            png=plot_scans(out / "after.png", after, "after alignment", origin),
            read="The two colours should cover the same ground, stems and crowns.",
        ),
        Figure(
            plot="",
            caption="After, a 2 m slice: stems and ground should not be doubled",
            png=plot_slice(out / "after_slice.png", after, "after alignment", origin=origin),
            read="One ground line and single stems mean aligned; two parallel lines are an offset.",
        ),
    ]
    if levels:
        kinds = (data.get("source_kind", "tls"), data.get("target_kind", "tls"))
        cfg = AlignConfig()
        lv = {}
        for name, xyz, kind in ((names[0], src_xyz, kinds[0]), (names[1], tgt_xyz, kinds[1])):
            p = prepare_cloud(PointCloud(xyz), kind, default_levels(kind), cfg, seed, name)
            lv[name] = (p.level_points, p.levels)
        figs.append(
            Figure(
                plot="",
                caption="Structural-complexity levels (the align pipeline's grouping)",
                png=plot_levels(out / "levels.png", lv, "structural-complexity levels", seed=seed),
                read="The levels the pipeline matched: ground, stems and foliage should fall apart.",
            )
        )
    return figs


def report_pair(
    result_path: str | Path,
    source_path: str | Path,
    target_path: str | Path,
    out: str | Path,
    points: int = 80_000,
    seed: int = 0,
    levels: bool = True,
    cfg: ReportConfig | None = None,
) -> Path:
    """report.md and report.html of one align result in `out`; returns report.md."""
    result_path, out = Path(result_path), Path(out)
    data, T = read_result(result_path)
    src, tgt = Path(source_path), Path(target_path)
    src_xyz, tgt_xyz = read_scan(src), read_scan(tgt)
    names = (f"source {src.stem}", f"target {tgt.stem}")
    motion = motion_of(T, source_centre(data, src_xyz))
    figs = _pictures(data, T, (src_xyz, tgt_xyz), names, out, points, seed, levels)
    G = nx.Graph()
    G.add_node(names[0], kind=data.get("source_kind", "tls"))
    G.add_node(names[1], kind=data.get("target_kind", "tls"))
    quality = {k: data[k] for k in QUALITY if isinstance(data.get(k), (int, float))}
    G.add_edge(names[0], names[1], source=names[0], target=names[1], transform=T, **quality)
    facts = (
        f"source: {src}",
        f"target: {tgt}",
        f"result: {result_path}",
        *(f"{k}: {v:.4f}" for k, v in quality.items()),
    )
    clouds = {str(src): src_xyz, str(tgt): tgt_xyz}
    inp = ReportInput(
        title=f"pair report: {src.name} -> {tgt.name}",
        out=out,
        graph=G,
        poses={names[0]: T, names[1]: np.eye(4)},
        paths={names[0]: src, names[1]: tgt},
        plots={"pair": list(names)},
        reader=lambda p: clouds[str(p)],  # both clouds are in memory already
        stages=_stages(data),
        facts=facts,
        blocks=(("Transform", _transform_block(T, motion)),),
        figures=tuple(figs),
    )
    _, all_figs = build_report(inp, cfg, seed)
    matrix = [" ".join(f"{v: .9f}" for v in row) for row in T]
    lines = [
        "# Pair registration report",
        "",
        *(f"- {f}" for f in facts),
        "",
        "One page with the same pictures and tables: [report.html](report.html)",
        "",
        "## Transform",
        "",
        *(f"- {line}" for line in transform_lines(T, motion)),
        "",
        "```",
        *matrix,
        "```",
        "",
        "## Pictures",
        "",
        *md_figures(all_figs),
    ]
    return write_text_atomic(out / "report.md", "\n".join(lines))
