"""The methods a benchmark compares, all behind one call: source' -> target, file coordinates.

  forestalign  plotmosaic's pipeline (global coarse stage on; `--no-coarse` starts it at identity)
  forestalign-placement  the same with register-plot's settings for placing a scan on an airborne
               tile (its search stops at the first vertical pair once one generator is clearly ahead)
  icp          Open3D point-to-point ICP from identity (the paper's "standard ICP")
  fpfh-ransac  Open3D FPFH features + RANSAC, refined by the same ICP (a standard global method)
  cpd          rigid Coherent Point Drift from probreg (optional; the paper's Table 3 baseline; scale fixed,
               sigma^2 update corrected), refined by the same ICP

Baselines work in a local frame around the target so UTM coordinates keep their centimetres.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from plotmosaic.align.pair import register_prepared
from plotmosaic.align.pipeline import AlignRequest, align_clouds
from plotmosaic.align.prepare import prepare_cloud
from plotmosaic.config.align import AlignConfig, default_levels
from plotmosaic.config.bench import CpdConfig, IcpConfig, MethodsConfig
from plotmosaic.config.register import placement_align_config
from plotmosaic.errors import InputError, RegistrationFailed
from plotmosaic.io.frame import Frame, to_global_transform
from plotmosaic.io.las import PointCloud

METHODS = ("forestalign", "forestalign-placement", "icp", "fpfh-ransac", "cpd")
OURS = ("forestalign", "forestalign-placement")  # plotmosaic's own: a wrong pose with exit 0 counts


@dataclass(frozen=True)
class MethodOutput:
    transform: np.ndarray  # 4x4 source' file coords -> target file coords
    seconds: float
    # the method reported failure (identity, or its refused estimate, is scored)
    failed: bool = False
    note: str = ""
    # forestalign's own confidence in its answer (also when it refused)
    confidence: float | None = None
    result: object | None = None  # forestalign's PairResult (also when it refused), else None


@dataclass(frozen=True)
class PairInput:
    source: PointCloud
    target: PointCloud
    source_kind: str = "tls"
    target_kind: str = "tls"
    # forestalign: the target prepared once for many trials (a suite's case); None prepares it per call
    target_prepared: object | None = None
    # forestalign: the source's scanner (file coordinates) where the trial knows it, as a TLS file
    # records it (the `paper` protocol moves the source off its own frame)
    source_scanner: np.ndarray | None = None


def available(name: str) -> str | None:
    """None when the method can run here, else why not."""
    if name not in METHODS:
        raise InputError(f"--methods: unknown method {name!r} (choose from {', '.join(METHODS)})")
    if name == "cpd":
        try:
            import probreg  # noqa: F401
        except ImportError:
            return "probreg is not installed (pip install 'plotmosaic[bench]'; it builds with a C++ compiler)"
    return None


def option_names(text: str, allowed, option: str) -> list[str]:
    """A comma-separated option's names, each one of `allowed` (else one InputError naming it)."""
    names = [v.strip() for v in text.split(",") if v.strip()]
    bad = [v for v in names if v not in allowed]
    if bad or not names:
        raise InputError(f"{option}: {bad[0] if bad else text!r} not one of {', '.join(allowed)}")
    return names


def runnable(
    methods: list[str], why_not: Callable[[str], str | None] = available
) -> tuple[list[str], dict[str, str]]:
    """The methods that can run here, and why each other one cannot (printed as it is skipped)."""
    skipped = {m: why for m in methods if (why := why_not(m))}
    for m, why in skipped.items():
        print(f"{m}: skipped, {why}", file=sys.stderr)
    return [m for m in methods if m not in skipped], skipped


def run_method(name: str, pair: PairInput, config: MethodsConfig, seed: int) -> MethodOutput:
    """Run one method once; a method that cannot register is flagged failed and scored as identity
    (so its error is the initial error), or as the estimate it refused when it reports one."""
    start = time.perf_counter()
    try:
        out = _RUNNERS[name](pair, config, seed)
        if isinstance(out, np.ndarray):
            return MethodOutput(out, time.perf_counter() - start)
        return MethodOutput(
            np.asarray(out.transform, dtype=np.float64),
            time.perf_counter() - start,
            confidence=out.confidence,
            result=out,
        )
    except RegistrationFailed as exc:
        # the pipeline refused its own answer (quality gate): score the transform it had, flag the refusal
        result = getattr(exc, "result", None)
        T = np.asarray(result.transform, dtype=np.float64) if result is not None else np.eye(4)
        confidence = getattr(result, "confidence", None)
        return MethodOutput(
            T, time.perf_counter() - start, True, str(exc).splitlines()[0][:200], confidence, result
        )
    except RuntimeError as exc:  # Open3D / probreg numerical trouble counts as a failed trial
        return MethodOutput(
            np.eye(4), time.perf_counter() - start, True, f"{type(exc).__name__}: {exc}"[:200]
        )


