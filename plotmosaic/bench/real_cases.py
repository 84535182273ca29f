"""The real-data benchmark suite's cases: source, target, truth and kinds built from ../shared/data + the simulator.

    build_case(name, data_dir=None, seed=0) -> RealCase   (CASES lists the names)
    RealCase.source, .target   PointCloud (file coordinates; each source in its own random frame)
    RealCase.truth             4x4 source file coordinates -> target file coordinates
    RealCase.source_kind, .target_kind, .note (where the truth comes from), .meta (figures)

Cases (issue 15's suite):
  treels-2views    two virtual scans of the TreeLS pine plot 7 m apart (exact truth)
  mls-2views       two ground-based virtual scans of the spanner MLS clip 8 m apart (exact truth)
  mls-boxed6m      the same pair, the source cut to 6 m range: a scanner boxed in by understorey (exact truth)
  uas-strip-als    a 5 m x 27 m strip of the UAS clip onto the ALS clip (refined truth)
  uas-als          the whole UAS clip onto the ALS clip (refined truth)
  mls-uas          the whole MLS clip onto the UAS clip (refined truth, MLS placement is approximate)
  sim-understorey  the simulator's `understorey` preset, scan 1 onto scan 0 7 m away (exact truth)
  sim-small        (on request) the simulator's `small` preset, scan 1 onto scan 0 (exact truth)
  mls-views12m     (on request) two views of the MLS clip 12 m apart with 10 m range: a sparse survey's neighbours

Refined truth: the clips' own co-registration refined by three independent fine methods (point-to-point ICP,
point-to-plane ICP, generalised ICP, each the sparser cloud onto the denser: ALS onto UAS, i.e. the reverse
direction); the truth is their mean, their spread is in `meta`.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plotmosaic.bench.refined_truth import refine_truth
from plotmosaic.config.simulate import TlsConfig
from plotmosaic.errors import InputError
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.frame import apply_transform, inverse, translation
from plotmosaic.io.las import PointCloud, read_cloud
from plotmosaic.poses import load_poses
from plotmosaic.simulate.from_cloud import cut_views, grid_positions
from plotmosaic.simulate.run import simulate
from plotmosaic.simulate.tls import random_pose

# beside the work tree, as in tests/conftest.py
DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
CASES = (
    "treels-2views",
    "mls-2views",
    "mls-boxed6m",
    "uas-strip-als",
    "uas-als",
    "mls-uas",
    "sim-understorey",
)
# on request: the simulator's `small` preset, a TLS pair (the old coarse suite); a sparse pair
EXTRA_CASES = ("sim-small", "mls-views12m")
ALL_CASES = CASES + EXTRA_CASES
STRIP_WIDTH = 5.0  # metres: a narrow drone strip (<= 6 m)
TREELS_SPACING = 7.0
MLS_SPACING = 8.0
BOXED_RANGE = 6.0
SPARSE_SPACING, SPARSE_RANGE = 12.0, 10.0  # a sparse survey's neighbours (issue 54)
UNDERSTOREY_POINTS = 200_000  # points per simulated scan: enough for the pipeline, a quick build


@dataclass(frozen=True)
class RealCase:
    name: str
    source: PointCloud
    target: PointCloud
    truth: np.ndarray  # source file -> target file
    source_kind: str
    target_kind: str
    note: str
    meta: dict = field(default_factory=dict)
    # each cloud in its own scanner frame (the scanner at the file origin), as a TLS file records
    # it; virtual views do not crowd around it as a real scan does, so the suite gives it
    at_scanner: bool = False


def data_dir(path: str | Path | None = None) -> Path:
    d = Path(path) if path is not None else DATA
    if not d.is_dir():
        raise InputError(f"{d}: real-data folder not found (expected spanner/ and treels/ in it)")
    return d


def _file(root: Path, rel: str) -> Path:
    p = root / rel
    if not p.is_file():
        raise InputError(f"{p}: not found (the real-data suite needs it)")
    return p


def random_frame(
    xyz: np.ndarray, rng: np.random.Generator, max_tilt_deg: float = 2.0
) -> np.ndarray:
    """A rigid G putting a cloud in its own frame: random heading and small tilt, centre moved near the origin."""
    centre = (xyz.min(axis=0) + xyz.max(axis=0)) / 2.0
    R = random_pose(np.zeros(3), TlsConfig(max_tilt_deg=max_tilt_deg), rng)[:3, :3]
    G = np.eye(4)
    G[:3, :3] = R.T
    return translation(rng.uniform(-10.0, 10.0, 3)) @ G @ translation(-centre)


def _moved(cloud: PointCloud, G: np.ndarray) -> PointCloud:
    return PointCloud(apply_transform(G, cloud.xyz), cloud.attrs, None)


@functools.lru_cache(maxsize=8)
def _spanner(root: str, name: str) -> PointCloud:
    return read_cloud(_file(Path(root), f"spanner/{name}_Clip.laz"), attributes=False)


# metres: two dense clips need less detail to agree
REFINE_VOXEL = {("UAS", "ALS"): 0.1, ("MLS", "UAS"): 0.15}


def cache_dir() -> Path:
    """Where refined truths are kept between runs (they take minutes on a busy 2-core box)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "plotmosaic" / "real-truth"


