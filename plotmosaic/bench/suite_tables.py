"""The real-data suite's tables and reliability diagram (bench/real_suite.py runs the trials): outcomes
per case, protocol and method, accuracy of the found, forestalign's coarse generators, and how its
confidence relates to being right; written as table.md, summary.json and a PNG.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from plotmosaic.bench.figures import pyplot
from plotmosaic.bench.methods import METHODS, OURS
from plotmosaic.bench.protocol import PARAMS, rotation_angle
from plotmosaic.config.bench import SUITE_PROTOCOLS
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.pictures import savefig


def _angles(r: dict) -> tuple[float, float]:
    if "rotation_deg" in r:
        return r["rotation_deg"], r["translation_m"]
    err = np.array([r[p] for p in PARAMS])
    return float(rotation_angle(err)[0]), float(np.linalg.norm(err[3:]))


def summarise(rows: list[dict]) -> list[dict]:
    """One dict per (case, protocol, method) in first-seen order; errors (RMSE per angle, median, worst) of the found."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["case"], r["protocol"], r["method"]), []).append(r)
    cases = list(dict.fromkeys(k[0] for k in groups))
    methods = list(METHODS)
    order = sorted(
        groups,
        key=lambda k: (
            cases.index(k[0]),
            list(SUITE_PROTOCOLS).index(k[1]) if k[1] in SUITE_PROTOCOLS else 99,
            methods.index(k[2]) if k[2] in methods else 99,
        ),
    )
    out = []
    for case, proto, method in order:
        sub = groups[(case, proto, method)]
        found = [r for r in sub if r["outcome"] == "found"]
        rmse = {
            p: float(np.sqrt(np.mean([r[p] ** 2 for r in found]))) if found else None
            for p in PARAMS
        }
        rot = [_angles(r)[0] for r in found]
        t = [_angles(r)[1] for r in found]
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
                "rot_rmse_deg": float(np.sqrt(np.mean(np.square(rot)))) if rot else None,
                **{f"rmse_{p}": v for p, v in rmse.items()},
                "t_rmse_m": float(np.sqrt(np.mean(np.square(t)))) if t else None,
                "rot_median_deg": float(np.median(rot)) if rot else None,
                "rot_worst_deg": float(np.max(rot)) if rot else None,
                "t_median_m": float(np.median(t)) if t else None,
                "t_worst_m": float(np.max(t)) if t else None,
                "wrong_errors": [_angles(r) for r in wrong],
                "wrong_trials": [
                    {
                        k: r.get(k)
                        for k in (
                            "trial",
                            "seed",
                            "confidence",
                            "judge_score",
                            "rival_score",
                            "fitness",
                            "result_json",
                            "commit",
                        )
                    }
                    | {"error_deg": _angles(r)[0], "error_m": _angles(r)[1]}
                    for r in wrong
                ],  # fmt: skip
                "seconds": float(np.mean([r["seconds"] for r in sub])) if sub else None,
                "commits": sorted({r.get("commit", "?") for r in sub}),
            }
        )
    return out


def cm(v: float | None) -> float | None:
    return None if v is None else 100 * v


def _fmt(v: float | None, digits: int = 3) -> str:
    return "—" if v is None else f"{v:.{digits}f}"


