"""The real-data suite (benchmarks/bench_real.py): run the cases under the protocols, count outcomes, draw reliability.

Outcomes per trial: refused (the method reported failure: exit 3 / RegistrationFailed for forestalign, whatever its
estimate), found (returned and within 1 deg / 10 cm), wrong (a wrong pose returned with exit 0).

Each trial's draw comes from (seed, case, protocol, trial) alone, so a run extends (N=10 -> N=50) by running the
trials it has not got, and `-j` changes nothing but the wall time. Every finished trial is one line of
OUT/trials.jsonl; tables and the reliability diagram are drawn from that file. A case is built once per worker,
its target prepared once for forestalign; each trial moves the source and runs every method on that draw.
Tables and the reliability diagram are bench/suite_tables.py.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plotmosaic.bench.methods import OURS, PairInput, prepare_target, run_method
from plotmosaic.bench.protocol import (
    PARAMS,
    is_success,
    params_to_matrix,
    pose_error,
    rotation_angle,
)
from plotmosaic.bench.real_cases import build_case
from plotmosaic.bench.trial_pool import run_each
from plotmosaic.config.bench import SUITE_PROTOCOLS, MethodsConfig
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.frame import Frame, apply_transform, to_local_transform
from plotmosaic.io.frame import pose_error as angle_distance
from plotmosaic.io.las import PointCloud


def print_wrong(rows: list[dict], where: Callable[[dict], str]) -> None:
    """plotmosaic's wrong poses with exit 0 among `rows`: their count, then one line each."""
    ours = [r for r in rows if r["method"] in OURS]
    wrong = [r for r in ours if r["outcome"] == "wrong"]
    print(f"plotmosaic wrong poses with exit 0: {len(wrong)} of {len(ours)} trials")
    for r in wrong:
        print(
            f"  {where(r)}: {r['rotation_deg']:.2f} deg / {r['translation_m']:.2f} m, confidence"
            f" {r.get('confidence')}, judge {r.get('judge_score')}, rival {r.get('rival_score')},"
            f" {r.get('result_json', '-')}"
        )


TRIALS_FILE = "trials.jsonl"
CASES_FILE = "cases.json"
NEAR_DEG, NEAR_M = 3.0, 1.0  # a generator's hypothesis "near the truth" (after screening)


def outcome(row: dict) -> str:
    """found = returned and right; refused = the method said no (even if its estimate was right); wrong = returned, wrong."""
    if row["failed"]:
        return "refused"
    return "found" if row["success"] else "wrong"


def _stable(text: str) -> int:
    return int(hashlib.sha256(text.encode()).hexdigest()[:8], 16)


def draw(protocol: str, seed: int, case: str, trial: int) -> np.ndarray:
    """The six start parameters of one trial: uniform in the protocol's ranges, from (seed, case, protocol, trial)."""
    ss = np.random.SeedSequence([seed, _stable(case), _stable(protocol), trial])
    return np.random.default_rng(ss).uniform(-1.0, 1.0, 6) * SUITE_PROTOCOLS[protocol].ranges


def _git(root: Path, *args: str) -> str:
    run = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=10)
    return run.stdout.strip()


def commit() -> str:
    """`git rev-parse --short HEAD` of the tree this runs from (+ '-dirty' when it has local changes), or '?'."""
    root = Path(__file__).resolve().parents[2]
    try:
        head = _git(root, "rev-parse", "--short", "HEAD")
        dirty = _git(root, "status", "--porcelain", "--untracked-files=no", "plotmosaic")
    except (OSError, subprocess.SubprocessError):
        head, dirty = "", ""
    if not head and (root / ".commit").is_file():  # a `git archive` snapshot names its commit there
        return (root / ".commit").read_text().strip()
    return (head or "?") + ("-dirty" if dirty else "")


# ---------------------------------------------------------------- trials


@dataclass(frozen=True)
class Trial:
    case: str
    protocol: str
    trial: int
    methods: tuple[str, ...]  # those of this draw not yet in the trials file
    seed: int = 0
    data: str | None = None
    # folder: a wrong forestalign pose with exit 0 keeps its result JSON there
    out: str | None = None