@functools.lru_cache(maxsize=4)
def _refined(root: str, source: str, target: str) -> tuple[np.ndarray, dict]:
    """Refined truth of two clips, cached on disk by the files' contents and the settings."""
    voxel = REFINE_VOXEL.get((source, target), 0.1)
    paths = [_file(Path(root), f"spanner/{n}_Clip.laz") for n in (source, target)]
    key = hashlib.sha256(
        b"".join(p.read_bytes() for p in paths) + f"v1 {voxel}".encode()
    ).hexdigest()[:20]
    path = cache_dir() / f"{source}-{target}-{key}.json"
    if path.is_file():
        try:
            data = json.loads(path.read_text())
            return np.asarray(data["transform"], dtype=np.float64).reshape(4, 4), data["meta"]
        except (ValueError, KeyError, TypeError):
            pass  # a damaged cache entry is recomputed
    T, meta = refine_truth(_spanner(root, source).xyz, _spanner(root, target).xyz, voxel=voxel)
    meta = {**meta, "voxel": voxel}
    try:
        write_text_atomic(path, json.dumps({"transform": T.tolist(), "meta": meta}))
    except (OSError, InputError):
        pass  # no cache: the next run refines again
    return T, meta


# ---------------------------------------------------------------- cases


def _views_case(
    name: str,
    cloud: PointCloud,
    spacing: float,
    seed: int,
    note: str,
    boxed: float | None = None,
    max_range: float | None = None,
) -> RealCase:
    positions = grid_positions(cloud.xyz, 2, spacing)
    reach = {} if max_range is None else {"max_range": max_range}
    target, source = cut_views(cloud.xyz, positions, seed, **reach)
    if boxed is not None:
        (source,) = cut_views(cloud.xyz, [tuple(source.position)], seed + 1, max_range=boxed)
    truth = inverse(target.truth) @ source.truth
    dist = float(np.linalg.norm(source.position[:2] - target.position[:2]))
    meta = {
        "distance_m": dist,
        "source_points": len(source.points),
        "target_points": len(target.points),
        "source_within_5m": source.stats["within_5m"],
        "target_within_5m": target.stats["within_5m"],
    }
    return RealCase(
        name,
        PointCloud(source.points),
        PointCloud(target.points),
        truth,
        "tls",
        "tls",
        f"{note}; scanners {dist:.2f} m apart, exact truth (both views cut from one cloud)",
        meta,
        at_scanner=True,
    )


def treels_2views(root: Path, seed: int = 0) -> RealCase:
    cloud = read_cloud(_file(root, "treels/pine_plot.laz"), attributes=False)
    return _views_case(
        "treels-2views", cloud, TREELS_SPACING, seed, "TreeLS pine plot, two virtual scans"
    )


def mls_2views(root: Path, seed: int = 0) -> RealCase:
    return _views_case(
        "mls-2views",
        _spanner(str(root), "MLS"),
        MLS_SPACING,
        seed,
        "spanner MLS clip, two ground-based virtual scans",
    )


def mls_boxed(root: Path, seed: int = 0) -> RealCase:
    return _views_case(
        "mls-boxed6m",
        _spanner(str(root), "MLS"),
        MLS_SPACING,
        seed,
        f"spanner MLS clip, two ground-based virtual scans, the source cut to {BOXED_RANGE:g} m range",
        boxed=BOXED_RANGE,
    )


def mls_views12(root: Path, seed: int = 0) -> RealCase:
    return _views_case(
        "mls-views12m",
        _spanner(str(root), "MLS"),
        SPARSE_SPACING,
        seed,
        f"spanner MLS clip, two ground-based virtual scans {SPARSE_SPACING:g} m apart with"
        f" {SPARSE_RANGE:g} m range",
        max_range=SPARSE_RANGE,
    )


