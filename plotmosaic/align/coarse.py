"""Global coarse alignment: any heading, tens of metres, no GNSS.

  1. several vertical hypotheses per cloud (ground normals, stem normals, a robust ground fit,
     z-up when airborne or already near vertical: levelling.py), each carried into the search,
  2. generators, under every vertical pair: heading searched exhaustively and the horizontal shift
     by masked FFT correlation of forest rasters (stems, canopy, terrain); stem maps matched as
     point patterns (stemmap.py); FPFH matches with a 4-DoF vote and a 6-DoF RANSAC (features3d.py);
     when the first vertical pair has not settled, fine height-slice occupancy correlated over
     heading x shift (slices.py: sparse ground views the 1 m rasters miss),
  3. the vertical offset of raster and stem hypotheses from the ground,
  4. screen every hypothesis with a short ICP, refine the best of each generator and the best
     overall with a quick robust ICP, and keep the best by how many non-flat points with a quick robust ICP and keep the best by how many non-flat points
     (stems, branches, crowns: flat ground matches anywhere) find a partner; the gap to the best
     distinct runner-up is the confidence.

Every transform here maps source-local to target-local coordinates (see PreparedCloud.frame).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import fft
from scipy.spatial import cKDTree

from plotmosaic.align import features3d, slices, stemmap
from plotmosaic.align.icp import evaluate, point_to_plane_icp
from plotmosaic.align.levelling import Vertical, rotate, vertical_hypotheses
from plotmosaic.align.memo import CloudMemo, PairMemo
from plotmosaic.align.normals import local_shape
from plotmosaic.align.peaks import angle_diff, distinct_peaks
from plotmosaic.align.rasters import (
    CHANNELS,
    MaskedNCC,
    PointFeatures,
    column_bins,
    height_above_ground,
    point_features,
    rasterise,
)
from plotmosaic.align.sampling import sample
from plotmosaic.align.voxel import thin, voxel_centroids
from plotmosaic.config.align import IcpStage
from plotmosaic.config.coarse import CoarseConfig
from plotmosaic.io.frame import pose_error
from plotmosaic.parallel import both, in_two_threads

__all__ = ["CoarseConfig", "CoarseResult", "coarse_align"]

AIRBORNE = {"als", "uls"}


@dataclass
class CoarseResult:
    transform: np.ndarray  # 4x4, source local frame -> target local frame
    confidence: float
    hypotheses: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    levelling: dict = field(default_factory=dict)
    timing: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "transform": np.asarray(self.transform).tolist(),
            "confidence": self.confidence,
            "seconds": self.seconds,
            "levelling": self.levelling,
            "timing": self.timing,
            "hypotheses": self.hypotheses,
        }


@dataclass
class _Base:
    """A cloud as the coarse stage sees it (local frame), with its vertical hypotheses."""

    points: np.ndarray  # one per feature voxel (capped), in cube order
    normals: np.ndarray
    verticals: list[Vertical]
    info: dict
    levelled: dict = field(default_factory=dict)  # vertical name -> _Levelled, made on demand


@dataclass
class _Levelled:
    points: np.ndarray  # levelled
    normals: np.ndarray
    R: np.ndarray  # levelling rotation (local -> levelled)
    feats: PointFeatures
    hag: np.ndarray  # height above the rough DTM
    name: str  # which vertical hypothesis
    info: dict
    _stems: stemmap.StemMap | None = None


def _base(
    cloud, config: CoarseConfig, rng: np.random.Generator, airborne: bool, upright: bool, limit: int
) -> _Base:
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
    return _Base(pts, nrm, verticals, info | {"points": len(pts)})


def _level(base: _Base, v: Vertical, config: CoarseConfig) -> _Levelled:
    if v.name not in base.levelled:
        R = v.R
        pts_l, nrm_l = rotate(base.points, R), rotate(base.normals, R)
        hag = height_above_ground(pts_l, config.feature_cell, config)
        feats = point_features(pts_l, nrm_l, config.feature_cell, config, hag=hag)
        info = {
            "stems": int(feats.stem.sum()),
            "canopy": int(feats.canopy.sum()),
            "ground": int(feats.ground.sum()),
        }
        base.levelled[v.name] = _Levelled(pts_l, nrm_l, R, feats, hag, v.name, info)
    return base.levelled[v.name]


def _stems(lv: _Levelled, config: CoarseConfig) -> stemmap.StemMap:
    if lv._stems is None:
        lv._stems = stemmap.stem_map(lv.points, lv.normals, lv.hag, config)
    return lv._stems


def _prepared(
    cloud,
    config: CoarseConfig,
    seed: int,
    airborne: bool,
    upright: bool,
    limit: int,
    memo: CloudMemo,
) -> _Base:
    """`_base`, kept in the cloud's memo: in a plot each scan takes part in several pairs."""
    key = (config.model_dump_json(), seed, airborne, upright, limit)
    return memo.coarse.get(
        key, lambda: _base(cloud, config, np.random.default_rng(seed), airborne, upright, limit)
    )


