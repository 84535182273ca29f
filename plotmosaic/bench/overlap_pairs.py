"""View pairs cut at a chosen overlap for benchmarks/bench_overlap.py: real separated ground views, not crops.

A *candidate* is one seeded geometry: two scanner positions `spacing` apart on a line through a point
near the cloud's centre (any heading), each seeing only what is within `max_range` of it and in its
line of sight (simulate/from_cloud.py's cut), for the real clouds; a 2 x 2 grid of the simulator's
`understorey` preset `spacing` apart with TLS range `max_range` for `sim` (its six scan pairs, the
higher-numbered scan onto the lower). Overlap is what the spacing and range leave: measured at the
true pose both ways (share of a scan's points with a point of the other within 25 cm,
bench/overlap.py) and binned on the larger of the two, so a pair in [0.10, 0.15) shares less than
15 % of either scan (the strict reading: views of uneven density can share 0.09 of one and 0.32 of
the other). Candidates are taken in seeded order and each pair fills its bin (at most two pairs of
one simulated scene a bin) until every bin holds `per_bin` pairs, so the catalogue depends on the
seed alone; measured candidates and the chosen pairs are kept on disk and a re-run cuts nothing it
has.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from plotmosaic.bench.overlap import overlap_fraction
from plotmosaic.bench.real_cases import UNDERSTOREY_POINTS, data_dir
from plotmosaic.config.simulate import grid_layout
from plotmosaic.errors import InputError
from plotmosaic.io.atomic import atomic_output, write_text_atomic
from plotmosaic.io.frame import apply_transform, inverse
from plotmosaic.io.las import read_cloud
from plotmosaic.poses import load_poses
from plotmosaic.simulate.from_cloud import cut_views
from plotmosaic.simulate.run import simulate

SOURCES = ("mls", "treels", "sim")
DEFAULT_EDGES = (0.05, 0.10, 0.15, 0.20, 0.30, 0.50)
PAIRS_PER_BIN = 5  # distinct geometries a bin's draws cycle over
FILES = {"mls": "spanner/MLS_Clip.laz", "treels": "treels/pine_plot.laz"}
# Where candidates are drawn from: a range (m) and a spacing as a multiple of it, which sets the
# overlap more directly than the spacing alone; wide enough to span 0.05-0.5 on each cloud (MLS clip
# 27 x 26 m, TreeLS plot 10 x 10 m; a position off the cloud is skipped before any cut).
SAMPLING = {
    "mls": {"max_range": (9.0, 15.0), "ratio": (0.6, 1.8), "shift": 2.0},
    "treels": {"max_range": (4.0, 7.0), "ratio": (0.9, 1.9), "shift": 1.0},
    "sim": {"max_range": (10.0, 18.0), "ratio": (0.5, 1.1), "shift": 0.0},
}
MAX_CANDIDATES = {"mls": 200, "treels": 200, "sim": 40}  # sim: six pairs a candidate
PER_CANDIDATE_BIN = 2  # pairs of one candidate (one simulated scene) a bin takes, at most
EDGE_MARGIN = 0.5  # a scanner stands at least this far inside the cloud's xy box
SIM_POINTS = UNDERSTOREY_POINTS  # as the real suite's sim-understorey case


Bin = tuple[float, float]


def parse_bins(text: str) -> list[Bin]:
    """'0.05,0.10,0.15' -> [(0.05, 0.10), (0.10, 0.15)]: increasing edges in (0, 1]."""
    try:
        edges = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"--bins: {text!r} is not comma-separated numbers") from None
    if len(edges) < 2 or any(b <= a for a, b in zip(edges, edges[1:])):
        raise InputError(f"--bins: {text!r} needs at least two increasing edges")
    if edges[0] <= 0 or edges[-1] > 1:
        raise InputError(f"--bins: edges must lie in (0, 1], got {text!r}")
    return list(zip(edges, edges[1:]))


def bin_of(overlap: float, bins: list[Bin]) -> Bin | None:
    """The bin holding `overlap`: [lo, hi), the last one closed [lo, hi]; None outside them all."""
    for k, (lo, hi) in enumerate(bins):
        if lo <= overlap < hi or (k == len(bins) - 1 and overlap == hi):
            return (lo, hi)
    return None


def bin_label(b: Bin) -> str:
    return f"{b[0]:.2f}-{b[1]:.2f}"


def _stable(text: str) -> int:
    return int(hashlib.sha256(text.encode()).hexdigest()[:8], 16)


@dataclass(frozen=True)
class Geometry:
    source: str
    index: int
    seed: int
    spacing: float
    max_range: float
    angle_deg: float
    shift: tuple[float, float]


def candidate(source: str, seed: int, index: int) -> Geometry:
    """The `index`-th geometry of `source`: a function of (source, seed, index) only."""
    if source not in SAMPLING:
        raise InputError(f"--sources: unknown source {source!r} (choose from {', '.join(SOURCES)})")
    s = SAMPLING[source]
    rng = np.random.default_rng(np.random.SeedSequence([seed, _stable(source), index]))
    max_range = float(rng.uniform(*s["max_range"]))
    spacing = float(rng.uniform(*s["ratio"]) * max_range)
    angle = float(rng.uniform(0.0, 180.0))
    shift = tuple(float(v) for v in rng.uniform(-s["shift"], s["shift"], 2))
    return Geometry(source, index, seed, spacing, max_range, angle, shift)


@dataclass(frozen=True)
class ViewPair:
    source: np.ndarray  # (n, 3) the source scan in its own frame (scanner at the origin)
    target: np.ndarray  # (m, 3) the target scan in its own frame (scanner at the origin)
    truth: np.ndarray  # 4x4 source frame -> target frame
    up: np.ndarray  # (3,) the world's up in the target frame (what a levelled scanner records)
    overlap_st: float  # share of source points with a target point within 25 cm at the truth
    overlap_ts: float  # the same, target onto source
    name: str = ""
    geometry: dict = field(default_factory=dict)

    @property
    def overlap(self) -> float:
        """The pair's overlap for binning: the larger of the two shares."""
        return max(self.overlap_st, self.overlap_ts)