# ---------------------------------------------------------------- forestalign


def _forestalign(pair: PairInput, config: MethodsConfig, seed: int, cfg: AlignConfig | None = None):
    """plotmosaic's PairResult (RegistrationFailed when it refuses), with `cfg` (default settings)."""
    cfg = cfg or AlignConfig()
    init = None
    if config.no_coarse:
        cfg = cfg.model_copy(update={"coarse": cfg.coarse.model_copy(update={"enabled": False})})
        init = np.eye(4)
    if pair.target_prepared is None:
        request = AlignRequest(
            source_kind=pair.source_kind,
            target_kind=pair.target_kind,
            config=cfg,
            init=init,
            seed=seed,
        )
        return align_clouds(pair.source, pair.target, request)
    kind = pair.source_kind.lower()
    src = prepare_cloud(
        pair.source, kind, default_levels(kind), cfg, seed, "source", scanner=pair.source_scanner
    )
    return register_prepared(src, pair.target_prepared, cfg, init, seed)


def _forestalign_placement(pair: PairInput, config: MethodsConfig, seed: int):
    """plotmosaic's PairResult as register-plot places a scan on the ALS tile."""
    return _forestalign(pair, config, seed, placement_align_config())


def prepare_target(pair: PairInput, seed: int, scanner: np.ndarray | None = None):
    """The target as forestalign prepares it (default settings), to share over a case's trials;
    `scanner`: where it was scanned from (file coordinates), when known."""
    kind = pair.target_kind.lower()
    return prepare_cloud(
        pair.target, kind, default_levels(kind), AlignConfig(), seed + 1, "target", scanner=scanner
    )


# ---------------------------------------------------------------- Open3D baselines


def _o3d():
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


def _local(pair: PairInput, voxel: float):
    """Both clouds voxel-downsampled in a frame centred on the target."""
    o3d = _o3d()
    frame = Frame.around(pair.target.xyz)
    out = []
    for cloud in (pair.source, pair.target):
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(frame.to_local(cloud.xyz)))
        out.append(pcd.voxel_down_sample(voxel))
    return frame, out[0], out[1]


def _icp_refine(src, tgt, init: np.ndarray, cfg: IcpConfig) -> np.ndarray:
    o3d = _o3d()
    reg = o3d.pipelines.registration
    T = np.asarray(init, dtype=np.float64)
    point_to_point = reg.TransformationEstimationPointToPoint()
    criteria = reg.ICPConvergenceCriteria(max_iteration=cfg.iterations)
    for d in cfg.distances:
        result = reg.registration_icp(src, tgt, d, T, point_to_point, criteria)
        T = np.asarray(result.transformation)
    return T


def _icp(pair: PairInput, config: MethodsConfig, seed: int) -> np.ndarray:
    frame, src, tgt = _local(pair, config.icp.voxel)
    T = _icp_refine(src, tgt, np.eye(4), config.icp)
    return to_global_transform(T, frame, frame)


def _fpfh_ransac(pair: PairInput, config: MethodsConfig, seed: int) -> np.ndarray:
    o3d = _o3d()
    reg = o3d.pipelines.registration
    cfg = config.fpfh
    v = cfg.voxel
    frame, src, tgt = _local(pair, v)
    rng = np.random.default_rng(seed)
    keys, feats = [], []
    for pcd in (src, tgt):
        pcd.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=2 * v, max_nn=cfg.max_nn_normal)
        )
        f = reg.compute_fpfh_feature(
            pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * v, max_nn=cfg.max_nn_feature)
        )
        keep = np.arange(len(pcd.points))
        if len(keep) > cfg.max_points:  # features from the full cloud, matched on a subset
            keep = np.sort(rng.choice(len(keep), cfg.max_points, replace=False))
        sub = reg.Feature()
        sub.data = np.asarray(f.data)[:, keep]
        keys.append(pcd.select_by_index(keep.tolist()))
        feats.append(sub)
    o3d.utility.random.seed(seed)  # determinism: Open3D's RANSAC draws from its own generator
    ransac = reg.registration_ransac_based_on_feature_matching(
        keys[0], keys[1], feats[0], feats[1], True, 1.5 * v,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * v)],
        reg.RANSACConvergenceCriteria(cfg.ransac_iterations, cfg.ransac_confidence),
    )  # fmt: skip
    if ransac.fitness == 0.0:
        raise RegistrationFailed("FPFH + RANSAC found no consistent correspondences")
    _, src_fine, tgt_fine = _local(pair, config.icp.voxel)
    T = _icp_refine(src_fine, tgt_fine, np.asarray(ransac.transformation), config.icp)
    return to_global_transform(T, frame, frame)


