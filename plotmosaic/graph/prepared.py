"""The prepared-cloud cache: each scan read and prepared once per run, kept under DIR/prepared/.

One `.npz` per scan, keyed by the file's content hash, its kind and levels, the align settings, the
seed and the plotmosaic version, so every pair, plot, worker and re-run (and tie-to-als) shares it.
Arrays are stored as such and the rest as JSON (no pickle: nothing in the folder can run code);
the KD-tree and the lazy ICP-target normals are rebuilt on load, which is cheap beside reading
and preparing the scan. Writes are atomic; a damaged entry is prepared again with one warning line.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import sys
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic import __version__
from plotmosaic.align.normals import LazyNormals
from plotmosaic.align.prepare import PreparedCloud, prepare_cloud
from plotmosaic.config.align import AlignConfig, StemNormalConfig, default_levels
from plotmosaic.config.reading import ReadingConfig
from plotmosaic.graph.cache import file_hash, settings_json
from plotmosaic.io.atomic import atomic_output
from plotmosaic.io.bounded import over_budget, read_scan_points
from plotmosaic.io.frame import Frame

FORMAT = 2  # 2: the stem-normal settings of target_normals
_REBUILT = ("tree", "target_normals")  # derived from `points` on load
_FIELDS = tuple(f.name for f in dataclasses.fields(PreparedCloud))


def prepared_key(
    path,
    kind: str,
    levels: int | None,
    config: AlignConfig,
    seed: int,
    reading: ReadingConfig | None = None,
) -> str:
    """What determines a prepared cloud (the role in a pair does not: one preparation serves both);
    the reading budget only for a scan it thins (`reading` None: the default budget)."""
    parts = {
        "file": file_hash(path),
        "kind": kind,
        "levels": levels,
        "config": json.loads(settings_json(config)),
        "seed": seed,
        "version": __version__,
        "format": FORMAT,
        "fields": _FIELDS,
    }
    reading = reading or ReadingConfig()
    if over_budget(path, reading):
        parts["read"] = reading.model_dump()
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:32]


def _plain(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def save_prepared(path: str | Path, cloud: PreparedCloud) -> Path:
    """Write `cloud` atomically as one .npz (arrays + a JSON "meta" entry)."""
    arrays, meta = {}, {}
    for name in _FIELDS:
        if name in _REBUILT:
            continue
        value = getattr(cloud, name)
        if name == "frame":
            arrays["frame_offset"] = np.asarray(value.offset, dtype=np.float64)
        elif isinstance(value, np.ndarray):
            arrays[name] = value
        else:
            meta[name] = value
    meta["normal_max_nn"] = cloud.target_normals.max_nn
    stems = cloud.target_normals.stems
    meta["stem_normals"] = None if stems is None else stems.model_dump()
    arrays["meta"] = np.frombuffer(json.dumps(meta, default=_plain).encode(), dtype=np.uint8)
    with atomic_output(path) as tmp:
        # a file object: np.savez would append ".npz" to the temporary name
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
    return Path(path)


def load_prepared(path: str | Path) -> PreparedCloud:
    """The cloud saved by `save_prepared`; raises ValueError (or OSError) when the file is damaged."""
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(arrays.pop("meta").tobytes().decode())
    max_nn = meta.pop("normal_max_nn")
    stems = meta.pop("stem_normals", None)
    stems = None if stems is None else StemNormalConfig(**stems)
    values = {**meta, **{k: v for k, v in arrays.items() if k != "frame_offset"}}
    values["frame"] = Frame(arrays["frame_offset"])
    points = values["points"]
    if points.ndim != 2 or points.shape[1] != 3 or not len(points):
        raise ValueError("points are not an (N, 3) array")
    values["tree"] = tree = cKDTree(points, balanced_tree=False, compact_nodes=False)
    values["target_normals"] = LazyNormals(points, tree, values["normal_radius"], max_nn, stems)
    missing = [n for n in _FIELDS if n not in values]
    if missing:
        raise ValueError(f"missing {', '.join(missing)}")
    if len(values["levels"]) != len(values["level_points"]):
        raise ValueError("levels and level points differ in length")
    return PreparedCloud(**{n: values[n] for n in _FIELDS})


def load_points(path: str | Path) -> np.ndarray:
    """Just the delta0 points of a cached cloud, in file coordinates (pictures: no tree, no re-read of the scan)."""
    with np.load(path, allow_pickle=False) as data:
        return data["points"] + data["frame_offset"]


def points_reader(
    entries: dict[str, Path],
    reading: ReadingConfig | None = None,
    config: AlignConfig | None = None,
):
    """A reader for the report's pictures: scan file -> points, from its prepared cloud when cached
    (`entries`: scan file path -> cache entry), else from the file (a damaged or missing entry)
    as a prepare job with `config` reads it, within the budget `reading` (None: the defaults)."""

    def read(path) -> np.ndarray:
        cached = entries.get(str(path))
        if cached is not None and Path(cached).is_file():
            try:
                return load_points(cached)
            except Exception:  # damaged entry: the scan itself
                pass
        return read_scan_points(path, reading or ReadingConfig(), config or AlignConfig()).xyz

    return read


@dataclass(frozen=True)
class PrepareJob:
    """One scan to read and prepare into the cache (plain data: pickles to any process or machine)."""

    key: str
    scan: str  # scan id, for messages
    path: str
    kind: str
    levels: int | None
    config: AlignConfig
    seed: int
    folder: str  # DIR/prepared
    # keyword-only: jobs extending this one add positional fields after `folder`
    reading: ReadingConfig = field(default_factory=ReadingConfig, kw_only=True)


def entry(folder: str | Path, key: str) -> Path:
    return Path(folder) / f"{key}.npz"


# Loaded clouds of this process, by cache entry (folder + key: another cache folder is another cache,
# its entry is written even when this process holds the same cloud): a scan in several pairs is
# loaded once per worker while it is used.
_LOADED: OrderedDict[str, PreparedCloud] = OrderedDict()
_LOADED_MAX = 4
reads = 0  # scans read and prepared by this process (tests and benchmarks count them)


def _compute(job: PrepareJob, cloud=None) -> PreparedCloud:
    """Prepare the job's scan: `cloud` when the caller holds its points already, else read from job.path."""
    global reads
    config = job.config
    if cloud is None:
        cloud = read_scan_points(job.path, job.reading, config)
        reads += 1
    return prepare_cloud(
        cloud, job.kind, job.levels or default_levels(job.kind), config, job.seed, job.scan
    )


