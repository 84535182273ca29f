"""The pair cache: one JSON file per pair result under DIR/pairs/, keyed by what determines it.

The key hashes both files' contents, their kinds and levels, the align settings, the seed and the
plotmosaic version, so a re-run (or a run resumed after Ctrl-C or a crash) redoes only what is
missing. Entries are written atomically: an interrupted run leaves only complete entries.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from plotmosaic import __version__
from plotmosaic.io.atomic import write_text_atomic

_CHUNK = 1 << 20
_hashes: dict[tuple[str, int, int], str] = {}


def file_hash(path: str | Path) -> str:
    """sha256 of a file's content, remembered per (path, mtime, size) for this process."""
    path = Path(path).resolve()
    st = path.stat()
    memo = (str(path), st.st_mtime_ns, st.st_size)
    if memo not in _hashes:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            while block := f.read(_CHUNK):
                h.update(block)
        _hashes[memo] = h.hexdigest()
    return _hashes[memo]


def pair_key(source_path, target_path, source_kind: str, target_kind: str, levels_source: int | None,
             levels_target: int | None, config_json: str, seed: int) -> str:
    parts = {
        "source": file_hash(source_path),
        "target": file_hash(target_path),
        "kinds": [source_kind, target_kind],
        "levels": [levels_source, levels_target],
        "config": json.loads(config_json),
        "seed": seed,
        "version": __version__,
    }
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:32]


class PairCache:
    """DIR/pairs/<key>.json. `writes` counts the entries written by this object (pairs computed)."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.writes = 0

    def path(self, key: str) -> Path:
        return self.folder / f"{key}.json"

    def get(self, key: str) -> dict | None:
        try:
            return json.loads(self.path(key).read_text())
        except (FileNotFoundError, json.JSONDecodeError, UnicodeDecodeError):
            return None  # missing or unreadable: compute it again

    def put(self, key: str, record: dict) -> None:
        write_text_atomic(self.path(key), json.dumps(record, indent=1))
        self.writes += 1

    def keys(self) -> set[str]:
        return {p.stem for p in self.folder.glob("*.json") if not p.name.startswith(".")}

    def clear(self) -> None:
        for p in self.folder.glob("*.json"):
            os.unlink(p)
