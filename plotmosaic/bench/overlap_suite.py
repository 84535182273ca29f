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
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plotmosaic.bench.figures import pyplot
from plotmosaic.bench.methods import (
    METHODS,
    OURS,
    PairInput,
    available,
    prepare_target,
    run_method,
)
from plotmosaic.bench.overlap_pairs import (
    SOURCES,
    Bin,
    PairRef,
    bin_label,
    load_pair,
)
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
    key,
    outcome,
    read_trials,
)
from plotmosaic.bench.trial_pool import run_each
from plotmosaic.config.bench import MethodsConfig
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.frame import apply_transform
from plotmosaic.io.las import PointCloud
from plotmosaic.io.pictures import savefig

PROTOCOL = "paper"
# the baselines of bench/methods.py (forestalign-placement is for airborne targets) and the peers
ALL_METHODS = ("forestalign", "icp", "fpfh-ransac", "cpd", *PEERS)


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
    out: str | None = (
        None  # folder: a wrong forestalign pose with exit 0 keeps its result JSON there
    )


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
        prepared = prepare_target(PairInput(aligned, target), seed)
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
            inp = PairInput(moved, target, "tls", "tls")
            if method in OURS:
                inp.target_prepared = prepared
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
            doc = {"draw": row, "truth": truth.tolist(), "result": res.to_dict()}
            row["result_json"] = str(
                write_text_atomic(
                    Path(job.out) / "wrong" / name, json.dumps(doc, indent=1, default=float)
                )
            )
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


# ---------------------------------------------------------------- tables and the curve


def _bin(r: dict) -> Bin:
    return (float(r["bin"][0]), float(r["bin"][1]))


