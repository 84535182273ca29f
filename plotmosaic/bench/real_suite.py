"""The real-data suite (benchmarks/bench_real.py): run the cases under the protocols, count outcomes, draw reliability.

Outcomes per trial: refused (the method reported failure: exit 3 / RegistrationFailed for forestalign, whatever its
estimate), found (returned and within 1 deg / 10 cm), wrong (a wrong pose returned with exit 0).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from plotmosaic.bench.protocol import PARAMS, PROTOCOLS, Protocol, rotation_angle
from plotmosaic.io.atomic import atomic_output, write_text_atomic

# paper: +-45 deg all three angles, +-15 m, all six at once; beyond: any heading, +-20 m (tilts as the paper);
# true: the source handed over in its true pose (the control)
SUITE_PROTOCOLS: dict[str, Protocol] = {
    "paper": PROTOCOLS["paper"],
    "beyond": Protocol(name="beyond", roll=45, pitch=45, yaw=180, tx=20, ty=20, tz=20),
    "true": Protocol(name="true", roll=0, pitch=0, yaw=0, tx=0, ty=0, tz=0),
}


def outcome(row: dict) -> str:
    """found = returned and right; refused = the method said no (even if its estimate was right); wrong = returned, wrong."""
    if row["failed"]:
        return "refused"
    return "found" if row["success"] else "wrong"


def run_suite(
    cases: list[str],
    protocols: dict[str, int],
    methods: list[str],
    seed: int = 0,
    data: str | Path | None = None,
    log: Callable[[str], None] = print,
    on_case: Callable[[list[dict], dict], None] | None = None,
) -> tuple[list[dict], dict]:
    """Every method on the same draws of every (case, protocol); `protocols` maps a name to its trial count.

    Returns (rows, info): one row per method x trial (bench columns + case, protocol, outcome); info holds the
    cases' notes and the methods that could not run. `on_case(rows, info)` is called after each case.
    """
    from plotmosaic.bench.real_cases import build_case
    from plotmosaic.bench.run import BenchConfig, run_bench

    rows: list[dict] = []
    info: dict = {"cases": {}, "skipped": {}}
    for ci, name in enumerate(cases):
        t0 = time.perf_counter()
        case = build_case(name, data, seed)
        info["cases"][name] = {
            "note": case.note,
            "meta": case.meta,
            "source_kind": case.source_kind,
            "target_kind": case.target_kind,
            "build_seconds": time.perf_counter() - t0,
        }
        log(
            f"{name}: {case.note} ({len(case.source):,} -> {len(case.target):,} points, built in {time.perf_counter() - t0:.1f} s)"
        )
        for pi, (proto, n) in enumerate(protocols.items()):
            config = BenchConfig(
                protocol=SUITE_PROTOCOLS[proto],
                trials=n,
                seed=seed + 1000 * ci + 100 * pi,
                methods=methods,
            )
            result = run_bench(
                [case.bench_pair()],
                config,
                progress=False,
                log=lambda m, p=proto: log(f"  [{p}] {m}"),
            )
            info["skipped"].update(result.skipped)
            for r in result.rows:
                rows.append({**r, "case": name, "protocol": proto, "outcome": outcome(r)})
        if on_case:
            on_case(rows, info)
    return rows, info


def summarise(rows: list[dict]) -> list[dict]:
    """One dict per (case, protocol, method) in first-seen order."""
    keys = list(dict.fromkeys((r["case"], r["protocol"], r["method"]) for r in rows))
    out = []
    for case, proto, method in keys:
        sub = [r for r in rows if (r["case"], r["protocol"], r["method"]) == (case, proto, method)]
        found = [r for r in sub if r["outcome"] == "found"]
        rmse = {
            p: float(np.sqrt(np.mean([r[p] ** 2 for r in found]))) if found else None
            for p in PARAMS
        }
        t = [np.linalg.norm([r["tx"], r["ty"], r["tz"]]) for r in found]
        wrong = [r for r in sub if r["outcome"] == "wrong"]
        out.append(
            {
                "case": case,
                "protocol": proto,
                "method": method,
                "n": len(sub),
                "found": len(found),
                "refused": sum(r["outcome"] == "refused" for r in sub),
                "wrong": len(wrong),
                "rot_rmse_deg": max(
                    (v for p, v in rmse.items() if p in ("roll", "pitch", "yaw") and v is not None),
                    default=None,
                ),
                **{f"rmse_{p}": v for p, v in rmse.items()},
                "t_rmse_m": float(np.sqrt(np.mean(np.square(t)))) if t else None,
                "wrong_errors": [
                    (
                        float(rotation_angle(np.array([r[p] for p in PARAMS]))[0]),
                        float(np.linalg.norm([r["tx"], r["ty"], r["tz"]])),
                    )
                    for r in wrong
                ],
                "seconds": float(np.mean([r["seconds"] for r in sub])) if sub else None,
            }
        )
    return out


def _fmt(v: float | None, digits: int = 3) -> str:
    return "—" if v is None else f"{v:.{digits}f}"


def markdown(summary: list[dict]) -> str:
    """The suite's table: found / refused / wrong-with-exit-0 per case, protocol and method, RMSE of the found ones."""
    head = [
        "case",
        "protocol",
        "method",
        "n",
        "found",
        "refused",
        "wrong (exit 0)",
        "rot RMSE r/p/y (deg)",
        "t RMSE (cm)",
        "s/trial",
        "wrong poses (deg / m)",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in summary:
        rot = (
            "—"
            if s["rmse_roll"] is None
            else "/".join(_fmt(s[f"rmse_{p}"]) for p in ("roll", "pitch", "yaw"))
        )
        wrong = ", ".join(f"{a:.1f} / {t:.2f}" for a, t in s["wrong_errors"][:4]) + (
            " ..." if len(s["wrong_errors"]) > 4 else ""
        )
        cells = [
            s["case"],
            s["protocol"],
            s["method"],
            str(s["n"]),
            str(s["found"]),
            str(s["refused"]),
            f"**{s['wrong']}**" if s["wrong"] and s["method"] == "forestalign" else str(s["wrong"]),
            rot,
            _fmt(None if s["t_rmse_m"] is None else 100 * s["t_rmse_m"], 1),
            _fmt(s["seconds"], 1),
            wrong or "—",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def reliability(rows: list[dict], method: str = "forestalign", bins: int = 10) -> list[dict]:
    """Per confidence bin: trials, fraction found, and how many were returned (exit 0) / refused."""
    sub = [r for r in rows if r["method"] == method and r.get("confidence") is not None]
    which = [min(max(int(np.floor(r["confidence"] * bins + 1e-9)), 0), bins - 1) for r in sub]
    out = []
    for k in range(bins):
        b = [r for r, w in zip(sub, which) if w == k]
        out.append(
            {
                "lo": k / bins,
                "hi": (k + 1) / bins,
                "n": len(b),
                "found": sum(r["success"] for r in b),
                "returned": sum(not r["failed"] for r in b),
                "wrong_returned": sum(r["outcome"] == "wrong" for r in b),
            }
        )
    return out


def plot_reliability(
    rows: list[dict], path: str | Path, method: str = "forestalign", title: str = ""
) -> Path:
    """Left: fraction correct per confidence bin (a calibrated judge follows the diagonal). Right: every trial's
    confidence against its rotation error, returned (exit 0) or refused, correct or not."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sub = [r for r in rows if r["method"] == method]
    with_conf = [r for r in sub if r.get("confidence") is not None]
    bins = reliability(rows, method)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 5.5))
    mids = [(b["lo"] + b["hi"]) / 2 for b in bins]
    frac = [b["found"] / b["n"] if b["n"] else np.nan for b in bins]
    ax.plot([0, 1], [0, 1], color="grey", lw=0.8, ls="--", label="calibrated")
    ax.bar(
        mids,
        [0 if np.isnan(f) else f for f in frac],
        width=0.09,
        color="tab:blue",
        alpha=0.6,
        label="fraction correct",
    )
    for m, f, b in zip(mids, frac, bins):
        if b["n"]:
            ax.text(m, (0 if np.isnan(f) else f) + 0.02, f"{b['n']}", ha="center", fontsize=8)
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.1)
    ax.set_xlabel(f"{method} confidence")
    ax.set_ylabel("fraction within 1 deg / 10 cm (trials per bin on top)")
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title("reliability")
    styles = {
        ("found", False): ("o", "tab:green", "correct, returned"),
        ("wrong", False): ("X", "tab:red", "WRONG, returned (exit 0)"),
        ("found", True): ("o", "tab:olive", "correct, refused"),
        ("refused", True): ("s", "tab:grey", "wrong, refused (exit 3)"),
    }
    for (kind, refused), (marker, colour, label) in styles.items():
        pts = [
            r
            for r in with_conf
            if bool(r["failed"]) == refused
            and (r["outcome"] == kind or (kind == "found" and r["success"]))
        ]
        if pts:
            err = [
                max(float(rotation_angle(np.array([r[p] for p in PARAMS]))[0]), 1e-3) for r in pts
            ]
            bx.scatter(
                [r["confidence"] for r in pts],
                err,
                marker=marker,
                c=colour,
                s=28,
                label=f"{label} ({len(pts)})",
                edgecolors="black",
                linewidths=0.3,
            )
    bx.axhline(1.0, color="grey", lw=0.8, ls="--")
    bx.set_yscale("log")
    bx.set_xlim(-0.02, 1.02)
    bx.set_xlabel(f"{method} confidence")
    bx.set_ylabel("rotation error (deg)")
    bx.legend(loc="upper right", fontsize=8)
    no_conf = len(sub) - len(with_conf)
    bx.set_title(
        f"every trial ({len(with_conf)} with a confidence"
        + (f", {no_conf} without" if no_conf else "")
        + ")"
    )
    fig.suptitle(
        title or f"{method} on the real-data suite: confidence against correctness", fontsize=10
    )
    fig.tight_layout()
    path = Path(path)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    return path


def write_outputs(
    rows: list[dict], info: dict, out: str | Path, command: str, figure: str | Path | None = None
) -> dict[str, Path]:
    """trials.csv (bench columns + case, protocol, outcome), table.md, summary.json, reliability PNG."""
    import csv

    from plotmosaic.bench.run import CSV_FIELDS

    out = Path(out)
    fields = ["case", "protocol", "outcome", *CSV_FIELDS]
    with atomic_output(out / "trials.csv") as tmp, open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in fields})
    summary = summarise(rows)
    notes = "".join(f"- `{name}`: {c['note']}\n" for name, c in info["cases"].items())
    skipped = "".join(f"\n{m}: not run ({why})\n" for m, why in info["skipped"].items())
    table = f"```\n{command}\n```\n\n" + markdown(summary) + "\nCases:\n" + notes + skipped
    paths = {"trials": out / "trials.csv", "table": write_text_atomic(out / "table.md", table)}
    paths["summary"] = write_text_atomic(
        out / "summary.json",
        json.dumps(
            {
                "command": command,
                "info": info,
                "summary": summary,
                "reliability": reliability(rows),
            },
            indent=1,
            default=float,
        ),
    )
    if any(r["method"] == "forestalign" for r in rows):
        paths["figure"] = plot_reliability(rows, figure or out / "reliability.png")
    return paths