def key(row: dict) -> tuple:
    return (row["case"], row["protocol"], int(row["trial"]), row["method"])


def read_trials(path: str | Path) -> list[dict]:
    """The rows of a trials file (a line cut short by an interrupted run is skipped)."""
    rows = []
    path = Path(path)
    if not path.is_file():
        return rows
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except ValueError:
            continue
        row["outcome"] = outcome(row)
        rows.append(row)
    return rows


def append_trials(path: str | Path, rows: Iterable[dict]) -> None:
    """One JSON line a row, flushed to disk: a run killed later keeps every finished trial."""
    with open(path, "a") as fh:
        for r in rows:
            fh.write(json.dumps(r, default=float) + "\n")
        fh.flush()
        os.fsync(fh.fileno())


def plan(
    cases: list[str],
    protocols: dict[str, int],
    methods: list[str],
    done: set[tuple],
    seed: int = 0,
    data: str | Path | None = None,
    out: str | Path | None = None,
) -> list[Trial]:
    """The trials still to run, case by case (a worker keeps its case between trials)."""
    jobs = []
    for name in cases:
        for proto, n in protocols.items():
            for i in range(n):
                todo = tuple(m for m in methods if (name, proto, i, m) not in done)
                if todo:
                    jobs.append(
                        Trial(name, proto, i, todo, seed, None if data is None else str(data),
                              None if out is None else str(out))
                    )  # fmt: skip
    return jobs


_STATE: dict = {}  # per process: the case being run (built once, its target prepared once)


def _case_state(name: str, seed: int, data: str | None):
    key_ = (name, seed, data)
    if key_ not in _STATE:
        _STATE.clear()  # one case at a time: memory stays bounded
        t0 = time.perf_counter()
        case = build_case(name, data, seed)
        aligned = PointCloud(apply_transform(case.truth, case.source.xyz), crs=case.target.crs)
        built = time.perf_counter() - t0
        pair = PairInput(aligned, case.target, case.source_kind, case.target_kind)
        prepared = prepare_target(pair, seed, scanner=np.zeros(3) if case.at_scanner else None)
        info = {
            "note": case.note,
            "meta": case.meta,
            "source_kind": case.source_kind,
            "target_kind": case.target_kind,
            "source_points": len(case.source),
            "target_points": len(case.target),
            "build_seconds": built,
            "prepare_target_seconds": time.perf_counter() - t0 - built,
        }
        _STATE[key_] = (case, aligned, prepared, info)
    return _STATE[key_]


def keep_wrong(path: Path, row: dict, truth: np.ndarray, result) -> None:
    """A wrong pose returned with exit 0: its draw, the truth and the result as JSON at `path`,
    which the row names."""
    doc = {"draw": row, "truth": truth.tolist(), "result": result.to_dict()}
    row["result_json"] = str(write_text_atomic(path, json.dumps(doc, indent=1, default=float)))


def _near(result, truth: np.ndarray) -> tuple[list[str], str | None]:
    """Generators with a hypothesis near the truth, and the winning generator:vertical (coarse stage only)."""
    coarse = getattr(result, "coarse", None)
    if not coarse or not coarse.get("hypotheses"):
        return [], None
    local = to_local_transform(
        truth, Frame(np.asarray(result.source_offset)), Frame(np.asarray(result.target_offset))
    )
    near = set()
    for h in coarse["hypotheses"]:
        deg, m = angle_distance(np.asarray(h["transform"]), local)
        if deg < NEAR_DEG and m < NEAR_M:
            near.add(h["generator"])
    win = coarse["hypotheses"][0]
    return sorted(near), f"{win.get('generator')}:{win.get('vertical')}"