def measure(source: np.ndarray, target: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(source -> target, target -> source) overlap at the true pose."""
    aligned = apply_transform(truth, source)
    return overlap_fraction(aligned, target), overlap_fraction(target, aligned)


@dataclass(frozen=True)
class _Cloud:
    xyz: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


_CLOUDS: dict[str, _Cloud] = {}


def _cloud(path: Path) -> _Cloud:
    key = str(path)
    if key not in _CLOUDS:
        xyz = read_cloud(path, attributes=False).xyz
        _CLOUDS[key] = _Cloud(xyz, xyz.min(axis=0), xyz.max(axis=0))
    return _CLOUDS[key]


def positions(geom: Geometry, lo: np.ndarray, hi: np.ndarray) -> list[tuple[float, float]]:
    """The two scanner positions (x, y) of a real-cloud candidate: target first, then source."""
    centre = (lo[:2] + hi[:2]) / 2.0 + np.asarray(geom.shift)
    a = np.radians(geom.angle_deg)
    half = 0.5 * geom.spacing * np.array([np.cos(a), np.sin(a)])
    return [tuple(float(v) for v in centre - half), tuple(float(v) for v in centre + half)]


def _cut_real(geom: Geometry, data: str | Path | None) -> list[ViewPair]:
    cloud = _cloud(data_dir(data) / FILES[geom.source])
    pos = positions(geom, cloud.lo, cloud.hi)
    inside = all(
        cloud.lo[i] + EDGE_MARGIN <= p[i] <= cloud.hi[i] - EDGE_MARGIN for p in pos for i in (0, 1)
    )
    if not inside:
        raise InputError("a scanner position lies outside the cloud")
    target, source = cut_views(
        cloud.xyz, pos, geom.seed * 100_003 + geom.index, max_range=geom.max_range
    )
    truth = inverse(target.truth) @ source.truth
    up = target.truth[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    st, ts = measure(source.points, target.points, truth)
    meta = {
        **asdict(geom),
        "distance_m": float(np.linalg.norm(source.position[:2] - target.position[:2])),
    }
    return [ViewPair(source.points, target.points, truth, up, st, ts, "S1->S0", meta)]


def _cut_sim(geom: Geometry) -> list[ViewPair]:
    """The understorey preset on a 2 x 2 grid: what `plotmosaic simulate OUT --preset understorey
    --scan-grid 2 --scan-spacing S --max-range R --points-per-scan 200000 --seed K` writes."""
    with tempfile.TemporaryDirectory(prefix="plotmosaic-overlap-") as tmp:
        result = simulate(
            tmp,
            "understorey",
            seed=geom.seed * 100_003 + geom.index,
            points_per_scan=SIM_POINTS,
            max_range=geom.max_range,
            scan_layout=grid_layout(2, geom.spacing),
        )
        poses = load_poses(result.ground_truth_path)
        ids = sorted(result.scan_paths)
        scans = {i: read_cloud(result.scan_paths[i], attributes=False).xyz for i in ids}
    pairs = []
    for t in range(len(ids)):
        for s in range(t + 1, len(ids)):
            Ts, Tt = poses.transform(ids[s]), poses.transform(ids[t])
            truth = inverse(Tt) @ Ts
            st, ts = measure(scans[ids[s]], scans[ids[t]], truth)
            meta = {**asdict(geom), "distance_m": float(np.linalg.norm(Ts[:2, 3] - Tt[:2, 3]))}
            up = Tt[:3, :3].T @ np.array([0.0, 0.0, 1.0])
            name = f"{ids[s]}->{ids[t]}"
            pairs.append(ViewPair(scans[ids[s]], scans[ids[t]], truth, up, st, ts, name, meta))
    return pairs


def cut_candidate(geom: Geometry, data: str | Path | None = None) -> list[ViewPair]:
    """Every pair of one candidate (one for a real cloud, six for the simulator), overlaps measured."""
    if geom.source == "sim":
        return _cut_sim(geom)
    return _cut_real(geom, data)


# ---------------------------------------------------------------- files


def save_pair(path: Path, pair: ViewPair) -> Path:
    """The pair as one .npz (float32 clouds: scanner frames span tens of metres, micrometres kept)."""
    with atomic_output(path) as tmp, open(tmp, "wb") as fh:
        np.savez(
            fh,
            source=pair.source.astype(np.float32),
            target=pair.target.astype(np.float32),
            truth=pair.truth,
            up=pair.up,
            overlap=np.array([pair.overlap_st, pair.overlap_ts]),
            meta=np.array(json.dumps({"name": pair.name, "geometry": pair.geometry})),
        )
    return path


def load_pair(path: str | Path) -> ViewPair:
    with np.load(path) as z:
        meta = json.loads(str(z["meta"]))
        st, ts = (float(v) for v in z["overlap"])
        source, target = z["source"].astype(np.float64), z["target"].astype(np.float64)
        truth, up = (np.asarray(z[k], dtype=np.float64) for k in ("truth", "up"))
        return ViewPair(source, target, truth, up, st, ts, meta["name"], meta["geometry"])


@dataclass(frozen=True)
class PairRef:
    """A catalogue entry: where the pair is and what it measured (what a trial needs to know)."""

    id: str  # "<source>-c<candidate>-p<pair>"
    path: str
    overlap_st: float
    overlap_ts: float
    spacing: float
    max_range: float
    distance_m: float


def _index_path(folder: Path, source: str, seed: int) -> Path:
    return folder / f"{source}-seed{seed}-candidates.json"


def _read_index(path: Path) -> dict[int, dict]:
    if not path.is_file():
        return {}
    try:
        return {int(k): v for k, v in json.loads(path.read_text()).items()}
    except (ValueError, AttributeError):
        return {}  # a damaged index is rebuilt: the cuts are deterministic


def build_catalogue(
    source: str,
    bins: list[Bin],
    per_bin: int,
    seed: int,
    folder: str | Path,
    data: str | Path | None = None,
    max_candidates: int | None = None,
    log: Callable[[str], None] | None = None,
) -> dict[Bin, list[PairRef]]:
    """Up to `per_bin` pairs of `source` in each bin, the first ones in candidate order.

    Measured candidates are kept in FOLDER/<source>-seed<seed>-candidates.json and chosen pairs as
    FOLDER/<source>-seed<seed>/<id>.npz, so a re-run (or other bins) cuts only what it lacks.
    """
    folder = Path(folder)
    if source != "sim" and not (data_dir(data) / FILES[source]).is_file():
        raise InputError(
            f"{data_dir(data) / FILES[source]}: not found (source {source!r} needs it)"
        )
    index_path = _index_path(folder, source, seed)
    index = _read_index(index_path)
    chosen: dict[Bin, list[PairRef]] = {b: [] for b in bins}
    limit = MAX_CANDIDATES[source] if max_candidates is None else max_candidates
    for k in range(limit):
        if all(len(v) >= per_bin for v in chosen.values()):
            break
        geom = candidate(source, seed, k)
        cut: list[ViewPair] | None = None
        if k in index and index[k]["geometry"] != json.loads(json.dumps(asdict(geom))):
            del index[k]  # measured under other sampling settings: cut again
            for old in (folder / f"{source}-seed{seed}").glob(f"{source}-c{k}-p*.npz"):
                old.unlink()
        if k not in index:
            try:
                cut = cut_candidate(geom, data)
                index[k] = {
                    "geometry": asdict(geom),
                    "pairs": [
                        {"name": p.name, "overlap": [p.overlap_st, p.overlap_ts], **p.geometry}
                        for p in cut
                    ],
                }
            except InputError as exc:  # a position off the cloud or in a trunk: no pair
                index[k] = {"geometry": asdict(geom), "pairs": [], "error": str(exc)}
            write_text_atomic(index_path, json.dumps(index, indent=1, default=float))
        for j, rec in enumerate(index[k]["pairs"]):
            st, ts = rec["overlap"]
            b = bin_of(max(st, ts), bins)
            if b is None or len(chosen[b]) >= per_bin:
                continue
            pid = f"{source}-c{k}-p{j}"
            if sum(r.id.startswith(f"{source}-c{k}-") for r in chosen[b]) >= PER_CANDIDATE_BIN:
                continue
            path = folder / f"{source}-seed{seed}" / f"{pid}.npz"
            if not path.is_file():
                cut = cut if cut is not None else cut_candidate(geom, data)
                save_pair(path, cut[j])
            ref = PairRef(
                pid, str(path), st, ts, geom.spacing, geom.max_range, float(rec["distance_m"])
            )
            chosen[b].append(ref)
            if log:
                log(
                    f"  {source} [{bin_label(b)}] {pid}: overlap {st:.3f} / {ts:.3f}, "
                    f"{rec['distance_m']:.1f} m apart, range {geom.max_range:.1f} m"
                )
    return chosen
