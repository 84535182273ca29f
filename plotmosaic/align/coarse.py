"""Global coarse alignment: any heading, tens of metres, no GNSS.

  1. level both clouds (normals: ground and stems give the vertical),
  2. search heading exhaustively and the horizontal shift by masked FFT correlation of forest
     rasters (stems, canopy, terrain), keeping several hypotheses,
  3. take the vertical offset from the ground,
  4. refine each hypothesis with a quick robust ICP and keep the best by how many non-flat points
     (stems, branches, crowns: flat ground matches anywhere) find a partner; the gap to the best
     distinct runner-up is the confidence.

Every transform here maps source-local to target-local coordinates (see PreparedCloud.frame).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, Field
from scipy import fft
from scipy.spatial import cKDTree

from plotmosaic.align.levelling import levelling_rotation
from plotmosaic.align.normals import local_shape
from plotmosaic.align.sampling import sample
from plotmosaic.align.voxel import thin, voxel_centroids
from plotmosaic.parallel import both, in_two_threads
from plotmosaic.io.frame import pose_error
from plotmosaic.align.rasters import CHANNELS, MaskedNCC, PointFeatures, column_bins, point_features, rasterise

AIRBORNE = {"als", "uls"}


class CoarseConfig(BaseModel):
    enabled: bool = True
    feature_voxel: float = Field(0.1, gt=0, description="voxel (m) of the cloud used for levelling and rasters")
    max_points: int = Field(150_000, gt=1000, description="cap on points used for the rasters")
    normal_radius: float = Field(0.75, gt=0, description="largest neighbourhood (m) of the coarse stage's own normals")
    normal_neighbours: int = Field(16, ge=5, description="nearest neighbours per normal: the neighbourhood adapts to density")
    max_tilt_deg: float = Field(75.0, description="largest roll/pitch the levelling searches")
    cell: float = Field(1.0, gt=0, description="raster cell (m); grown for large extents")
    max_fft: int = Field(512, description="largest padded FFT side; the cell grows to respect it")
    yaw_step_deg: float = Field(4.0, gt=0, le=10, description="heading step of the full-circle search")
    refine_headings: int = Field(8, ge=0, description="best headings searched again at half a step either side")
    blur_cells: float = 1.0
    min_overlap: float = Field(0.08, description="least overlap, as a fraction of the smaller footprint")
    hypotheses: int = Field(8, ge=1, description="hypotheses refined and verified")
    peaks_per_yaw: int = 2
    verify_voxel: float = 0.3
    verify_points: int = Field(6_000, description="source points used to refine and score the best hypotheses")
    screen_points: int = Field(3_000, description="of those, the points of the first short ICP that ranks every hypothesis")
    verify_iterations: int = 10
    refine_top: int = Field(3, ge=1, description="screened hypotheses refined fully")
    verify_distance_ground: float = Field(0.2, description="inlier distance (m) between ground-based scans")
    verify_distance_airborne: float = Field(0.5, description="inlier distance (m) when one cloud is airborne (sparse)")
    prior_yaw_deg: float = Field(30.0, gt=0, description="with an initial guess: headings searched either side of it")
    prior_shift_m: float = Field(8.0, gt=0, description="with an initial guess: horizontal distance searched around it")


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
class _Levelled:
    points: np.ndarray  # levelled, one per feature voxel (capped), in cube order
    normals: np.ndarray
    R: np.ndarray  # levelling rotation (local -> levelled)
    feats: PointFeatures
    info: dict


def _level(cloud, config: CoarseConfig, rng: np.random.Generator, upright: bool = False) -> _Levelled:
    """`upright`: take the file's z as the vertical (georeferenced airborne targets) instead of estimating it."""
    # own normals over a wider neighbourhood than ForestAlign's 0.25 m: the coarse stage must also
    # work on sparse clouds (far TLS ranges, ALS), where 0.25 m holds too few points for a plane
    pts = voxel_centroids(cloud.points, config.feature_voxel)
    pts = pts[sample(len(pts), config.max_points, rng)]
    tree = cKDTree(pts, balanced_tree=False, compact_nodes=False)
    nrm = local_shape(pts, tree, pts, config.normal_radius, config.normal_neighbours)[0]
    some_normals = nrm[rng.choice(len(nrm), min(len(nrm), 10_000), replace=False)]
    R, info = levelling_rotation(some_normals, max_tilt_deg=config.max_tilt_deg)
    if upright:
        info = {"tilt_deg": 0.0, "estimated_tilt_deg": info["tilt_deg"], "stem_share": info["stem_share"], "upright": True}
        R = np.eye(3)
    pts_l, nrm_l = pts @ R.T, nrm @ R.T
    feats = point_features(pts_l, nrm_l, cell=1.0)
    info.update(stems=int(feats.stem.sum()), canopy=int(feats.canopy.sum()), ground=int(feats.ground.sum()), points=len(pts))
    return _Levelled(pts_l, nrm_l, R, feats, info)