def _airborne_case(
    name: str,
    root: Path,
    source: str,
    target: str,
    seed: int,
    kinds: tuple[str, str],
    strip: bool = False,
) -> RealCase:
    src, tgt = _spanner(str(root), source), _spanner(str(root), target)
    T_ref, meta = _refined(str(root), source, target)
    note = (
        f"{source} clip onto {target} clip; truth = their co-registration refined by {', '.join(meta['methods'])} ({meta['direction']}) "
        f"(spread {meta['spread_deg']:.3f} deg / {100 * meta['spread_m']:.1f} cm, moved {meta['from_init_deg']:.3f} deg / "
        f"{100 * meta['from_init_m']:.1f} cm from the files' own placement)"
    )
    if strip:  # along the longer side, through the centre
        xy = src.xyz[:, :2]
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        axis = int(np.argmax(hi - lo))
        mid = (lo[1 - axis] + hi[1 - axis]) / 2.0
        src = src.select(np.abs(xy[:, 1 - axis] - mid) <= STRIP_WIDTH / 2.0)
        meta = {**meta, "strip_m": [STRIP_WIDTH, float(hi[axis] - lo[axis])]}
        note = f"a {STRIP_WIDTH:g} m x {hi[axis] - lo[axis]:.1f} m strip of the " + note
    G = random_frame(src.xyz, np.random.default_rng(np.random.SeedSequence([seed, 77])))
    meta = {**meta, "source_points": len(src), "target_points": len(tgt)}
    return RealCase(name, _moved(src, G), tgt, T_ref @ inverse(G), kinds[0], kinds[1], note, meta)


def uas_strip_als(root: Path, seed: int = 0) -> RealCase:
    return _airborne_case("uas-strip-als", root, "UAS", "ALS", seed, ("uls", "als"), strip=True)


def uas_als(root: Path, seed: int = 0) -> RealCase:
    return _airborne_case("uas-als", root, "UAS", "ALS", seed, ("uls", "als"))


def mls_uas(root: Path, seed: int = 0) -> RealCase:
    return _airborne_case("mls-uas", root, "MLS", "UAS", seed, ("mls", "uls"))


def _sim_case(
    name: str, preset: str, seed: int, points_per_scan: int | None, pair=("P1-S1", "P1-S0")
) -> RealCase:
    """A simulator preset into a temporary folder (removed after reading), scan pair[0] onto pair[1]."""
    with tempfile.TemporaryDirectory(prefix=f"plotmosaic-{preset}-") as tmp:
        kw = {} if points_per_scan is None else {"points_per_scan": points_per_scan}
        result = simulate(tmp, preset, seed=seed, **kw)
        poses = load_poses(result.ground_truth_path)
        src = read_cloud(result.scan_paths[pair[0]], attributes=False)
        tgt = read_cloud(result.scan_paths[pair[1]], attributes=False)
    Ts, Tt = poses.transform(pair[0]), poses.transform(pair[1])
    within = [float(np.mean(np.linalg.norm(c.xyz, axis=1) <= 5.0)) for c in (src, tgt)]
    dist = float(np.linalg.norm(Ts[:2, 3] - Tt[:2, 3]))
    meta = {
        "distance_m": dist,
        "source_points": len(src),
        "target_points": len(tgt),
        "source_within_5m": within[0],
        "target_within_5m": within[1],
    }
    pts = "" if points_per_scan is None else f", {points_per_scan:,} points a scan"
    note = (
        f"simulated (preset {preset}, seed {seed}{pts}), scans {dist:.2f} m apart, "
        f"{100 * within[0]:.0f} % / {100 * within[1]:.0f} % of points within 5 m; exact truth"
    )
    return RealCase(name, src, tgt, inverse(Tt) @ Ts, "tls", "tls", note, meta)


def sim_understorey(
    root: Path | None = None, seed: int = 0, points_per_scan: int = UNDERSTOREY_POINTS
) -> RealCase:
    """The `understorey` preset (dense understorey), scan 1 onto scan 0 7 m away."""
    return _sim_case("sim-understorey", "understorey", seed, points_per_scan)


def sim_small(root: Path | None = None, seed: int = 0) -> RealCase:
    """The `small` preset, scan 1 onto scan 0 (the old coarse suite's simulated TLS pair)."""
    return _sim_case("sim-small", "small", seed, None)


BUILDERS = {
    "treels-2views": treels_2views,
    "mls-2views": mls_2views,
    "mls-boxed6m": mls_boxed,
    "uas-strip-als": uas_strip_als,
    "uas-als": uas_als,
    "mls-uas": mls_uas,
    "sim-understorey": sim_understorey,
    "sim-small": sim_small,
    "mls-views12m": mls_views12,
}


def build_case(name: str, data: str | Path | None = None, seed: int = 0) -> RealCase:
    """One case of the suite by name (see the module docstring)."""
    if name not in BUILDERS:
        raise InputError(f"--cases: unknown case {name!r} (choose from {', '.join(ALL_CASES)})")
    if name.startswith("sim-"):
        return BUILDERS[name](None, seed)
    return BUILDERS[name](data_dir(data), seed)
