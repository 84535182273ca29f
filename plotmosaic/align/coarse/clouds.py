"""A cloud as the coarse stage sees it: a capped feature-voxel sample with its own normals and
vertical hypotheses, levelled under each hypothesis on demand (kept in the memo that owns the
cloud); and the poses between levelled clouds.

Every transform here maps source-local to target-local coordinates (see PreparedCloud.frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.align import features3d, stemmap
from plotmosaic.align.levelling import Vertical, rotate, vertical_hypotheses
from plotmosaic.align.memo import CloudMemo, Shelf
from plotmosaic.align.normals import local_shape
from plotmosaic.align.rasters import PointFeatures, height_above_ground, point_features
from plotmosaic.align.sampling import sample
from plotmosaic.align.voxel import thin, voxel_centroids
from plotmosaic.config.coarse import CoarseConfig

AIRBORNE = {"als", "uls"}


@dataclass(frozen=True, kw_only=True, eq=False)
class Levelled:
    """A coarse cloud turned upright under one vertical hypothesis, with its raster features."""

    points: np.ndarray  # levelled
    normals: np.ndarray
    R: np.ndarray  # levelling rotation (local -> levelled)
    feats: PointFeatures
    hag: np.ndarray  # height above the rough DTM
    name: str  # which vertical hypothesis
    info: dict

    def ground_tree(self, config: CoarseConfig) -> cKDTree | None:
        """KD-tree of its ground cells' xy, or None with fewer than `tz_min_ground`."""
        ground_xy = self.feats.xy[self.feats.ground]
        return cKDTree(ground_xy) if len(ground_xy) >= config.tz_min_ground else None


@dataclass(frozen=True, kw_only=True, eq=False)
class CoarseCloud:
    """A cloud as the coarse stage sees it (local frame), with its vertical hypotheses."""

    points: np.ndarray  # one per feature voxel (capped), in cube order
    normals: np.ndarray
    verticals: tuple[Vertical, ...]
    info: dict


def levelled(cloud: CoarseCloud, v: Vertical, config: CoarseConfig) -> Levelled:
    """`cloud` turned upright under `v`, with its raster features."""
    R = v.R
    pts_l, nrm_l = rotate(cloud.points, R), rotate(cloud.normals, R)
    hag = height_above_ground(pts_l, config.feature_cell, config)
    feats = point_features(pts_l, nrm_l, config.feature_cell, config, hag=hag)
    info = {
        "stems": int(feats.stem.sum()),
        "canopy": int(feats.canopy.sum()),
        "ground": int(feats.ground.sum()),
    }
    return Levelled(points=pts_l, normals=nrm_l, R=R, feats=feats, hag=hag, name=v.name, info=info)


@dataclass(frozen=True, eq=False)
class Levels:
    """A coarse cloud and the shelf (in the memo that owns the cloud) where its levelled forms and
    their stem maps are kept, each made on first use: every generator levels under the same pairs."""

    cloud: CoarseCloud
    shelf: Shelf = field(default_factory=Shelf)

    def level(self, v: Vertical, config: CoarseConfig) -> Levelled:
        """The cloud levelled under `v`."""
        return self.shelf.get(("level", v.name), lambda: levelled(self.cloud, v, config))

    def stems(self, v: Vertical, config: CoarseConfig) -> stemmap.StemMap:
        """The stem map of the cloud levelled under `v`."""

        def make() -> stemmap.StemMap:
            lv = self.level(v, config)
            return stemmap.stem_map(lv.points, lv.normals, lv.hag, config)

        return self.shelf.get(("stems", v.name), make)

    def ground_tree(self, v: Vertical, config: CoarseConfig) -> cKDTree | None:
        """KD-tree of the ground cells' xy of the cloud levelled under `v` (Levelled.ground_tree)."""
        return self.shelf.get(("ground", v.name), lambda: self.level(v, config).ground_tree(config))

    def voxels(self, voxel: float) -> int:
        """Points of the cloud at `voxel` (features3d.voxel_count: every pair's FPFH voxel search
        asks a target for the same few sizes)."""
        return self.shelf.get(
            ("voxels", voxel), lambda: len(voxel_centroids(self.cloud.points, voxel))
        )

    def fpfh(self, config: CoarseConfig, voxel: float) -> features3d.Features:
        """FPFH of the cloud at `voxel`."""
        return self.shelf.get(
            ("fpfh", voxel), lambda: features3d.fpfh_features(self.cloud.points, config, voxel)
        )

    def verify_sample(self, config: CoarseConfig) -> tuple:
        """(points, normals, KD-tree): one point (and its own normal) per verify cube, the
        coarse verification's target."""

        def make() -> tuple:
            pts, nrm = self.cloud.points, self.cloud.normals
            keep = thin(pts, config.verify_voxel)
            return (
                pts[keep],
                nrm[keep],
                cKDTree(pts[keep], balanced_tree=False, compact_nodes=False),
            )

        return self.shelf.get(("verify",), make)


