"""Peer tools' pair registration beside bench/methods.py's baselines (benchmarks/bench_overlap.py).

  sylva           Sylva's (UQ-EORC, `pip install sylva-rs`, the bench extra) pair registration: per scan
                  `sylva.coreg.prepare_scan` (terrain model, stem map from circles in breast-height
                  slices, planar ICP subsample), then `sylva.coreg.register_pair` (global stem-map
                  match, height from the two terrain models, robust point-to-plane ICP, its own
                  acceptance tests: `success` False counts as refused). Given the clouds alone, as
                  every other method is.
  sylva-levelled  the same, also given what Sylva's API expects from a TLS survey: each scan's
                  levelling (the scanner's inclinometer: the rotation that makes the cloud's up
                  vertical, the heading left unknown) and its scanner position. Sylva matches stem maps
                  in 4 DoF, so a scan tilted by the `paper` protocol's +-45 deg is out of its reach
                  without them.

A peer returns a bench/methods.py MethodOutput (transform source' file -> target file coordinates).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from plotmosaic.bench.methods import MethodOutput

PEERS = ("sylva", "sylva-levelled")


@dataclass(frozen=True)
class Sensors:
    """What a scanner records beside its points, in the cloud's own frame."""

    up: np.ndarray  # (3,) the world's up direction
    scanner: np.ndarray  # (3,) where the scanner stood


def peer_available(name: str) -> str | None:
    """None when the peer can run here, else why not (one line)."""
    if name not in PEERS:
        raise ValueError(f"unknown peer {name!r} (choose from {', '.join(PEERS)})")
    try:
        import sylva.coreg  # noqa: F401  (optional: the bench extra)
    except ImportError:
        return "sylva-rs is not installed (pip install 'plotmosaic[bench]')"
    return None


def levelling(up: np.ndarray) -> np.ndarray:
    """4x4 rotation turning `up` onto +z by the shortest arc (no heading of its own)."""
    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(u, z)
    s, c = float(np.linalg.norm(axis)), float(u @ z)
    L = np.eye(4)
    if s < 1e-12:
        L[:3, :3] = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
        return L
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    L[:3, :3] = np.eye(3) + s * K + (1 - c) * K @ K
    return L


def _sylva(
    source: np.ndarray,
    target: np.ndarray,
    seed: int,
    source_sensors: Sensors | None,
    target_sensors: Sensors | None,
) -> MethodOutput:
    from sylva import coreg  # optional (the bench extra): only when a Sylva method runs

    start = time.perf_counter()
    cfg = coreg.CoregConfig(verbose=False, workers=1)
    cfg.stems.seed = seed
    cfg.matching.seed = seed
    Ls, Lt = np.eye(4), np.eye(4)
    kw_s: dict = {}
    kw_t: dict = {}
    if source_sensors is not None and target_sensors is not None:
        Ls, Lt = levelling(source_sensors.up), levelling(target_sensors.up)
        kw_s = {"levelling": Ls, "origin": Ls[:3, :3] @ source_sensors.scanner}
        kw_t = {"levelling": Lt, "origin": Lt[:3, :3] @ target_sensors.scanner}
    src = coreg.prepare_scan(np.ascontiguousarray(source), cfg, "source", **kw_s)
    tgt = coreg.prepare_scan(np.ascontiguousarray(target), cfg, "target", **kw_t)
    for name, scan in (("source", src), ("target", tgt)):
        if not scan.usable:
            return MethodOutput(
                np.eye(4),
                time.perf_counter() - start,
                True,
                f"{name} unusable: {scan.error or 'no ICP points'}"[:200],
            )
    res = coreg.register_pair(src, tgt, cfg)
    # Sylva's transform maps the levelled source into the levelled target
    T = np.linalg.inv(Lt) @ np.asarray(res.transform, dtype=np.float64) @ Ls
    note = f"stems {len(src.stem_map)} / {len(tgt.stem_map)}, matched {res.n_stem_matches}"
    if not res.success:
        note = f"{res.reason}; {note}"
    return MethodOutput(T, time.perf_counter() - start, not res.success, note[:200])


def run_peer(
    name: str,
    source: np.ndarray,
    target: np.ndarray,
    seed: int,
    source_sensors: Sensors | None = None,
    target_sensors: Sensors | None = None,
) -> MethodOutput:
    """One peer once on (source' xyz, target xyz); sensors are used by `sylva-levelled` only.

    A peer that raises on numerical trouble counts as failed (scored as identity), as in methods.py.
    """
    if name not in PEERS:
        raise ValueError(f"unknown peer {name!r} (choose from {', '.join(PEERS)})")
    start = time.perf_counter()
    if name == "sylva-levelled" and (source_sensors is None or target_sensors is None):
        raise ValueError("sylva-levelled needs both scans' sensors (up vector, scanner position)")
    try:
        if name == "sylva":
            return _sylva(source, target, seed, None, None)
        return _sylva(source, target, seed, source_sensors, target_sensors)
    except (RuntimeError, ValueError) as exc:
        return MethodOutput(
            np.eye(4), time.perf_counter() - start, True, f"{type(exc).__name__}: {exc}"[:200]
        )
