"""Is a prepared cloud a forest scene at all? Checked by the judge before it weighs any pose.

The judge compares a pose with its rivals; it cannot tell that both clouds are forest. An industrial
pump a few metres across fits a forest scan's stems and ground with its pipes and floor as sharply as
a weak right pair, and a room or a street fits its walls and road. Three figures of the cloud, from
the shape features the levels are made of (independent of the pose and of how the cloud is turned):

* extent: the largest span (2-98 percentile) along the cloud's principal axes. A plot's scan holds
  several trees; a cloud a few metres across holds a machine, an object, at most one stem.
* linear share: share of the level sample whose 2 r neighbourhood is a line (stems, branches,
  twigs). Forests of every sensor have them; rooms, facades and random clouds hardly any.
* crossing planes: share on a plane (planarity at or above the judge's structure limit) turned
  across the cloud's main plane orientation: walls on a floor, facades on a road. Built scenes are
  made of them; a forest's planes are its ground (and a grassland's or a bare ALS tile's too, which
  stay registrable: one orientation, however much of it).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from plotmosaic.align.memo import CloudMemo, PairMemo
from plotmosaic.config.judge import JudgeConfig
from plotmosaic.errors import RegistrationFailed


@dataclass(frozen=True)
class SceneFigures:
    extent_m: float  # largest 2-98 percentile span along the principal axes
    linear_share: float  # level points on a line (linearity >= scene.linearity)
    flat_share: float  # level points on a plane (planarity >= structure_max_planarity)
    crossing_share: float  # of them, those whose normal is across the main plane orientation
    points: int  # level points the figures come from


def figures(cloud, config: JudgeConfig, memo: CloudMemo | None = None) -> SceneFigures:
    """The scene figures of a prepared cloud, kept in `memo` (a scan takes part in several pairs)."""
    key = config.model_dump_json(include={"scene", "structure_max_planarity"})
    return (memo or CloudMemo()).scene.get(key, lambda: _figures(cloud, config))


def _figures(cloud, config: JudgeConfig) -> SceneFigures:
    pts = np.asarray(cloud.level_points, dtype=float)
    f = np.asarray(cloud.features, dtype=float)
    valid = np.isfinite(f[:, :2]).all(axis=1)
    extent = 0.0
    if len(pts) >= 3:
        centred = pts - pts.mean(axis=0)
        _, _, axes = np.linalg.svd(centred[:: max(1, len(pts) // 50_000)], full_matrices=False)
        proj = centred @ axes.T
        lo, hi = np.percentile(proj, [2, 98], axis=0)
        extent = float(np.max(hi - lo))
    n = max(1, int(valid.sum()))
    flat = valid & (np.nan_to_num(f[:, 1]) >= config.structure_max_planarity)
    return SceneFigures(
        extent_m=extent,
        linear_share=float((f[valid, 0] >= config.scene.linearity).sum() / n),
        flat_share=float(flat.sum() / n),
        crossing_share=float(_crossing(np.asarray(cloud.normals)[flat], config).sum() / n),
        points=len(pts),
    )


def _crossing(normals: np.ndarray, config: JudgeConfig) -> np.ndarray:
    """Which plane normals lie across the main orientation (the top axis of their scatter matrix):
    independent of how the cloud is turned."""
    normals = normals[np.isfinite(normals).all(axis=1)]
    if len(normals) < 3:
        return np.zeros(0, dtype=bool)
    main = np.linalg.eigh(normals.T @ normals)[1][:, -1]
    return np.abs(normals @ main) < config.scene.crossing_max_cos


def problems(s: SceneFigures, config: JudgeConfig) -> list[str]:
    """Why the figures are not those of a forest scene (empty: they are)."""
    c = config.scene
    out = []
    if s.extent_m < c.min_extent_m:
        out.append(f"it spans {s.extent_m:.1f} m at most (< {c.min_extent_m} m)")
    if s.linear_share < c.min_linear_share:
        out.append(
            f"{s.linear_share:.3f} of it on lines (< {c.min_linear_share}: no stems or branches)"
        )
    if s.crossing_share > c.max_crossing_share:
        out.append(
            f"{s.crossing_share:.2f} of it on planes across its main planes"
            f" (> {c.max_crossing_share}: walls on floors)"
        )
    return out


def check(src, tgt, config: JudgeConfig, memo: PairMemo | None = None) -> None:
    """Raise RegistrationFailed (exit 3), naming the cloud and its figures, when the source or the
    target is not a forest scene; nothing when the check is off (`scene.enabled`)."""
    if not config.scene.enabled:
        return
    memo = memo or PairMemo()
    found = []
    for role, cloud, held in (("source", src, memo.source), ("target", tgt, memo.target)):
        why = problems(figures(cloud, config, held), config)
        if why:
            found.append(f"the {role} is not a forest scene: " + ", ".join(why))
    if found:
        raise RegistrationFailed("pair cannot be registered: " + "; ".join(found))


def record(cloud, config: JudgeConfig) -> dict:
    """The figures as a plain dict (benchmarks, reports)."""
    return asdict(figures(cloud, config))