# ---------------------------------------------------------------- probreg CPD


def _rigid_cpd(source: np.ndarray, target: np.ndarray, cfg: CpdConfig) -> np.ndarray:
    """Rigid CPD (scale fixed at 1) of `source` onto `target`: 4x4.

    probreg 0.3.8's RigidCPD with update_scale=False updates sigma^2 with -tr(A'R) where the fixed-scale
    M-step has -2 tr(A'R) (Myronenko and Song 2010, Fig. 2 with s = 1), so sigma^2 stays near the
    clouds' spread and CPD stops at the coarse, centroid-matching pose, even from the true pose.
    This M-step is probreg's with that term corrected; the E-step is probreg's.
    """
    from probreg import cpd, transformation  # optional (the bench extra): only when CPD runs

    class FixedScaleRigidCPD(cpd.RigidCPD):
        def maximization_step(self, target, estep_res, sigma2_p=None):
            pt1, p1, px, n_p = estep_res
            y, x = self._source[:, :3], target[:, :3]
            mu_x, mu_y = px.sum(axis=0) / n_p, y.T @ p1 / n_p
            y_hat, x_hat = y - mu_y, x - mu_x
            a = px.T @ y_hat - np.outer(mu_x, p1 @ y_hat)
            u, _, vh = np.linalg.svd(a)
            rot = (u * [1.0, 1.0, np.linalg.det(u @ vh)]) @ vh
            tr_atr = float(np.trace(a.T @ rot))
            tr_xx = float(np.sum(pt1 * np.sum(x_hat**2, axis=1)))
            tr_yy = float(np.sum(p1 * np.sum(y_hat**2, axis=1)))
            sigma2 = max((tr_xx + tr_yy - 2.0 * tr_atr) / (3.0 * n_p), np.finfo(np.float32).eps)
            q = (tr_xx - 2.0 * tr_atr + tr_yy) / (2.0 * sigma2) + 1.5 * n_p * np.log(sigma2)
            tf = transformation.RigidTransformation(rot, mu_x - rot @ mu_y, 1.0)
            return cpd.MstepResult(tf, sigma2, q)

    solver = FixedScaleRigidCPD(source, update_scale=False)
    tf = solver.registration(target, w=cfg.w, maxiter=cfg.maxiter, tol=cfg.tol).transformation
    T = np.eye(4)
    T[:3, :3] = np.asarray(tf.rot)
    T[:3, 3] = np.asarray(tf.t)
    return T


def _cpd(pair: PairInput, config: MethodsConfig, seed: int) -> np.ndarray:
    cfg = config.cpd
    frame, src, tgt = _local(pair, cfg.voxel)
    rng = np.random.default_rng(seed)
    xyz = []
    for pcd in (src, tgt):
        pts = np.asarray(pcd.points)
        if len(pts) > cfg.points:
            pts = pts[np.sort(rng.choice(len(pts), cfg.points, replace=False))]
        xyz.append(pts)
    T = _rigid_cpd(xyz[0], xyz[1], cfg)
    if not np.isfinite(T).all():
        raise RegistrationFailed("CPD diverged")
    # CPD on a few thousand points stops at decimetres: the same ICP as fpfh-ransac
    if config.cpd.refine:
        _, src_fine, tgt_fine = _local(pair, config.icp.voxel)
        T = _icp_refine(src_fine, tgt_fine, T, config.icp)
    return to_global_transform(T, frame, frame)


_RUNNERS = {
    "forestalign": _forestalign,
    "forestalign-placement": _forestalign_placement,
    "icp": _icp,
    "fpfh-ransac": _fpfh_ransac,
    "cpd": _cpd,
}