def run_trial(job: Trial) -> tuple[dict, list[dict]]:
    """Every method of `job` on its draw: (the case's info, one row a method)."""
    case, aligned, prepared, info = _case_state(job.case, job.seed, job.data)
    p = draw(job.protocol, job.seed, job.case, job.trial)
    centre = aligned.xyz.mean(axis=0)
    P = params_to_matrix(p, centre)
    moved = PointCloud(apply_transform(P, aligned.xyz), crs=aligned.crs)
    truth = np.linalg.inv(P)
    rows = []
    for method in job.methods:
        target_prepared = prepared if method in OURS else None
        scanner = apply_transform(P, case.truth[:3, 3][None])[0] if case.at_scanner else None
        pair = PairInput(
            moved,
            case.target,
            case.source_kind,
            case.target_kind,
            target_prepared,
            source_scanner=scanner,
        )
        out = run_method(method, pair, MethodsConfig(), seed=job.seed + job.trial)
        err = pose_error(out.transform, truth, centre)
        row = {
            "case": job.case,
            "protocol": job.protocol,
            "trial": job.trial,
            "method": method,
            "seed": job.seed,
            **{f"init_{n}": float(v) for n, v in zip(PARAMS, p)},
            **{n: float(v) for n, v in zip(PARAMS, err)},
            "rotation_deg": float(rotation_angle(err)[0]),
            "translation_m": float(np.linalg.norm(err[3:])),
            "success": bool(is_success(err)[0]),
            "failed": bool(out.failed),
            "seconds": out.seconds,
            "note": out.note,
            "confidence": out.confidence,
        }
        res = out.result
        if res is not None:
            judge = getattr(res, "judge", None) or {}
            near, winner = _near(res, truth)
            row.update(
                fitness=float(res.fitness),
                judge_score=judge.get("score"),
                rival_score=judge.get("rival_score"),
                rival_source=judge.get("rival_source"),
                near=near,
                winner=winner,
            )
        row["outcome"] = outcome(row)
        if row["outcome"] == "wrong" and res is not None and job.out:
            name = f"{job.case}-{job.protocol}-seed{job.seed}-trial{job.trial}.json"
            keep_wrong(Path(job.out) / "wrong" / name, row, truth, res)
        rows.append(row)
    return info, rows


@dataclass(frozen=True)
class Suite:
    """What a run draws: its cases, each protocol's trial count, the methods, the seed, the data."""

    cases: tuple[str, ...]
    protocols: dict[str, int]
    methods: tuple[str, ...]
    seed: int = 0
    data: str | Path | None = None


def run_suite(
    suite: Suite,
    out: str | Path | None = None,
    jobs: int = 1,
    log: Callable[[str], None] = print,
    on_trial: Callable[[dict, list[dict]], None] | None = None,
) -> list[dict]:
    """Every method on the same draws of every (case, protocol) of `suite`.

    Trials already in OUT/trials.jsonl are not run again; each finished trial is appended there (and passed to
    `on_trial(case info, rows)`). `jobs` worker processes share the thread budget of plotmosaic.parallel.
    Returns the new rows.
    """
    done = set()
    path = None
    if out is not None:
        Path(out).mkdir(parents=True, exist_ok=True)
        path = Path(out) / TRIALS_FILE
        done = {key(r) for r in read_trials(path)}
    todo = plan(suite.cases, suite.protocols, suite.methods, done, suite.seed, suite.data, out)
    head = commit()
    log(
        f"{len(todo)} trials to run ({len(done)} rows already in {path}); commit {head}, {jobs} job(s)"
    )
    new: list[dict] = []

    def finish(info: dict, rows: list[dict], job: Trial) -> None:
        for r in rows:
            r["commit"] = head
        if path is not None:
            append_trials(path, rows)
        new.extend(rows)
        if on_trial:
            on_trial(info, rows)
        log(
            f"  {job.case} [{job.protocol}] trial {job.trial}: "
            + ", ".join(
                f"{r['method']} {r['outcome']} {r['rotation_deg']:.3f} deg / {100 * r['translation_m']:.1f} cm"
                for r in rows
            )
            + f" ({sum(r['seconds'] for r in rows):.0f} s)"
        )

    def crashed(job: Trial, exc: Exception) -> None:
        log(
            f"  {job.case} [{job.protocol}] trial {job.trial}: CRASHED, not recorded ({type(exc).__name__}: {exc})"
        )

    run_each(todo, jobs, run_trial, lambda result, job: finish(*result, job), crashed)
    return new