def _weights(source_kind: str, target_kind: str, config: CoarseConfig) -> dict[str, float]:
    if source_kind in AIRBORNE or target_kind in AIRBORNE:
        return dict(config.weights_airborne)
    return dict(config.weights_ground)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s], [s, c]])


def _search(
    src: _Levelled,
    tgt: _Levelled,
    weights: dict[str, float],
    config: CoarseConfig,
    prior: np.ndarray | None = None,
) -> list[dict]:
    """Exhaustive heading search; masked-NCC shift per heading; the best distinct peaks.

    `prior` (levelled source -> levelled target): search only headings within `prior_yaw_deg` of
    it and shifts within `prior_shift_m` of where it puts the source centroid.
    """
    centre = src.feats.xy.mean(axis=0)
    radius = float(np.linalg.norm(src.feats.xy - centre, axis=1).max()) + 1.0
    t_min, t_max = tgt.feats.xy.min(axis=0) - 1.0, tgt.feats.xy.max(axis=0) + 1.0
    cell = config.cell
    while True:
        t_shape = tuple(np.ceil((t_max - t_min) / cell).astype(int) + 1)
        s_side = int(np.ceil(2 * radius / cell)) + 1
        if max(fft.next_fast_len(t + s_side, real=True) for t in t_shape) <= config.max_fft:
            break
        cell *= config.cell_growth
    s_shape = (s_side, s_side)
    s_origin = centre - radius
    src_bins, tgt_bins = column_bins(src.feats, cell / 4), column_bins(tgt.feats, cell / 4)
    target = rasterise(tgt_bins.xy, tgt_bins, cell, t_min, t_shape, config.blur_cells)
    area_t = target.masks["canopy"].sum()
    ncc = MaskedNCC(
        target, s_shape, min_overlap=1, workers=1
    )  # headings run in two threads instead
    area_s = rasterise(src_bins.xy, src_bins, cell, s_origin, s_shape, 0).masks["canopy"].sum()
    min_cells = config.min_overlap * min(area_s, area_t)

    rel = src_bins.xy - centre
    allowed = None
    if prior is not None:
        c3 = np.array([*centre, float(np.median(src.feats.z))])
        prior_yaw = float(np.arctan2(prior[1, 0], prior[0, 0]))
        prior_t = (prior[:3, :3] @ c3 + prior[:3, 3])[:2] - centre
        rows, cols = np.meshgrid(np.arange(ncc.shape[0]), np.arange(ncc.shape[1]), indexing="ij")
        shift = np.stack(
            [
                np.where(rows < ncc.shape[0] // 2, rows, rows - ncc.shape[0]),
                np.where(cols < ncc.shape[1] // 2, cols, cols - ncc.shape[1]),
            ],
            axis=-1,
        )
        t_xy = target.origin - s_origin + shift * cell
        allowed = np.linalg.norm(t_xy - prior_t, axis=-1) <= config.prior_shift_m

    def peaks(yaw: float) -> list[dict]:
        c, s_ = np.cos(yaw), np.sin(yaw)
        xy = np.empty_like(rel)
        xy[:, 0] = c * rel[:, 0] - s_ * rel[:, 1] + centre[0]
        xy[:, 1] = s_ * rel[:, 0] + c * rel[:, 1] + centre[1]
        source = rasterise(xy, src_bins, cell, s_origin, s_shape, config.blur_cells)
        total = 0.0
        overlap = None
        for name, (score, ov) in ncc.scores(
            source, [n for n in CHANNELS if weights[n] != 0]
        ).items():
            if name == "canopy":
                overlap = ov
            if name == "terrain":  # a handful of shared ground cells proves nothing
                score = np.where(
                    ov >= max(min_cells * config.terrain_min_share, config.terrain_min_cells),
                    score,
                    0.0,
                )
            total = total + weights[name] * score
        total = total / sum(weights.values())
        frac = overlap / max(min(area_s, area_t), 1.0)
        total = np.where(
            overlap >= min_cells, total * np.clip(frac, 0, 1) ** config.overlap_exponent, -1.0
        )
        if allowed is not None:
            total = np.where(allowed, total, -1.0)
        found = []
        for _ in range(config.peaks_per_yaw):
            k = np.unravel_index(int(np.argmax(total)), total.shape)
            if total[k] <= 0:
                break
            t_xy = ncc.shift_to_translation(k, source)
            found.append(
                {
                    "score": float(total[k]),
                    "yaw": float(yaw),
                    "t_xy": t_xy,
                    "overlap": float(min(frac[k], 1.0)),
                }
            )
            r = max(1, int(round(config.peak_suppression_m / cell)))
            rows = np.arange(k[0] - r, k[0] + r + 1) % total.shape[0]
            cols = np.arange(k[1] - r, k[1] + r + 1) % total.shape[1]
            total[np.ix_(rows, cols)] = -1.0
        return found

    # coarse-to-fine in heading: the full circle at yaw_step_deg, then half steps either side of
    # the best headings (a peak is several steps wide once the rasters are blurred)
    step = np.radians(config.yaw_step_deg)
    yaws = np.arange(0.0, 2 * np.pi, step)
    if prior is not None:
        yaws = [y for y in yaws if angle_diff(y, prior_yaw) <= np.radians(config.prior_yaw_deg)] + [
            prior_yaw % (2 * np.pi)
        ]
    # rasterising and FFTs release the GIL: headings two at a time
    candidates = [c for found in in_two_threads(peaks, [float(y) for y in yaws]) for c in found]
    best_yaws: list[float] = []
    for c in sorted(candidates, key=lambda c: -c["score"]):
        if all(angle_diff(c["yaw"], y) > 1.5 * step for y in best_yaws):
            best_yaws.append(c["yaw"])
        if len(best_yaws) >= config.refine_headings:
            break
    refine = [
        float((yaw + d) % (2 * np.pi)) for yaw in best_yaws for d in (-0.5 * step, 0.5 * step)
    ]
    candidates += [c for found in in_two_threads(peaks, refine) for c in found]
    candidates.sort(key=lambda c: -c["score"])
    return distinct_peaks(
        candidates,
        config.distinct_yaw_deg,
        config.distinct_shift_m,
        config.hypotheses,
        centre=centre,
        cell=cell,
    )


def _hypothesis_transform(
    h: dict, src: _Levelled, tgt: _Levelled, ground_tree: cKDTree | None, config: CoarseConfig
) -> np.ndarray:
    """Full 4x4 (levelled source -> levelled target) of a heading/shift hypothesis, tz from the ground."""
    Rz = np.eye(3)
    Rz[:2, :2] = _rot_z(h["yaw"])
    A = np.eye(4)
    A[:3, :3] = Rz
    c = np.array([*h["centre"], 0.0])
    A[:3, 3] = c - Rz @ c + np.array([*h["t_xy"], 0.0])
    return _with_height(A, src, tgt, ground_tree, config)


def _with_height(
    A: np.ndarray, src: _Levelled, tgt: _Levelled, ground_tree: cKDTree | None, config: CoarseConfig
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


def _refine(
    src_pts: np.ndarray, tgt: tuple, T0: np.ndarray, distances: tuple[float, ...], iterations: int
) -> np.ndarray:
    """Quick robust point-to-plane ICP over shrinking correspondence distances (Tukey width = distance)."""
    points, normals, tree = tgt
    stages = [IcpStage(max_distance=d, iterations=iterations) for d in distances]
    return point_to_plane_icp(
        src_pts,
        points,
        normals,
        T0,
        stages,
        tree=tree,
        kernel_floor=0.0,
        kernel_ratio=1.0,
        tol=1e-4,
    ).T


def _score(structure: np.ndarray, tgt: tuple, T: np.ndarray, distance: float) -> float:
    """Share of non-flat source points with a target partner: flat ground matches anywhere, stems do not."""
    return evaluate(structure, tgt[2], T, distance)[0]


def _distinct(A: np.ndarray, B: np.ndarray, config: CoarseConfig) -> bool:
    degrees, metres = pose_error(A, B)
    return metres > config.distinct_m or degrees > config.distinct_deg


def _homogeneous(R: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    return T


def _vertical_pairs(
    src: _Base, tgt: _Base, config: CoarseConfig
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


def _fpfh_matches(src: _Base, tgt: _Base, config: CoarseConfig) -> tuple[np.ndarray, np.ndarray]:
    """Mutually matched FPFH points (source, target), local frames."""
    voxel = features3d.shared_voxel([src.points, tgt.points], config)
    fs, ft = (
        features3d.fpfh_features(src.points, config, voxel),
        features3d.fpfh_features(tgt.points, config, voxel),
    )
    i, j = features3d.mutual_matches(fs, ft)
    return fs.points[i], ft.points[j]


def _fpfh_starts(
    matches: tuple[np.ndarray, np.ndarray],
    pairs,
    config: CoarseConfig,
    rng: np.random.Generator,
    six_dof: bool,
) -> list[tuple]:
    """(local 4x4, hypothesis dict) from FPFH matches: a 4-DoF vote per vertical pair, and (`six_dof`) one 6-DoF RANSAC."""
    p, q = matches
    out = []
    for vs, vt in pairs:
        Rs, Rt = vs.R, vt.R
        for A, n in features3d.vote_4dof(rotate(p, Rs), rotate(q, Rt), config):
            T = _homogeneous(Rt.T) @ A @ _homogeneous(Rs)
            out.append((T, {"generator": "fpfh", "vertical": f"{vs.name}/{vt.name}", "votes": n}))
    if six_dof and config.fpfh_six_dof:
        for T, n in features3d.ransac_6dof(p, q, config, rng):
            out.append((T, {"generator": "fpfh", "vertical": "none (6-DoF)", "votes": n}))
    return out


def _stem_starts(
    src: _Base, tgt: _Base, pairs, config: CoarseConfig, rng: np.random.Generator
) -> list[tuple]:
    """(local 4x4, hypothesis dict) from stem-map matches per vertical pair."""
    out = []
    for vs, vt in pairs:
        ls, lt = _level(src, vs, config), _level(tgt, vt, config)
        ms, mt = _stems(ls, config), _stems(lt, config)
        found = stemmap.match_stem_maps(ms, mt, config, rng)
        if not found:
            continue
        ground_xy = lt.feats.xy[lt.feats.ground]
        ground_tree = cKDTree(ground_xy) if len(ground_xy) >= config.tz_min_ground else None
        for yaw, t_xy, n in found:
            h = {"yaw": yaw, "t_xy": t_xy, "centre": np.zeros(2)}
            A = _hypothesis_transform(h, ls, lt, ground_tree, config)
            T = _homogeneous(lt.R.T) @ A @ _homogeneous(ls.R)
            out.append(
                (
                    T,
                    {
                        "generator": "stems",
                        "vertical": f"{vs.name}/{vt.name}",
                        "votes": n,
                        "yaw": yaw,
                        "stems": [len(ms.xy), len(mt.xy)],
                    },
                )
            )
    return out


def _slice_starts(src: _Base, tgt: _Base, pairs, config: CoarseConfig) -> list[tuple]:
    """(local 4x4, hypothesis dict) of the height-slice occupancy search per vertical pair."""
    out = []
    for vs, vt in pairs:
        ls, lt = _level(src, vs, config), _level(tgt, vt, config)
        ground_xy = lt.feats.xy[lt.feats.ground]
        ground_tree = cKDTree(ground_xy) if len(ground_xy) >= config.tz_min_ground else None
        for h in slices.slice_search(ls.points, ls.hag, lt.points, lt.hag, config):
            A = _hypothesis_transform(h, ls, lt, ground_tree, config)
            T = _homogeneous(lt.R.T) @ A @ _homogeneous(ls.R)
            out.append(
                (
                    T,
                    {
                        "generator": "slices",
                        "vertical": f"{vs.name}/{vt.name}",
                        "slice_score": h["score"],
                        "yaw": h["yaw"],
                        "overlap": h["overlap"],
                        "cell": h["cell"],
                    },
                )
            )
    return out


def _raster_starts(
    src: _Base,
    tgt: _Base,
    pairs,
    weights,
    config: CoarseConfig,
    prior: np.ndarray | None,
    first: int = 0,
) -> tuple[list[tuple], float | None]:
    """(local 4x4, hypothesis dict) of the raster search per vertical pair, and the raster cell used.

    `first`: the index of `pairs[0]` among all vertical pairs (pair 0 gets the most hypotheses)."""
    out, cell = [], None
    for k, (vs, vt) in enumerate(pairs, start=first):
        ls, lt = _level(src, vs, config), _level(tgt, vt, config)
        prior_l = None if prior is None else _homogeneous(lt.R) @ prior @ _homogeneous(ls.R.T)
        hyps = _search(ls, lt, weights, config, prior_l)[
            : config.hypotheses if k == 0 else config.secondary_hypotheses
        ]
        ground_xy = lt.feats.xy[lt.feats.ground]
        ground_tree = cKDTree(ground_xy) if len(ground_xy) >= config.tz_min_ground else None
        # a narrow scene (a 12 m understorey view is 12 cells at 1 m) also gets a finer-cell search
        # beside, never instead of, the usual one: finer cells alone found a wrong pose with full confidence
        side = float(np.ptp(ls.feats.xy, axis=0).min())
        if (
            k == 0
            and side < config.small_scene_cells * config.cell
            and config.cell > config.min_cell
        ):
            fine = config.model_copy(
                update={"cell": max(config.min_cell, side / config.small_scene_cells)}
            )
            hyps = hyps + [
                h | {"fine": True}
                for h in _search(ls, lt, weights, fine, prior_l)[: config.secondary_hypotheses]
            ]
        for h in hyps:
            cell = h["cell"] if cell is None else cell
            T = (
                _homogeneous(lt.R.T)
                @ _hypothesis_transform(h, ls, lt, ground_tree, config)
                @ _homogeneous(ls.R)
            )
            out.append(
                (
                    T,
                    {
                        "generator": "raster",
                        "vertical": f"{vs.name}/{vt.name}" + (" fine" if h.get("fine") else ""),
                        "score": h["score"],
                        "yaw": h["yaw"],
                        "overlap": h["overlap"],
                        "cell": h["cell"],
                    },
                )
            )
    return out, cell


def _unique_starts(starts: list[tuple], config: CoarseConfig) -> list[tuple]:
    """Starts without near-duplicates (the first kept; the generators that agreed with it noted in "agree")."""
    out: list[tuple] = []
    for T, h in starts:
        for T2, h2 in out:
            deg, m = pose_error(T, T2)
            if (
                m < config.start_duplicate_m
                and deg < config.start_duplicate_deg
                and not h.get("prior")
            ):
                h2.setdefault("agree", []).append(f"{h['generator']}:{h['vertical']}")
                break
        else:
            out.append((T, h))
    return out


def _yaw_deg(T: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(T[1, 0], T[0, 0])))


def coarse_align(
    source,
    target,
    config: CoarseConfig | None = None,
    seed: int = 0,
    prior: np.ndarray | None = None,
    memo: PairMemo | None = None,
) -> CoarseResult:
    """Global alignment of two prepared clouds (anything with local `points` and a `kind`).

    Hypotheses come from three generators (forest rasters, FPFH matches, stem maps) under every
    vertical hypothesis, and all go through one verification. `prior` (source local -> target
    local, e.g. from --init): the raster search looks around it instead of everywhere, and the prior
    itself is verified beside the hypotheses found, so a start that is already right stays.

    The first vertical pair is searched and verified first; the other pairs only when its best pose
    is not already settled (`_settled`): clearly ahead of its distinct rivals, fitting well and found
    by two generators independently. Its rivals stay in the hypotheses for the judge.
    `memo`: the pair's, where each cloud's levelled sample is kept.
    """
    config = config or CoarseConfig()
    memo = memo or PairMemo()
    start = time.perf_counter()
    rng = np.random.default_rng(seed)
    # An airborne target (ALS/ULS) is georeferenced: its z is the vertical, while its ground normals
    # show the terrain's slope and few stems correct them (docs/method.md#coarse-stage-settings).
    # The source may come in any orientation: several vertical hypotheses (z-up first when it is
    # airborne), each searched.
    src, tgt = both(
        lambda job: _prepared(*job),
        (source, config, seed, source.kind in AIRBORNE, False, config.max_verticals, memo.source),
        (
            target,
            config,
            seed + 1,
            target.kind in AIRBORNE,
            target.kind in AIRBORNE,
            config.max_target_verticals,
            memo.target,
        ),
    )
    pairs = _vertical_pairs(src, tgt, config)
    timing = {"levelling": time.perf_counter() - start}
    weights = _weights(source.kind, target.kind, config)
    prior = None if prior is None else np.asarray(prior, dtype=float)
    verify = _Verifier(src, tgt, source.kind in AIRBORNE or target.kind in AIRBORNE, config, rng)
    # generators draw from their own stream: adding one changes no other
    gen_rng = np.random.default_rng([seed, 1])
    matches = None

    def clock(name: str, t: float) -> None:
        timing[name] = timing.get(name, 0.0) + time.perf_counter() - t

    def generate(first: int, chosen) -> tuple[list[tuple], float | None]:
        nonlocal matches
        t = time.perf_counter()
        out, cell = _raster_starts(src, tgt, chosen, weights, config, prior, first)
        clock("search", t)
        if config.fpfh:
            t = time.perf_counter()
            if matches is None:
                matches = _fpfh_matches(src, tgt, config)
            own = chosen[: max(0, config.fpfh_vertical_pairs - first)]
            out += _fpfh_starts(matches, own, config, gen_rng, six_dof=first == 0)
            clock("fpfh", t)
        if config.stems:
            t = time.perf_counter()
            out += _stem_starts(src, tgt, chosen, config, gen_rng)
            clock("stems", t)
        return out, cell

    starts, cell = generate(0, pairs[:1])
    if prior is not None:
        starts.append(
            (prior, {"generator": "prior", "vertical": "prior", "prior": True})
        )  # never merged away
    starts = _unique_starts(starts, config)
    settled = False
    if config.settle_early and len(pairs) > 1:
        t = time.perf_counter()
        # refined only when two generators' screened poses already agree: otherwise it cannot settle
        if verify.agreed(starts):
            results, confidence = verify(starts)
            settled = _settled(results, confidence, config)
        clock("verify", t)
    if not settled:
        if len(pairs) > 1:
            more, _ = generate(1, pairs[1:])
            starts = _unique_starts(starts + more, config)
        if config.slices:  # only now: a settled pair needs no finer search
            t = time.perf_counter()
            more = _slice_starts(src, tgt, pairs[: config.slice_vertical_pairs], config)
            starts = _unique_starts(starts + more, config)
            clock("slices", t)
        t = time.perf_counter()
        results, confidence = verify(starts)
        clock("verify", t)
    best = results[0]
    counts = {
        g: sum(r["generator"] == g for r in results)
        for g in ("raster", "fpfh", "stems", "slices", "prior")
    }
    searched = pairs if len(pairs) == 1 or not settled else pairs[:1]
    return CoarseResult(
        transform=best["T"],
        confidence=confidence,
        hypotheses=[
            {k: v for k, v in r.items() if k != "T"} | {"transform": np.asarray(r["T"]).tolist()}
            for r in results
        ],
        seconds=time.perf_counter() - start,
        levelling={
            "source": src.info,
            "target": tgt.info,
            "raster_cell": cell,
            "vertical_pairs": [f"{a.name}/{b.name}" for a, b in searched],
            "vertical_pairs_skipped": len(pairs) - len(searched),
            "hypotheses_by_generator": counts,
        },
        timing=timing,
    )


def _support(results: list[dict], best: dict, config: CoarseConfig) -> set[str]:
    """Generators whose own hypotheses reached `best`'s pose (screened or as a duplicate start)."""
    out = set()
    for r in results:
        if not _distinct(best["T"], r["T"], config):
            out.add(r["generator"])
            out.update(a.split(":")[0] for a in r.get("agree", []))
    return out - {"prior"}


def _settled(results: list[dict], confidence: float, config: CoarseConfig) -> bool:
    """The first vertical pair's best pose needs no other: ahead of its rivals, fitting, found twice."""
    best = results[0]
    return (
        best["refined"]
        and confidence >= config.settled_confidence
        and (best["score"] or 0.0) >= config.settled_score
        and len(_support(results, best, config)) >= config.settled_generators
    )


class _Verifier:
    """Screens starts (short ICP), refines the best distinct ones, and ranks them; each start and each
    refinement is computed once, so a second call with more starts only pays for the new ones."""

    def __init__(self, src: _Base, tgt: _Base, airborne: bool, config: CoarseConfig, rng):
        self.config = config
        d = config.verify_distance_airborne if airborne else config.verify_distance_ground
        self.d = d
        self.iterations = (
            config.verify_iterations_airborne if airborne else config.verify_iterations
        )
        # verification in the clouds' local frames (each hypothesis carries its own verticals); one kept
        # point (and its own normal: averaged axial normals cancel) per verify cube
        keep = thin(tgt.points, config.verify_voxel)
        self.tgt_v = (
            tgt.points[keep],
            tgt.normals[keep],
            cKDTree(tgt.points[keep], balanced_tree=False, compact_nodes=False),
        )
        keep = thin(src.points, config.verify_voxel)
        keep = keep[sample(len(keep), config.verify_points, rng)]
        self.src_v = src.points[keep]
        # non-flat under the source's first vertical: one fixed set, so every hypothesis is scored on the same points
        up = src.verticals[0].up
        flat_ok = np.abs(src.normals[keep] @ up) < config.structure_normal_z
        self.structure = self.src_v[flat_ok]
        few = sample(len(self.src_v), config.screen_points, rng)
        self.src_few, self.structure_few = self.src_v[few], self.src_v[few][flat_ok[few]]
        self.screened: dict[
            int, tuple
        ] = {}  # id of a start's hypothesis dict -> (score, pose, dict)
        self.refined: dict[int, tuple] = {}  # the same key -> (pose, score)

    def _screen(self, start):
        c, d = self.config, self.d
        A = _refine(
            self.src_few, self.tgt_v, start[0], (c.screen_distance_factor * d,), self.iterations
        )
        return _score(self.structure_few, self.tgt_v, A, c.screen_score_factor * d), A, start[1]

    def _refine(self, A):
        c, d = self.config, self.d
        A = _refine(
            self.src_v,
            self.tgt_v,
            A,
            tuple(f * d for f in c.refine_distance_factors),
            self.iterations,
        )
        return A, _score(self.structure, self.tgt_v, A, d)

    def _screen_all(self, starts: list[tuple]) -> None:
        new = [s for s in starts if id(s[1]) not in self.screened]
        for s, r in zip(new, in_two_threads(self._screen, new)):
            self.screened[id(s[1])] = r

    def agreed(self, starts: list[tuple]) -> bool:
        """Whether the best screened pose was reached by `settled_generators` generators."""
        self._screen_all(starts)
        screened = sorted((self.screened[id(s[1])] for s in starts), key=lambda r: -r[0])
        if not screened:
            return False
        rows = [
            {"T": A, "generator": h["generator"], "agree": h.get("agree", [])}
            for _, A, h in screened
        ]
        return len(_support(rows, rows[0], self.config)) >= self.config.settled_generators

    def __call__(self, starts: list[tuple]) -> tuple[list[dict], float]:
        config = self.config
        self._screen_all(starts)
        # independent ICPs, two at a time (KD-tree queries release the GIL); refined: the best screened
        # of each generator first (so no generator's best is lost to another's near-duplicates), then by score
        screened = sorted((self.screened[id(s[1])] for s in starts), key=lambda r: -r[0])
        # screened poses have converged: refine distinct ones only, so the runner-up is a real rival
        distinct: list[int] = []
        for i, (_, A, _) in enumerate(screened):
            if all(_distinct(A, screened[j][1], config) for j in distinct):
                distinct.append(i)
        chosen = [
            k
            for k in (
                next((i for i in distinct if screened[i][2]["generator"] == gen), None)
                for gen in ("raster", "fpfh", "stems", "slices", "prior")
            )
            if k is not None and screened[k][0] > 0
        ]
        chosen = sorted(
            chosen
            + [i for i in distinct if i not in chosen][: max(0, config.refine_top - len(chosen))]
        )
        todo = [i for i in chosen if id(screened[i][2]) not in self.refined]
        for i, r in zip(todo, in_two_threads(self._refine, [screened[i][1] for i in todo])):
            self.refined[id(screened[i][2])] = r
        results = []
        for pre, A, h in screened:
            # every refined pose competes, also one refined before more starts came (more rivals)
            refined = id(h) in self.refined
            A, score = self.refined[id(h)] if refined else (A, None)
            results.append(
                {
                    "T": A,
                    "refined": refined,
                    "score": score,
                    "screen_score": pre,
                    "raster_score": h.get(
                        "score"
                    ),  # None for other generators (strict JSON: no NaN)
                    "yaw_deg": float(np.degrees(h["yaw"])) if "yaw" in h else _yaw_deg(A),
                    "overlap": h.get("overlap"),
                    "prior": bool(h.get("prior", False)),
                    "generator": h["generator"],
                    "vertical": h["vertical"],
                }
                | {k: h[k] for k in ("votes", "agree", "slice_score") if k in h}
            )
        if not results:
            results.append(
                {
                    "T": np.eye(4),
                    "refined": True,
                    "score": 0.0,
                    "screen_score": 0.0,
                    "raster_score": 0.0,
                    "yaw_deg": 0.0,
                    "overlap": 0.0,
                    "prior": False,
                    "generator": "none",
                    "vertical": "none",
                }
            )
        results.sort(
            key=lambda r: (not r["refined"], -(r["score"] if r["refined"] else r["screen_score"]))
        )
        best = results[0]
        # only refined hypotheses compete: an unrefined one may be the best pose not yet converged
        runner_up = next(
            (r for r in results[1:] if r["refined"] and _distinct(best["T"], r["T"], config)), None
        )
        second = runner_up["score"] if runner_up else 0.0
        confidence = float(1.0 - second / best["score"]) if best["score"] > 0 else 0.0
        return results, confidence
