"""Success against overlap (benchmarks/bench_overlap.py): every method on the same `paper` draws of view
pairs binned by overlap (bench/overlap_pairs.py cuts them), counted per bin and source, drawn as a curve.

A trial is (source, bin, trial index): its pair is the bin's catalogue pair `trial % len(pairs)`, its start
pose the `paper` draw of real_suite.draw(seed, case, trial) applied to the source about its centroid, as
bench_real does; "found" is the suite's success (within 1 deg / 10 cm), "refused" the method said no
(exit 3), "wrong" a wrong pose returned with exit 0. Every finished trial is one line of OUT/trials.jsonl:
re-runs skip what is there and -j changes nothing but the wall time.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plotmosaic.bench.methods import OURS, PairInput, available, prepare_target, run_method
from plotmosaic.bench.overlap_pairs import SOURCES, Bin, PairRef, bin_label, load_pair
from plotmosaic.bench.peers import PEERS, Sensors, peer_available, run_peer
from plotmosaic.bench.protocol import (
    PARAMS,
    is_success,
    params_to_matrix,
    pose_error,
    rotation_angle,
)
from plotmosaic.bench.real_suite import (
    TRIALS_FILE,
    append_trials,
    commit,
    draw,
    keep_wrong,
    key,
    outcome,
    read_trials,
)
from plotmosaic.bench.trial_pool import run_each
from plotmosaic.config.bench import MethodsConfig
from plotmosaic.io.frame import apply_transform
from plotmosaic.io.las import PointCloud

PROTOCOL = "paper"


def method_available(name: str) -> str | None:
    """None when the method can run here, else why not."""
    return peer_available(name) if name in PEERS else available(name)


def case_name(source: str, b: Bin) -> str:
    """The case of a (source, bin): names the draws (real_suite.draw) and the trials' keys."""
    return f"{source}:{bin_label(b)}"


@dataclass(frozen=True)
class Job:
    source: str
    bin: Bin
    trial: int
    pair: PairRef
    methods: tuple[str, ...]
    seed: int = 0
    # folder: a wrong forestalign pose with exit 0 keeps its result JSON there
    out: str | None = None


def plan(
    catalogues: dict[str, dict[Bin, list[PairRef]]],
    n: int,
    methods: list[str],
    done: set[tuple],
    seed: int = 0,
    out: str | Path | None = None,
) -> list[Job]:
    """The trials still to run, ordered by pair so a worker reuses a loaded pair and its prepared target."""
    jobs = []
    for source, bins in catalogues.items():
        for b, pairs in bins.items():
            if not pairs:
                continue
            case = case_name(source, b)
            for i in range(n):
                todo = tuple(m for m in methods if (case, PROTOCOL, i, m) not in done)
                if todo:
                    pair = pairs[i % len(pairs)]
                    jobs.append(
                        Job(source, b, i, pair, todo, seed, None if out is None else str(out))
                    )
    jobs.sort(key=lambda j: (SOURCES.index(j.source), j.bin, j.pair.id, j.trial))
    return jobs


_STATE: dict = {}  # per process: the pair being run, its target prepared once for forestalign


def _pair_state(ref: PairRef, seed: int):
    if ref.id not in _STATE:
        _STATE.clear()
        pair = load_pair(ref.path)
        aligned = PointCloud(apply_transform(pair.truth, pair.source))
        target = PointCloud(pair.target)
        # each view in its own scanner frame, as a TLS file is (scanner at the origin)
        prepared = prepare_target(PairInput(aligned, target), seed, scanner=np.zeros(3))
        _STATE[ref.id] = (pair, aligned, target, prepared)
    return _STATE[ref.id]