def markdown(summary: list[dict]) -> str:
    """The suite's table: found / refused / wrong-with-exit-0 per case, protocol and method; errors of the found."""
    head = [
        "case",
        "protocol",
        "method",
        "n",
        "found",
        "refused",
        "wrong (exit 0)",
        "rot median / worst (deg)",
        "t median / worst (cm)",
        "rot RMSE r/p/y (deg)",
        "t RMSE (cm)",
        "s/trial",
        "wrong poses (deg / m)",
        "commit",
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
            f"**{s['wrong']}**" if s["wrong"] and s["method"] in OURS else str(s["wrong"]),
            f"{_fmt(s.get('rot_median_deg'))} / {_fmt(s.get('rot_worst_deg'))}",
            f"{_fmt(cm(s.get('t_median_m')), 1)} / {_fmt(cm(s.get('t_worst_m')), 1)}",
            rot,
            _fmt(cm(s["t_rmse_m"]), 1),
            _fmt(s["seconds"], 1),
            wrong or "—",
            ", ".join(s.get("commits", [])),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


ACCURACY_CASES = ("uas-als", "treels-2views", "mls-2views")  # issue 15's accuracy targets


def accuracy(rows: list[dict], cases: Iterable[str] = ACCURACY_CASES) -> str:
    """RMSE per angle and of the translation over every found trial of a case (all protocols), per method."""
    head = [
        "case",
        "method",
        "found / n",
        "roll",
        "pitch",
        "yaw (deg RMSE)",
        "rotation",
        "t (mm RMSE)",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for case in cases:
        methods = list(dict.fromkeys(r["method"] for r in rows if r["case"] == case))
        for m in methods:
            sub = [r for r in rows if r["case"] == case and r["method"] == m]
            found = [r for r in sub if r["outcome"] == "found"]
            if not found:
                lines.append(f"| {case} | {m} | 0 / {len(sub)} | — | — | — | — | — |")
                continue
            rms = {p: float(np.sqrt(np.mean([r[p] ** 2 for r in found]))) for p in PARAMS}
            rot = float(np.sqrt(np.mean([_angles(r)[0] ** 2 for r in found])))
            t = float(np.sqrt(np.mean([_angles(r)[1] ** 2 for r in found])))
            cells = [case, m, f"{len(found)} / {len(sub)}"]
            cells += [f"{rms[p]:.4f}" for p in ("roll", "pitch", "yaw")]
            cells += [f"{rot:.4f}", f"{1000 * t:.1f}"]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def generators(rows: list[dict]) -> str:
    """forestalign's coarse stage per case and protocol: trials with a hypothesis of each generator near the
    truth (within 3 deg / 1 m, after screening), and which generator:vertical won."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        if r["method"] == "forestalign" and "near" in r:
            groups.setdefault((r["case"], r["protocol"]), []).append(r)
    if not groups:
        return ""
    gens = sorted({g for sub in groups.values() for r in sub for g in r["near"]} | {"raster"})
    head = ["case", "protocol", "n", *[f"near: {g}" for g in gens], "winners"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for (case, proto), sub in groups.items():
        wins: dict[str, int] = {}
        for r in sub:
            if r.get("winner"):
                wins[r["winner"]] = wins.get(r["winner"], 0) + 1
        cells = [case, proto, str(len(sub))]
        cells += [str(sum(g in r["near"] for r in sub)) for g in gens]
        cells.append(
            ", ".join(f"{k} {v}" for k, v in sorted(wins.items(), key=lambda kv: -kv[1])) or "—"
        )
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
    plt = pyplot()
    sub = [r for r in rows if r["method"] == method]
    with_conf = [r for r in sub if r.get("confidence") is not None]
    bins = reliability(rows, method)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 5.5))
    mids = [(b["lo"] + b["hi"]) / 2 for b in bins]
    frac = [b["found"] / b["n"] if b["n"] else 0 for b in bins]
    ax.plot([0, 1], [0, 1], color="grey", lw=0.8, ls="--", label="calibrated")
    ax.bar(mids, frac, width=0.09, color="tab:blue", alpha=0.6, label="fraction correct")
    for m, f, b in zip(mids, frac, bins):
        if b["n"]:
            ax.text(m, f + 0.02, f"{b['n']}", ha="center", fontsize=8)
    ax.set(xlim=(0, 1), ylim=(0, 1.1))
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
            and not (kind == "refused" and r["success"])
        ]
        if pts:
            err = [max(_angles(r)[0], 1e-3) for r in pts]
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
    bx.set(xlabel=f"{method} confidence", ylabel="rotation error (deg)")
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
    return savefig(fig, path, dpi=100, tight=False)


def write_outputs(
    rows: list[dict], info: dict, out: str | Path, command: str, figure: str | Path | None = None
) -> dict[str, Path]:
    """table.md, summary.json and the reliability PNG, from `rows` (all of a trials file) and the cases' info."""
    out = Path(out)
    summary = summarise(rows)
    cases = info.get("cases", {})
    notes = "".join(f"- `{name}`: {c['note']}\n" for name, c in cases.items())
    skipped = "".join(f"\n{m}: not run ({why})\n" for m, why in info.get("skipped", {}).items())
    commits: dict[str, int] = {}
    for r in rows:
        commits[r.get("commit", "?")] = commits.get(r.get("commit", "?"), 0) + 1
    table = (
        f"```\n{command}\n```\n\ncommits (rows): "
        + ", ".join(f"{c} ({n})" for c, n in commits.items())
        + "\n\n"
        + markdown(summary)
        + "\nAccuracy (RMSE over the found trials of all protocols):\n\n"
        + accuracy(rows)
    )
    gens = generators(rows)
    if gens:
        table += "\nforestalign's coarse stage (hypotheses near the truth, winners):\n\n" + gens
    table += "\nCases:\n" + notes + skipped
    paths = {"table": write_text_atomic(out / "table.md", table)}
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
