"""ForestAlign pairwise registration (paper Algorithm 1) from two clouds or two files.

prepare (voxel, normals, levels) -> register (align/pair.py: search, level stage, final ICP,
judge, quality, floors).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from plotmosaic.align.figures import save_levels as write_levels
from plotmosaic.align.kinds import KindDetection, detect_kind
from plotmosaic.align.pair import register_prepared
from plotmosaic.align.prepare import (
    MIN_POINTS,
    PreparedCloud,
    RobustPoints,
    prepare_cloud,
    robust_points,
)
from plotmosaic.align.result import PairResult
from plotmosaic.config.align import KINDS, AlignConfig, default_levels
from plotmosaic.config.reading import ReadingConfig
from plotmosaic.errors import InputError
from plotmosaic.io.bounded import read_scan_points
from plotmosaic.io.las import PointCloud
from plotmosaic.parallel import both

__all__ = ["AlignRequest", "align_clouds", "align_files", "pair_kinds", "prepare_pair"]


def _kind(kind: str, which: str) -> str:
    k = str(kind).lower()
    if k not in KINDS:
        raise InputError(f"{which} kind {kind!r} not one of {', '.join(KINDS)}")
    return k


def pair_kinds(
    source: np.ndarray,
    target: np.ndarray,
    source_kind: str | None,
    target_kind: str | None,
    config: AlignConfig,
    seed: int = 0,
) -> tuple[str, str, dict[str, KindDetection]]:
    """Both kinds: a given kind stands, a missing one (None) is detected from its points (stray
    points already dropped: one far point would widen the cloud it is judged on)."""
    detected = {
        role: detect_kind(xyz, config.kinds, config.viewpoint, seed)
        for role, xyz, kind in (("source", source, source_kind), ("target", target, target_kind))
        if kind is None
    }
    sk = detected["source"].kind if source_kind is None else _kind(source_kind, "source")
    tk = detected["target"].kind if target_kind is None else _kind(target_kind, "target")
    return sk, tk, detected


def _robust(cloud: PointCloud, config: AlignConfig, name: str) -> RobustPoints | None:
    """The points without stray ones, made once for the kinds and the preparation; None for a cloud
    too small to register (prepare_cloud names it)."""
    if len(cloud) < MIN_POINTS:
        return None
    return robust_points(cloud.xyz, config.stray, name)


def prepare_pair(
    source: PointCloud,
    target: PointCloud,
    kinds: tuple[str, str],
    levels: tuple[int, int],
    config: AlignConfig,
    seed: int = 0,
    robust: tuple[RobustPoints | None, RobustPoints | None] = (None, None),
) -> tuple[PreparedCloud, PreparedCloud]:
    """Both clouds prepared at once (source with `seed`, target with `seed + 1`); `kinds`, `levels`
    and `robust` are (source's, target's), `robust` their points without stray ones where the
    caller made them already."""
    return both(
        lambda job: prepare_cloud(*job[:-1], robust=job[-1]),
        (source, kinds[0], levels[0], config, seed, "source", robust[0]),
        (target, kinds[1], levels[1], config, seed + 1, "target", robust[1]),
    )


@dataclass(frozen=True, kw_only=True, eq=False)
class AlignRequest:
    """What a pair's registration is asked for, the clouds aside."""

    source_kind: str | None = None  # None: detected from its points (align/kinds.py)
    target_kind: str | None = None
    config: AlignConfig = field(default_factory=AlignConfig)
    init: np.ndarray | None = (
        None  # source file -> target file: the coarse stage's prior, or the start
    )
    levels_source: int | None = None  # None: default_levels of its kind
    levels_target: int | None = None
    seed: int = 0
    save_levels: Path | None = (
        None  # a folder for the levels as LAZ + PNG (before ICP: also on failure)
    )
    reading: ReadingConfig = field(default_factory=ReadingConfig)  # files: the memory budget


def align_clouds(
    source: PointCloud,
    target: PointCloud,
    request: AlignRequest | None = None,
    progress: Callable[[str], None] | None = None,
) -> PairResult:
    """Register `source` onto `target` as `request` asks; the result maps source file coordinates
    to target file coordinates."""
    return _align(source, target, request or AlignRequest(), progress, None)


def align_files(
    source_path,
    target_path,
    request: AlignRequest | None = None,
    progress: Callable[[str], None] | None = None,
) -> PairResult:
    """`align_clouds` on two point-cloud files (coordinates only, within the reading budget)."""
    request = request or AlignRequest()
    t0 = time.perf_counter()
    (progress or _silent)("reading source and target")
    source, target = both(
        lambda path: read_scan_points(path, request.reading, request.config),
        source_path,
        target_path,
    )
    paths = (str(Path(source_path).resolve()), str(Path(target_path).resolve()))
    files = _Files(start=t0, read=time.perf_counter() - t0, paths=paths)
    return _align(source, target, request, progress, files)


@dataclass(frozen=True, kw_only=True, eq=False)
class _Files:
    """What align_files did before the clouds: when it started, the reading's seconds, the files."""

    start: float  # time.perf_counter()
    read: float
    paths: tuple[str, str]  # source, target, resolved


def _align(
    source: PointCloud,
    target: PointCloud,
    request: AlignRequest,
    progress: Callable[[str], None] | None,
    files: _Files | None,
) -> PairResult:
    """The registration of two clouds, its result built whole: the pair function's steps after
    the reading (`files`, when from files), the kinds and the preparation."""
    config, seed = request.config, request.seed
    t0 = time.perf_counter()
    say = progress or _silent
    # the points as registration sees them (stray points dropped): the source's bounding box, the
    # kinds and the preparation
    robust = _robust(source, config, "source"), _robust(target, config, "target")
    source_kind, target_kind = request.source_kind, request.target_kind
    if source_kind is None or target_kind is None:
        say("detecting sensor kinds")
    sk, tk, detected = pair_kinds(
        *(cloud.xyz if r is None else r.xyz for cloud, r in zip((source, target), robust)),
        source_kind,
        target_kind,
        config,
        seed,
    )
    t_kinds = time.perf_counter() - t0
    say("preparing source and target")
    levels = (
        request.levels_source or default_levels(sk),
        request.levels_target or default_levels(tk),
    )
    src, tgt = prepare_pair(source, target, (sk, tk), levels, config, seed, robust)
    if request.save_levels is not None:
        say("saving levels")
        write_levels(request.save_levels, src, tgt, source.crs, target.crs)
    t1 = time.perf_counter()
    result = register_prepared(src, tgt, config, request.init, seed, progress)
    centre = None if robust[0] is None else [float(v) for v in robust[0].bounds.mean(axis=1)]
    return replace(
        result,
        timings={
            **({} if files is None else {"read": files.read}),
            "kinds": t_kinds,  # the source's bounds, and the kinds not given
            "prepare": t1 - t0 - t_kinds,
            "prepare_source": src.seconds,
            "prepare_target": tgt.seconds,
            **result.timings,
        },
        source_centre=centre,
        detected_kinds={role: d.to_dict() for role, d in detected.items()},
        seconds=time.perf_counter() - (t0 if files is None else files.start),
        source_path=None if files is None else files.paths[0],
        target_path=None if files is None else files.paths[1],
    )


def _silent(msg: str) -> None:
    pass
