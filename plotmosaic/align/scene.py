"""Is a prepared cloud a forest scene at all? Checked by the judge before it weighs any pose.

The judge compares a pose with its rivals; it cannot tell that both clouds are forest. An industrial
pump a few metres across fits a forest scan's stems and ground with its pipes and floor as sharply as
a weak right pair, and a room or a street fits its walls and road. The figures come from the level
sample's shape features and normals, measured from the cloud's own ground (independent of the pose,
of how the cloud is turned and of where its ground lies):

* extent: the largest span (2-98 percentile) along the cloud's principal axes. A plot's scan holds
  several trees; a cloud a few metres across holds a machine, an object, at most one stem.
* what stands on the ground, the forest itself. The cloud is levelled by its own up (the direction
  its ground normals and upright stem surfaces agree on) and given heights above a rough ground
  model. Stems: upright, narrow columns of line or surface points 0.5-3.5 m above the ground (the
  trunks a ground-based scan sees, leaning or not, however much foliage or ground fills the rest).
  Above-ground lines: the share of what stands above the ground that lies on lines (branches,
  twigs, grass blades: what airborne clouds, grassland and short views hold where trunks are few);
  they count where they stand on something: a ground seen under them (a random cloud's lowest
  points lie on no surface), or lines that chain into branches (a clip without its ground; a sparse
  random cloud's chance lines stand alone). A forest scene has stems or such lines; a random cloud,
  a bare plane or a room has neither. Both are counted among above-ground points only, so scattered
  foliage or a scan that sees mostly ground does not dilute them.
* crossing planes: share on a plane (planarity at or above the judge's structure limit) turned
  across the cloud's main plane orientation: walls on a floor, facades on a road. Built scenes are
  made of them; a forest's planes are its ground (and a grassland's or a bare ALS tile's too, which
  stay registrable: one orientation, however much of it).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.align.levelling import fibonacci_hemisphere, rotation_between
from plotmosaic.align.memo import CloudMemo, PairMemo
from plotmosaic.align.rasters import height_above_ground
from plotmosaic.align.voxel import occupied_groups
from plotmosaic.config.coarse import CoarseConfig
from plotmosaic.config.judge import JudgeConfig, SceneConfig
from plotmosaic.errors import RegistrationFailed

Z = np.array([0.0, 0.0, 1.0])
# the up vote: directions tried (axial, every tilt: the cloud may be turned any way), normals it
# looks at (a fixed stride of the flat and line points), and its bands; the vote lands within a
# few degrees, the ground normals refine it
UP_CANDIDATES = 300
UP_MAX_NORMALS = 8_000
GROUND_BAND_COS = np.cos(np.radians(15.0))  # a ground normal: within 15 deg of up
UPRIGHT_BAND_SIN = np.sin(np.radians(10.0))  # a stem normal: within 10 deg of horizontal
UPRIGHT_WEIGHT = 0.5  # stems' vote beside the ground's (levelling's balance)
MIN_GROUND_NORMALS = 0.05  # share of the normals looked at: fewer, and the stems refine up


@dataclass(frozen=True)
class SceneFigures:
    extent_m: float  # largest 2-98 percentile span along the principal axes
    stems: int  # upright narrow columns in the stem band above the ground (trunks)
    above_linear_share: float  # of the level points above the ground, those on a line
    above_share: float  # level points more than `above_ground_m` above the ground
    ground_share: float  # level points on the ground: below that, on a plane facing up
    branch_share: float  # of the above-ground points, those on a line with line neighbours
    flat_share: float  # level points on a plane (planarity >= structure_max_planarity)
    crossing_share: float  # of them, those whose normal is across the main plane orientation
    points: int  # level points the figures come from


def figures(cloud, config: JudgeConfig, memo: CloudMemo | None = None) -> SceneFigures:
    """The scene figures of a prepared cloud, kept in `memo` (a scan takes part in several pairs)."""
    key = config.model_dump_json(include={"scene", "structure_max_planarity"})
    return (memo or CloudMemo()).scene.get(key, lambda: _figures(cloud, config))


def _figures(cloud, config: JudgeConfig) -> SceneFigures:
    c = config.scene
    pts = np.asarray(cloud.level_points, dtype=float)
    f = np.asarray(cloud.features, dtype=float)
    normals = np.asarray(cloud.normals, dtype=float)
    valid = np.isfinite(f[:, :2]).all(axis=1) & np.isfinite(normals).all(axis=1)
    extent = 0.0
    if len(pts) >= 3:
        centred = pts - pts.mean(axis=0)
        _, _, axes = np.linalg.svd(centred[:: max(1, len(pts) // 50_000)], full_matrices=False)
        proj = centred @ axes.T
        lo, hi = np.percentile(proj, [2, 98], axis=0)
        extent = float(np.max(hi - lo))
    n = max(1, int(valid.sum()))
    flat = valid & (np.nan_to_num(f[:, 1]) >= config.structure_max_planarity)
    line = valid & (np.nan_to_num(f[:, 0]) >= c.linearity)
    stems, above, ground = 0, np.zeros(len(pts), dtype=bool), np.zeros(len(pts), dtype=bool)
    branches = 0
    if valid.sum() >= 3:
        up = _up(pts, normals, flat, line, valid)
        R = rotation_between(up, Z)
        levelled, facing = pts @ R.T, np.abs(normals @ up)
        upright = facing < c.stem_max_normal_cos
        hag = height_above_ground(levelled, c.ground_cell, CoarseConfig())
        above = valid & (hag >= c.above_ground_m)
        ground = flat & ~above & (facing > GROUND_BAND_COS)
        lo_m, hi_m = c.stem_band_m
        band = valid & (line | flat) & upright & (hag >= lo_m) & (hag <= hi_m)
        stems = _stems(levelled[band], c)
        branches = _chained(pts[line & above], c)
    return SceneFigures(
        extent_m=extent,
        stems=stems,
        above_linear_share=float((line & above).sum() / max(1, int(above.sum()))),
        above_share=float(above.sum() / n),
        ground_share=float(ground.sum() / n),
        branch_share=float(branches / max(1, int(above.sum()))),
        flat_share=float(flat.sum() / n),
        crossing_share=float(_crossing(normals[flat], config).sum() / n),
        points=len(pts),
    )


def _up(
    pts: np.ndarray, normals: np.ndarray, flat: np.ndarray, line: np.ndarray, valid: np.ndarray
) -> np.ndarray:
    """The cloud's up: the axis most normals of its flat and line points lie along (ground) or
    across (stems), refined on the ground normals; pointing away from the ground (the side the
    rest of the cloud stands on), the file's +z side when no ground is seen."""
    pick = np.flatnonzero(flat | line)
    if len(pick) < 3:
        pick = np.flatnonzero(valid)
    nn = normals[pick[:: max(1, len(pick) // UP_MAX_NORMALS)]]
    cands = fibonacci_hemisphere(UP_CANDIDATES)
    dots = np.abs(nn.astype(np.float32) @ cands.T.astype(np.float32))
    votes = (dots > GROUND_BAND_COS).mean(axis=0) + UPRIGHT_WEIGHT * (dots < UPRIGHT_BAND_SIN).mean(
        axis=0
    )
    up = cands[int(np.argmax(votes))]
    # refined on the ground's normals (their mean axis), or where little ground is seen (a clip
    # without its ground) on the stems' (the axis they lie across)
    ground = nn[np.abs(nn @ up) > GROUND_BAND_COS]
    upright = nn[np.abs(nn @ up) < UPRIGHT_BAND_SIN]
    if len(ground) >= max(3, MIN_GROUND_NORMALS * len(nn)):
        axis = np.linalg.eigh(ground.T @ ground)[1][:, -1]
    elif len(upright) >= 3:
        axis = np.linalg.eigh(upright.T @ upright)[1][:, 0]
    else:
        axis = up
    up = axis if axis @ up >= 0 else -axis
    # which way is up: the ground lies below what stands on it
    h = pts @ up
    on_ground = flat & (np.abs(normals @ up) > GROUND_BAND_COS)
    rest = valid & ~on_ground
    if on_ground.sum() >= 50 and rest.sum() >= 50:
        return up if np.median(h[on_ground]) <= np.median(h[rest]) else -up
    return up if up[2] >= 0 else -up


def _stems(band: np.ndarray, c: SceneConfig) -> int:
    """Trunks among the upright points of the stem band (levelled): groups of `stem_cell` squares
    that stand through the band (main axis near up, long), narrow as a trunk. A random cloud's
    chance columns are as wide as the grouping lets them grow."""
    found = 0
    for idx in occupied_groups(band[:, :2], c.stem_cell) if len(band) else []:
        if len(idx) < c.stem_min_points:
            continue
        p = band[idx]
        w, V = np.linalg.eigh(np.cov(p.T))
        axis = V[:, -1]
        if abs(axis[2]) < np.cos(np.radians(c.stem_max_lean_deg)):
            continue
        width = 4.0 * np.sqrt(max(float(w[-2]), 0.0))
        if np.ptp(p @ axis) >= c.stem_min_span_m and width <= c.stem_max_width_m:
            found += 1
    return found


def _chained(line_points: np.ndarray, c: SceneConfig) -> int:
    """How many line points have `branch_neighbours` other line points within `branch_radius_m`:
    branches and stems are chains of line points; a sparse random cloud's chance lines stand alone."""
    if len(line_points) <= c.branch_neighbours:
        return 0
    tree = cKDTree(line_points)
    near = tree.query_ball_point(line_points, c.branch_radius_m, return_length=True) - 1
    return int((near >= c.branch_neighbours).sum())


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
    if not decided_by(s, config):
        lines = (
            f"{s.above_linear_share:.3f} of what stands above its ground on lines"
            f" (< {c.min_above_linear_share})"
            if _stands(s, c)
            else f"no ground seen ({s.ground_share:.3f} of it, < {c.min_ground_share}) under"
            f" its lines, nor branches ({s.branch_share:.3f}, < {c.min_branch_share})"
        )
        out.append(
            f"nothing stands on a ground as trees do: {s.stems} stems (< {c.min_stems}), {lines}"
        )
    if s.crossing_share > c.max_crossing_share:
        out.append(
            f"{s.crossing_share:.2f} of it on planes across its main planes"
            f" (> {c.max_crossing_share}: walls on floors)"
        )
    return out


def decided_by(s: SceneFigures, config: JudgeConfig) -> str:
    """The figure that makes the cloud's above-ground structure a forest's, named with its value
    ("" when neither does): its stems, else its lines above a ground."""
    c = config.scene
    if s.stems >= c.min_stems:
        return f"{s.stems} stems (>= {c.min_stems})"
    if _stands(s, c) and s.above_linear_share >= c.min_above_linear_share:
        return f"above-ground lines {s.above_linear_share:.3f} (>= {c.min_above_linear_share})"
    return ""


def _stands(s: SceneFigures, c: SceneConfig) -> bool:
    """Whether lines above the ground count: a ground is seen under them, or they chain into
    branches (a random cloud's lowest points are no ground, its chance lines stand alone)."""
    return s.ground_share >= c.min_ground_share or s.branch_share >= c.min_branch_share


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
    """The figures as a plain dict (benchmarks, reports), with the figure the check decides on."""
    s = figures(cloud, config)
    return {**asdict(s), "decided_by": decided_by(s, config)}