def _remember(key: str, cloud: PreparedCloud) -> None:
    _LOADED[key] = cloud
    _LOADED.move_to_end(key)
    while len(_LOADED) > _LOADED_MAX:
        _LOADED.popitem(last=False)


def prepare_held(job: PrepareJob, cloud) -> PreparedCloud:
    """The job's prepared cloud from points this process holds (exactly job.path's points, e.g. a
    cloud it has just written there): into the cache and this process's memo, the file not read
    unless it is over the reading budget."""
    path = entry(job.folder, job.key)
    if str(path) in _LOADED:
        return _LOADED[str(path)]
    prepared = _load_or_warn(path, job.scan)
    if prepared is None:
        # over the budget, the file is read as any prepare job reads it (thinned): one cloud per key
        prepared = _compute(job, None if over_budget(job.path, job.reading) else cloud)
        save_prepared(path, prepared)
    _remember(str(path), prepared)
    return prepared


def _load_or_warn(path: Path, scan: str) -> PreparedCloud | None:
    """The cached cloud, or None when absent or damaged (then one warning line: it is prepared again)."""
    if not path.is_file():
        return None
    try:
        return load_prepared(path)
    except Exception as exc:  # truncated, foreign or edited file
        print(
            f"warning: {path}: damaged prepared cloud of scan {scan} ({type(exc).__name__}: {exc}); preparing it again",
            file=sys.stderr,
        )
        return None


def get_prepared(job: PrepareJob) -> tuple[PreparedCloud, float]:
    """(prepared cloud, seconds spent reading and preparing it here): from memory, the cache, or computed and cached."""
    path = entry(job.folder, job.key)
    if str(path) in _LOADED:
        _LOADED.move_to_end(str(path))
        return _LOADED[str(path)], 0.0
    cloud = _load_or_warn(path, job.scan)
    seconds = 0.0
    if cloud is None:
        start = time.perf_counter()
        cloud = _compute(job)
        seconds = time.perf_counter() - start
        save_prepared(path, cloud)
    _remember(str(path), cloud)
    return cloud, seconds


def run_prepare_job(job: PrepareJob) -> dict:
    """Worker: make sure the scan's prepared cloud is in the cache; a record with status "ok" or "failed"."""
    start = time.perf_counter()
    record = {"key": job.key, "scan": job.scan, "kind": "prepare", "computed": False}
    try:
        path = entry(job.folder, job.key)
        held = _LOADED.get(str(path))
        if held is not None and not path.is_file():
            save_prepared(path, held)
        elif held is None and _load_or_warn(path, job.scan) is None:
            cloud = _compute(job)
            save_prepared(path, cloud)
            _remember(str(path), cloud)  # a worker kept for the pairs may register this scan next
            record["computed"] = True
        record["status"] = "ok"
    # unreadable scan, too few points, out of memory: its pairs fail with this
    except Exception as exc:
        record.update(
            status="failed",
            error=f"{type(exc).__name__}: {exc}" if not str(exc).startswith(job.scan) else str(exc),
        )
    record["seconds"] = time.perf_counter() - start
    return record
