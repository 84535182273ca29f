"""The pair cache: one JSON file per pair result under DIR/pairs/, keyed by what determines it.

The key (graph/jobs.py, `job_key`) hashes both files' contents, their kinds and levels, the align
settings, the seed and the plotmosaic version, so a re-run (or a run resumed after Ctrl-C or a crash) redoes only what is
missing. Entries are written atomically: an interrupted run leaves only complete entries. An entry
that does not validate (damaged, edited, truncated) is discarded with one warning line and the
pair is registered again. An entry holds the pair's own result only: whether the pose graph kept
the edge is recorded in graph.json, never here.
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
from pathlib import Path

import numpy as np
from pydantic import BaseModel

from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.e57 import split_scan_ref
from plotmosaic.poses import rigid_problem

_CHUNK = 1 << 20
_hashes: dict[tuple[str, int, int], str] = {}
SCOPE = "pair registration only; the pose graph's keep/drop decision for this edge is in graph.json"


def file_hash(path: str | Path) -> str:
    """sha256 of a file's content, remembered per (path, mtime, size) for this process.

    A scan inside a multi-scan file (`plot.e57#3`) is the file's hash plus the scan index, so the
    scans of one file never share a cache entry.
    """
    file, scan = split_scan_ref(path)
    path = Path(file).resolve()
    st = path.stat()
    memo = (str(path), st.st_mtime_ns, st.st_size)
    if memo not in _hashes:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            while block := f.read(_CHUNK):
                h.update(block)
        _hashes[memo] = h.hexdigest()
    return _hashes[memo] if scan is None else f"{_hashes[memo]}#{scan}"


def settings_json(settings: BaseModel) -> str:
    """Settings as the cache keys hold them: the one place a config becomes JSON (jobs carry their
    settings typed, to any worker process or Dask machine)."""
    return settings.model_dump_json()


class PairCache:
    """DIR/pairs/<key>.json. `writes` counts the entries written by this object (pairs computed)."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.writes = 0

    def path(self, key: str) -> Path:
        return self.folder / f"{key}.json"

    def get(self, key: str) -> dict | None:
        """The cached record, or None when missing or damaged (then one warning line names the file)."""
        path = self.path(key)
        try:
            record = json.loads(path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
            return self._discard(path, f"not readable JSON ({getattr(exc, 'msg', exc)})")
        problem = record_problem(record, key)
        if problem:
            return self._discard(path, problem)
        return record

    def _discard(self, path: Path, why: str) -> None:
        print(
            f"warning: {path}: damaged cache entry ({why}); registering the pair again",
            file=sys.stderr,
        )
        return None

    def put(self, key: str, record: dict) -> None:
        write_text_atomic(self.path(key), json.dumps({**record, "scope": SCOPE}, indent=1))
        self.writes += 1

    def keys(self) -> set[str]:
        return {p.stem for p in self.folder.glob("*.json") if not p.name.startswith(".")}


def _finite_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def record_problem(record, key: str) -> str | None:
    """Why a cached record cannot be used (None if it can): what the graph reads must be present and sane."""
    if not isinstance(record, dict):
        return "not a JSON object"
    if record.get("key") != key:
        return f"key {record.get('key')!r} does not match the file name"
    if not isinstance(record.get("source"), str) or not isinstance(record.get("target"), str):
        return "missing 'source' or 'target'"
    status = record.get("status")
    if status == "failed":
        return None if isinstance(record.get("error"), str) else "failed entry without 'error'"
    if status != "ok":
        return f"unknown status {status!r}"
    if "transform" not in record:
        return "missing 'transform'"
    try:
        T = np.asarray(record["transform"], dtype=np.float64)
        info = np.asarray(record.get("information"), dtype=np.float64)
    except (TypeError, ValueError):
        return "'transform' or 'information' is not numeric"
    problem = rigid_problem(T)
    if problem:
        return f"'transform' {problem}"
    if info.shape != (6, 6) or not np.isfinite(info).all():
        return "'information' must be a finite 6x6 matrix"
    for name in ("fitness", "inlier_rmse", "overlap"):
        if not _finite_number(record.get(name)):
            return f"'{name}' must be a finite number"
    return None