def run_trial(job: Job) -> list[dict]:
    """Every method of `job` on its draw: one row a method."""
    pair, aligned, target, prepared = _pair_state(job.pair, job.seed)
    case = case_name(job.source, job.bin)
    p = draw(PROTOCOL, job.seed, case, job.trial)
    centre = aligned.xyz.mean(axis=0)
    P = params_to_matrix(p, centre)
    moved = PointCloud(apply_transform(P, aligned.xyz))
    truth = np.linalg.inv(P)
    # what a levelled scanner records, in the moved source's frame and the target's
    src_sensors = Sensors(P[:3, :3] @ pair.up, apply_transform(P, pair.truth[:3, 3][None])[0])
    tgt_sensors = Sensors(pair.up, np.zeros(3))
    rows = []
    for method in job.methods:
        seed = job.seed + job.trial
        cpu0 = time.process_time()
        if method in PEERS:
            out = run_peer(method, moved.xyz, target.xyz, seed, src_sensors, tgt_sensors)
        else:
            inp = PairInput(
                moved,
                target,
                "tls",
                "tls",
                prepared if method in OURS else None,
                source_scanner=src_sensors.scanner,
            )
            out = run_method(method, inp, MethodsConfig(), seed=seed)
        cpu = time.process_time() - cpu0
        err = pose_error(out.transform, truth, centre)
        row = {
            "case": case,
            "protocol": PROTOCOL,
            "trial": job.trial,
            "method": method,
            "seed": job.seed,
            "source": job.source,
            "bin": list(job.bin),
            "pair": job.pair.id,
            "overlap_st": job.pair.overlap_st,
            "overlap_ts": job.pair.overlap_ts,
            "distance_m": job.pair.distance_m,
            "max_range": job.pair.max_range,
            **{f"init_{n}": float(v) for n, v in zip(PARAMS, p)},
            **{n: float(v) for n, v in zip(PARAMS, err)},
            "rotation_deg": float(rotation_angle(err)[0]),
            "translation_m": float(np.linalg.norm(err[3:])),
            "success": bool(is_success(err)[0]),
            "failed": bool(out.failed),
            "seconds": out.seconds,
            "cpu_seconds": cpu,
            "note": out.note,
            "confidence": out.confidence,
        }
        res = out.result
        if res is not None:
            judge = getattr(res, "judge", None) or {}
            row.update(judge_score=judge.get("score"), rival_score=judge.get("rival_score"))
        row["outcome"] = outcome(row)
        if row["outcome"] == "wrong" and method in OURS and res is not None and job.out:
            name = f"{job.pair.id}-trial{job.trial}-seed{job.seed}.json"
            keep_wrong(Path(job.out) / "wrong" / name, row, truth, res)
        rows.append(row)
    return rows


def source_hash() -> str:
    """A fingerprint of plotmosaic's source as it is on disk: the tree is edited while runs go on,
    and a commit with '-dirty' does not tell two states of the working tree apart."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:12]


def run(
    catalogues: dict[str, dict[Bin, list[PairRef]]],
    n: int,
    methods: list[str],
    out: str | Path,
    seed: int = 0,
    jobs: int = 1,
    log: Callable[[str], None] = print,
) -> list[dict]:
    """Run the trials not yet in OUT/trials.jsonl, appending each as it finishes; returns the new rows."""
    path = Path(out) / TRIALS_FILE
    done = {key(r) for r in read_trials(path)}
    todo = plan(catalogues, n, methods, done, seed, out)
    head, code = commit(), source_hash()
    log(f"{len(todo)} trials to run ({len(done)} rows already in {path}); commit {head}, source {code}, {jobs} job(s)")  # fmt: skip
    new: list[dict] = []

    def finish(rows: list[dict], job: Job) -> None:
        for r in rows:
            r["commit"], r["code"] = head, code
        append_trials(path, rows)
        new.extend(rows)
        log(
            f"  {job.source} [{bin_label(job.bin)}] {job.pair.id} trial {job.trial}: "
            + ", ".join(f"{r['method']} {r['outcome']}" for r in rows)
            + f" ({sum(r['cpu_seconds'] for r in rows):.0f} CPU s)"
        )

    def crashed(job: Job, exc: Exception) -> None:
        log(f"  {job.source} [{bin_label(job.bin)}] trial {job.trial}: CRASHED, not recorded ({type(exc).__name__}: {exc})")  # fmt: skip

    run_each(todo, jobs, run_trial, finish, crashed)
    return new