def coarse_cloud(
    cloud, config: CoarseConfig, rng: np.random.Generator, airborne: bool, upright: bool, limit: int
) -> CoarseCloud:
    """`upright`: take the file's z as the only vertical (georeferenced airborne targets)."""
    # own normals over a wider neighbourhood than ForestAlign's 0.25 m: the coarse stage must also
    # work on sparse clouds (far TLS ranges, ALS), where 0.25 m holds too few points for a plane
    pts = voxel_centroids(cloud.points, config.feature_voxel)
    pts = pts[sample(len(pts), config.max_points, rng)]
    tree = cKDTree(pts, balanced_tree=False, compact_nodes=False)
    nrm = local_shape(pts, tree, pts, config.normal_radius, config.normal_neighbours)[0]
    few = sample(len(nrm), config.levelling_normals, rng)
    # trunk axes on every point: a 40,000-point sample of an 8M scan's 150,000 left no trunk group
    verticals, info = vertical_hypotheses(
        pts[few], nrm[few], config, airborne=airborne, limit=limit, dense=(pts, nrm)
    )
    if upright:  # z-up first, and one estimate: on a slope a ground-levelled source pairs with a ground-levelled target
        info = {**info, "estimated_tilt_deg": info["tilt_deg"], "tilt_deg": 0.0, "upright": True}
    return CoarseCloud(
        points=pts, normals=nrm, verticals=tuple(verticals), info=info | {"points": len(pts)}
    )


def remembered(
    cloud,
    config: CoarseConfig,
    seed: int,
    airborne: bool,
    upright: bool,
    limit: int,
    memo: CloudMemo,
) -> Levels:
    """`coarse_cloud` and its levelled forms, kept in the cloud's memo: in a plot each scan takes
    part in several pairs."""
    key = (config.model_dump_json(), seed, airborne, upright, limit)
    return memo.coarse.get(
        key,
        lambda: Levels(
            coarse_cloud(cloud, config, np.random.default_rng(seed), airborne, upright, limit)
        ),
    )


def vertical_pairs(
    src: CoarseCloud, tgt: CoarseCloud, config: CoarseConfig
) -> list[tuple[Vertical, Vertical]]:
    """Vertical pairs searched: the first of each first, then like with like (two views of one plot see
    the same trunks lean and the same slope: estimates of one kind are biased alike and level the pair
    alike), then every source vertical against the target's first, then the rest."""
    names = {v.name: v for v in tgt.verticals}
    pairs = [(src.verticals[0], tgt.verticals[0])]
    pairs += [(v, names[v.name]) for v in src.verticals[1:] if v.name in names]
    pairs += [(v, tgt.verticals[0]) for v in src.verticals[1:]]
    pairs += [(a, b) for b in tgt.verticals[1:] for a in src.verticals]
    out: list[tuple[Vertical, Vertical]] = []
    for p in pairs:
        if all(p[0] is not o[0] or p[1] is not o[1] for o in out):
            out.append(p)
    return out[: config.max_vertical_pairs]


def homogeneous(R: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    return T


def unlevelled(A: np.ndarray, src: Levelled, tgt: Levelled) -> np.ndarray:
    """A pose between the levelled clouds as a pose between their local frames."""
    return homogeneous(tgt.R.T) @ A @ homogeneous(src.R)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s], [s, c]])


def hypothesis_transform(
    src: Levelled,
    tgt: Levelled,
    ground_tree: cKDTree | None,
    config: CoarseConfig,
    *,
    yaw: float,
    t_xy: np.ndarray,
    centre: np.ndarray,
) -> np.ndarray:
    """Full 4x4 (levelled source -> levelled target) of a heading `yaw` about `centre` and a
    horizontal shift `t_xy`, tz from the ground."""
    Rz = np.eye(3)
    Rz[:2, :2] = _rot_z(yaw)
    A = np.eye(4)
    A[:3, :3] = Rz
    c = np.array([*centre, 0.0])
    A[:3, 3] = c - Rz @ c + np.array([*t_xy, 0.0])
    return with_height(A, src, tgt, ground_tree, config)


def with_height(
    A: np.ndarray, src: Levelled, tgt: Levelled, ground_tree: cKDTree | None, config: CoarseConfig
) -> np.ndarray:
    """`A` with its vertical offset taken from the shared ground (the median of target - source heights)."""
    A = A.copy()
    g = src.feats.ground
    if ground_tree is not None and g.any():
        moved = rotate(np.column_stack([src.feats.xy[g], src.feats.z[g]]), A[:3, :3]) + A[:3, 3]
        d, idx = ground_tree.query(moved[:, :2], distance_upper_bound=config.tz_ground_radius)
        ok = np.isfinite(d)
        if ok.sum() >= config.tz_min_ground:
            A[2, 3] += float(np.median(tgt.feats.z[tgt.feats.ground][idx[ok]] - moved[ok, 2]))
            return A
    moved_z = src.feats.z * A[2, 2] + A[2, 3]
    A[2, 3] += float(np.median(tgt.feats.z) - np.median(moved_z))  # no shared ground: crude
    return A