def summarise(rows: list[dict]) -> list[dict]:
    """One dict per (source or 'all', bin, method): n, found, refused, wrong, overlaps, CPU s."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        for src in ("all", r["source"]):
            groups.setdefault((src, _bin(r), r["method"]), []).append(r)
    order = ["all", *SOURCES]
    meths = list(ALL_METHODS)
    out = []
    for src, b, m in sorted(
        groups,
        key=lambda k: (
            order.index(k[0]) if k[0] in order else 99,
            k[1],
            meths.index(k[2]) if k[2] in meths else 99,
        ),
    ):
        sub = groups[(src, b, m)]
        out.append(
            {
                "source": src,
                "bin": list(b),
                "method": m,
                "n": len(sub),
                "pairs": len({(r["source"], r["pair"]) for r in sub}),
                "found": sum(r["outcome"] == "found" for r in sub),
                "refused": sum(r["outcome"] == "refused" for r in sub),
                "wrong": sum(r["outcome"] == "wrong" for r in sub),
                "overlap_st": [
                    float(np.min([r["overlap_st"] for r in sub])),
                    float(np.median([r["overlap_st"] for r in sub])),
                    float(np.max([r["overlap_st"] for r in sub])),
                ],  # fmt: skip
                "overlap_ts": [
                    float(np.min([r["overlap_ts"] for r in sub])),
                    float(np.median([r["overlap_ts"] for r in sub])),
                    float(np.max([r["overlap_ts"] for r in sub])),
                ],  # fmt: skip
                "cpu_median_s": float(np.median([r["cpu_seconds"] for r in sub])),
                "commits": sorted({r.get("commit", "?") for r in sub}),
            }
        )
    return out


def _cell(s: dict) -> str:
    wrong = f"**{s['wrong']}**" if s["wrong"] and s["method"] in OURS else str(s["wrong"])
    return f"{s['found']} / {s['refused']} / {wrong}"


def markdown(summary: list[dict]) -> str:
    """Per source (and all pooled) and bin: N, overlap both ways, found / refused / wrong per method."""
    methods = [m for m in ALL_METHODS if any(s["method"] == m for s in summary)]
    groups: dict[tuple, dict[str, dict]] = {}
    for s in summary:
        groups.setdefault((s["source"], tuple(s["bin"])), {})[s["method"]] = s
    head = ["source", "overlap bin", "pairs", "N", "overlap s->t", "overlap t->s"]
    head += [f"{m} found / refused / wrong" for m in methods]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for (src, b), per in groups.items():
        any_ = next(iter(per.values()))
        n = max(s["n"] for s in per.values())
        cells = [
            f"**{src}**" if src == "all" else src,
            f"[{b[0]:.2f}, {b[1]:.2f}{']' if b[1] >= 0.5 else ')'}",
            str(any_["pairs"]),
            str(n),
            "{1:.2f} ({0:.2f}-{2:.2f})".format(*any_["overlap_st"]),
            "{1:.2f} ({0:.2f}-{2:.2f})".format(*any_["overlap_ts"]),
        ]
        cells += [_cell(per[m]) if m in per else "—" for m in methods]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def cpu_table(rows: list[dict]) -> str:
    """Median CPU seconds a trial per method and source (all bins)."""
    methods = [m for m in ALL_METHODS if any(r["method"] == m for r in rows)]
    lines = ["| source | " + " | ".join(methods) + " |", "|" + "---|" * (len(methods) + 1)]
    for src in ("all", *SOURCES):
        cells = []
        for m in methods:
            cpu = [
                r["cpu_seconds"] for r in rows if r["method"] == m and src in ("all", r["source"])
            ]
            cells.append(f"{np.median(cpu):.1f}" if cpu else "—")
        if any(c != "—" for c in cells):
            lines.append(f"| {src} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def pairs_table(rows: list[dict]) -> str:
    """The pairs behind each source and bin: scanner distance and range (what sets the overlap)."""
    groups: dict[tuple, dict[str, dict]] = {}
    for r in rows:
        groups.setdefault((r["source"], tuple(_bin(r))), {})[r["pair"]] = r
    lines = [
        "| source | overlap bin | pairs | scanners apart (m) | range (m) |",
        "|---|---|---|---|---|",
    ]
    for (src, b), pairs in sorted(
        groups.items(), key=lambda kv: (SOURCES.index(kv[0][0]), kv[0][1])
    ):
        d = [p["distance_m"] for p in pairs.values()]
        rng = [p["max_range"] for p in pairs.values()]
        lines.append(
            f"| {src} | {bin_label(b)} | {len(pairs)} | {min(d):.1f}-{max(d):.1f} | "
            f"{min(rng):.1f}-{max(rng):.1f} |"
        )
    return "\n".join(lines) + "\n"


def plot_curve(summary: list[dict], path: str | Path) -> Path:
    """Found share against overlap bin, one line per method: all sources pooled, then each source."""
    plt = pyplot()
    panels = ["all", *[s for s in SOURCES if any(x["source"] == s for x in summary)]]
    bins = sorted({tuple(s["bin"]) for s in summary})
    methods = [m for m in ALL_METHODS if any(s["method"] == m for s in summary)]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.6 * len(panels), 3.6), sharey=True)
    axes = np.atleast_1d(axes)
    x = np.arange(len(bins))
    markers = "osD^vPX*"
    for ax, src in zip(axes, panels):
        for k, m in enumerate(methods):
            per = {tuple(s["bin"]): s for s in summary if s["source"] == src and s["method"] == m}
            y = [
                per[b]["found"] / per[b]["n"] if b in per and per[b]["n"] else np.nan for b in bins
            ]
            style = {"lw": 2.4, "color": "k"} if m in OURS else {"lw": 1.2, "alpha": 0.85}
            dodge = 0.06 * (k - (len(methods) - 1) / 2)  # lines at equal shares stay visible
            ax.plot(x + dodge, y, marker=markers[k % len(markers)], ms=5, label=m, **style)
        n = [max((s["n"] for s in summary if s["source"] == src and tuple(s["bin"]) == b), default=0) for b in bins]  # fmt: skip
        ax.set_xticks(x, [f"{b[0]:.2f}-{b[1]:.2f}\nN={k}" for b, k in zip(bins, n)], fontsize=7)
        ax.set_title("all sources" if src == "all" else src, fontsize=10)
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
        ax.set_xlabel("pair overlap (larger share, 25 cm)", fontsize=8)
    axes[0].set_ylabel("found (within 1 deg / 10 cm)")
    axes[0].legend(fontsize=7, loc="upper left")
    fig.suptitle("paper protocol: found share against overlap", fontsize=10)
    return savefig(fig, path)


def write_outputs(
    rows: list[dict], out: str | Path, command: str, figure: str | Path | None
) -> dict:
    """OUT/table.md, OUT/summary.json and the curve (OUT/overlap.png unless `figure`)."""
    out = Path(out)
    summary = summarise(rows)
    wrong = [r for r in rows if r["method"] in OURS and r["outcome"] == "wrong"]
    text = (
        f"Command:\n\n    {command}\n\n"
        + markdown(summary)
        + "\nThe pairs (each bin's draws cycle over them):\n\n"
        + pairs_table(rows)
        + "\nMedian CPU seconds a trial:\n\n"
        + cpu_table(rows)
        + f"\nplotmosaic wrong poses with exit 0: {len(wrong)} of "
        + f"{sum(r['method'] in OURS for r in rows)} trials\n"
    )
    states: dict[tuple, int] = {}
    for r in rows:
        k = (r.get("commit", "?"), r.get("code", "?"))
        states[k] = states.get(k, 0) + 1
    text += (
        "\nCode measured (commit, source hash: rows): "
        + "; ".join(f"{c}, {h}: {n}" for (c, h), n in states.items())
        + "\n"
    )
    paths = {
        "table": write_text_atomic(out / "table.md", text),
        "summary": write_text_atomic(
            out / "summary.json", json.dumps(summary, indent=1, default=float)
        ),
        "figure": plot_curve(summary, figure or out / "overlap.png"),
    }
    return paths


__all__ = [
    "ALL_METHODS",
    "METHODS",
    "PROTOCOL",
    "TRIALS_FILE",
    "Job",
    "case_name",
    "cpu_table",
    "markdown",
    "method_available",
    "plan",
    "plot_curve",
    "read_trials",
    "run",
    "run_trial",
    "summarise",
    "write_outputs",
]