def _levelled(cloud, config: CoarseConfig, seed: int, upright: bool = False) -> _Levelled:
    """`_level`, remembered on the cloud object: in a plot each scan takes part in several pairs."""
    key = (config.model_dump_json(), seed, upright)
    memo = cloud.__dict__.setdefault("_coarse_levelled", {})
    if key not in memo:
        memo.clear()  # one entry is enough and keeps memory bounded
        memo[key] = _level(cloud, config, np.random.default_rng(seed), upright)
    return memo[key]


def _weights(source_kind: str, target_kind: str) -> dict[str, float]:
    if source_kind in AIRBORNE or target_kind in AIRBORNE:
        return {"stems": 0.25, "canopy": 1.0, "terrain": 1.0}
    return {"stems": 1.0, "canopy": 0.5, "terrain": 0.5}


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s], [s, c]])


def _search(src: _Levelled, tgt: _Levelled, weights: dict[str, float], config: CoarseConfig,
            prior: np.ndarray | None = None) -> list[dict]:
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
        cell *= 1.5
    s_shape = (s_side, s_side)
    s_origin = centre - radius
    src_bins, tgt_bins = column_bins(src.feats, cell / 4), column_bins(tgt.feats, cell / 4)
    target = rasterise(tgt_bins.xy, tgt_bins, cell, t_min, t_shape, config.blur_cells)
    area_t = target.masks["canopy"].sum()
    ncc = MaskedNCC(target, s_shape, min_overlap=1, workers=1)  # headings run in two threads instead
    area_s = rasterise(src_bins.xy, src_bins, cell, s_origin, s_shape, 0).masks["canopy"].sum()
    min_cells = config.min_overlap * min(area_s, area_t)

    rel = src_bins.xy - centre
    allowed = None
    if prior is not None:
        c3 = np.array([*centre, float(np.median(src.feats.z))])
        prior_yaw = float(np.arctan2(prior[1, 0], prior[0, 0]))
        prior_t = (prior[:3, :3] @ c3 + prior[:3, 3])[:2] - centre
        rows, cols = np.meshgrid(np.arange(ncc.shape[0]), np.arange(ncc.shape[1]), indexing="ij")
        shift = np.stack([np.where(rows < ncc.shape[0] // 2, rows, rows - ncc.shape[0]),
                          np.where(cols < ncc.shape[1] // 2, cols, cols - ncc.shape[1])], axis=-1)
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
        for name, (score, ov) in ncc.scores(source, [n for n in CHANNELS if weights[n] != 0]).items():
            if name == "canopy":
                overlap = ov
            if name == "terrain":  # a handful of shared ground cells proves nothing
                score = np.where(ov >= max(min_cells * 0.25, 4), score, 0.0)
            total = total + weights[name] * score
        total = total / sum(weights.values())
        frac = overlap / max(min(area_s, area_t), 1.0)
        total = np.where(overlap >= min_cells, total * np.clip(frac, 0, 1) ** 0.25, -1.0)
        if allowed is not None:
            total = np.where(allowed, total, -1.0)
        found = []
        for _ in range(config.peaks_per_yaw):
            k = np.unravel_index(int(np.argmax(total)), total.shape)
            if total[k] <= 0:
                break
            t_xy = ncc.shift_to_translation(k, source)
            found.append({"score": float(total[k]), "yaw": float(yaw), "t_xy": t_xy, "overlap": float(min(frac[k], 1.0))})
            r = max(1, int(round(3.0 / cell)))
            rows = np.arange(k[0] - r, k[0] + r + 1) % total.shape[0]
            cols = np.arange(k[1] - r, k[1] + r + 1) % total.shape[1]
            total[np.ix_(rows, cols)] = -1.0
        return found

    # coarse-to-fine in heading: the full circle at yaw_step_deg, then half steps either side of
    # the best headings (a peak is several steps wide once the rasters are blurred)
    step = np.radians(config.yaw_step_deg)
    yaws = np.arange(0.0, 2 * np.pi, step)
    if prior is not None:
        yaws = [y for y in yaws if _angle_diff(y, prior_yaw) <= np.radians(config.prior_yaw_deg)] + [prior_yaw % (2 * np.pi)]
    # rasterising and FFTs release the GIL: headings two at a time
    candidates = [c for found in in_two_threads(peaks, [float(y) for y in yaws]) for c in found]
    best_yaws: list[float] = []
    for c in sorted(candidates, key=lambda c: -c["score"]):
        if all(_angle_diff(c["yaw"], y) > 1.5 * step for y in best_yaws):
            best_yaws.append(c["yaw"])
        if len(best_yaws) >= config.refine_headings:
            break
    refine = [float((yaw + d) % (2 * np.pi)) for yaw in best_yaws for d in (-0.5 * step, 0.5 * step)]
    candidates += [c for found in in_two_threads(peaks, refine) for c in found]
    candidates.sort(key=lambda c: -c["score"])
    chosen: list[dict] = []
    for c in candidates:
        if all(_angle_diff(c["yaw"], o["yaw"]) > np.radians(6) or np.linalg.norm(c["t_xy"] - o["t_xy"]) > 3.0 for o in chosen):
            chosen.append({**c, "centre": centre, "cell": cell})
        if len(chosen) >= config.hypotheses:
            break
    return chosen


def _angle_diff(a: float, b: float) -> float:
    return abs((a - b + np.pi) % (2 * np.pi) - np.pi)


def _hypothesis_transform(h: dict, src: _Levelled, tgt: _Levelled, ground_tree: cKDTree | None) -> np.ndarray:
    """Full 4x4 (levelled source -> levelled target) of a heading/shift hypothesis, tz from the ground."""
    Rz = np.eye(3)
    Rz[:2, :2] = _rot_z(h["yaw"])
    A = np.eye(4)
    A[:3, :3] = Rz
    c = np.array([*h["centre"], 0.0])
    A[:3, 3] = c - Rz @ c + np.array([*h["t_xy"], 0.0])
    g = src.feats.ground
    if ground_tree is not None and g.any():
        moved = (np.column_stack([src.feats.xy[g], src.feats.z[g]]) @ A[:3, :3].T) + A[:3, 3]
        d, idx = ground_tree.query(moved[:, :2], distance_upper_bound=0.75)
        ok = np.isfinite(d)
        if ok.sum() >= 20:
            A[2, 3] = float(np.median(tgt.feats.z[tgt.feats.ground][idx[ok]] - moved[ok, 2]))
            return A
    A[2, 3] = float(np.median(tgt.feats.z) - np.median(src.feats.z))  # no shared ground: crude
    return A


def _refine(src_pts: np.ndarray, tgt: tuple, T0: np.ndarray, distances: tuple[float, ...], iterations: int) -> np.ndarray:
    """Quick robust point-to-plane ICP over shrinking correspondence distances (Tukey width = distance)."""
    from plotmosaic.align.config import IcpStage  # here: align.config imports this module
    from plotmosaic.align.icp import point_to_plane_icp

    points, normals, tree = tgt
    stages = [IcpStage(max_distance=d, iterations=iterations) for d in distances]
    return point_to_plane_icp(src_pts, points, normals, T0, stages, tree=tree, kernel_floor=0.0, kernel_ratio=1.0,
                              tol=1e-4).T


def _score(structure: np.ndarray, tgt: tuple, T: np.ndarray, distance: float) -> float:
    """Share of non-flat source points with a target partner: flat ground matches anywhere, stems do not."""
    from plotmosaic.align.icp import evaluate

    return evaluate(structure, tgt[2], T, distance)[0]


def _distinct(A: np.ndarray, B: np.ndarray) -> bool:
    degrees, metres = pose_error(A, B)
    return metres > 1.0 or degrees > 3.0


def _homogeneous(R: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    return T


def coarse_align(source, target, config: CoarseConfig | None = None, seed: int = 0,
                 prior: np.ndarray | None = None) -> CoarseResult:
    """Global alignment of two prepared clouds (anything with local `points` and a `kind`).

    `prior` (source local -> target local, e.g. from --init): search around it instead of everywhere,
    and verify the prior itself beside the hypotheses found, so a start that is already right stays.
    """
    config = config or CoarseConfig()
    start = time.perf_counter()
    rng = np.random.default_rng(seed)
    # An airborne target (ALS/ULS) is georeferenced: its z is the vertical, while its ground normals
    # show the terrain's slope (11 deg on the simulated plot) and few stems correct them. Levelling it
    # by its normals tilted it against a TLS source levelled by its stems, and 10 % of TLS -> ALS
    # starts then took a heading 180 deg off. The source may come in any orientation: always levelled.
    src, tgt = both(lambda job: _levelled(*job), (source, config, seed, False),
                    (target, config, seed + 1, target.kind in AIRBORNE))
    timing = {"levelling": time.perf_counter() - start}
    weights = _weights(source.kind, target.kind)
    L_s, L_t_inv = _homogeneous(src.R), _homogeneous(tgt.R.T)
    prior_levelled = None if prior is None else _homogeneous(tgt.R) @ np.asarray(prior, dtype=float) @ _homogeneous(src.R.T)
    hyps = _search(src, tgt, weights, config, prior_levelled)
    timing["search"] = time.perf_counter() - start - timing["levelling"]

    airborne = source.kind in AIRBORNE or target.kind in AIRBORNE
    d = config.verify_distance_airborne if airborne else config.verify_distance_ground
    # one kept point (and its own normal: averaged axial normals cancel) per verify cube
    keep = thin(tgt.points, config.verify_voxel)
    tgt_v = (tgt.points[keep], tgt.normals[keep], cKDTree(tgt.points[keep], balanced_tree=False, compact_nodes=False))
    keep = thin(src.points, config.verify_voxel)
    keep = keep[sample(len(keep), config.verify_points, rng)]
    src_v = src.points[keep]
    structure = src_v[np.abs(src.normals[keep, 2]) < 0.8]
    few = sample(len(src_v), config.screen_points, rng)
    src_few, structure_few = src_v[few], src_v[few][np.abs(src.normals[keep[few], 2]) < 0.8]
    ground_xy = tgt.feats.xy[tgt.feats.ground]
    ground_tree = cKDTree(ground_xy) if len(ground_xy) >= 20 else None

    # screen every hypothesis with one short ICP, refine the most promising ones fully
    starts = [(_hypothesis_transform(h, src, tgt, ground_tree), h) for h in hyps]
    if prior_levelled is not None:
        yaw = float(np.arctan2(prior_levelled[1, 0], prior_levelled[0, 0]))
        starts.append((prior_levelled, {"score": float("nan"), "yaw": yaw, "overlap": float("nan"), "prior": True}))
    def screen(start):
        A = _refine(src_few, tgt_v, start[0], (6 * d,), config.verify_iterations)
        return _score(structure_few, tgt_v, A, 2 * d), A, start[1]

    def refine(A):
        A = _refine(src_v, tgt_v, A, (3 * d, 1.5 * d), config.verify_iterations)
        return A, _score(structure, tgt_v, A, d)

    # independent ICPs, two at a time (KD-tree queries release the GIL)
    screened = sorted(in_two_threads(screen, starts), key=lambda r: -r[0])
    top = in_two_threads(refine, [A for _, A, _ in screened[: config.refine_top]])
    results = []
    for rank, (pre, A, h) in enumerate(screened):
        refined = rank < config.refine_top
        A, score = top[rank] if refined else (A, None)
        results.append({"T": L_t_inv @ A @ L_s, "refined": refined, "score": score, "screen_score": pre, "raster_score": h["score"], "yaw_deg": float(np.degrees(h["yaw"])), "overlap": h["overlap"], "prior": bool(h.get("prior", False))})
    if not results:
        identity = {"T": np.eye(4), "refined": True, "score": 0.0, "screen_score": 0.0, "raster_score": 0.0, "yaw_deg": 0.0, "overlap": 0.0}
        results.append(identity)
    results.sort(key=lambda r: (not r["refined"], -(r["score"] if r["refined"] else r["screen_score"])))
    best = results[0]
    # only refined hypotheses compete: an unrefined one may be the best pose not yet converged
    runner_up = next((r for r in results[1:] if r["refined"] and _distinct(best["T"], r["T"])), None)
    second = runner_up["score"] if runner_up else 0.0
    confidence = float(1.0 - second / best["score"]) if best["score"] > 0 else 0.0
    return CoarseResult(
        transform=best["T"],
        confidence=confidence,
        hypotheses=[
            {k: v for k, v in r.items() if k != "T"} | {"transform": np.asarray(r["T"]).tolist()}
            for r in results
        ],
        seconds=time.perf_counter() - start,
        levelling={"source": src.info, "target": tgt.info, "raster_cell": hyps[0]["cell"] if hyps else None},
        timing=timing | {"verify": time.perf_counter() - start - timing["levelling"] - timing["search"]},
    )
