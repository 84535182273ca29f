"""Calibration of the judge against scenes that are not a forest (issue 38 item 2, issue 53).

Industrial / indoor / urban scenes (the E57 samples, a synthetic room and street) and random clouds
(uniform in a box, a gaussian blob), each aligned onto forest scans (simulated small / paper presets,
the spanner MLS clip, the treels pine plot) and the reverse, through the same path as `plotmosaic
align` (prepare both, register_prepared). Every one must be refused (exit 3). The right forest pairs
of bench_judge.py's cases are run through the same path (`--right`): every one must still be accepted.

    nice -n 10 .venv/bin/python benchmarks/bench_judge_scenes.py --work /tmp/scenes --json rows.json
    nice -n 10 .venv/bin/python benchmarks/bench_judge_scenes.py --right --quick   # right sim pairs
    nice -n 10 .venv/bin/python benchmarks/bench_judge_scenes.py --forests --work /tmp/scenes

`--forests` prints the scene figures of every forest cloud the check must pass and the figure it
decides on: the real clouds, one or two scans and the ALS tile of every simulator preset (the
issue-53 stands at 50, 150 and 400 stems/ha too), a forest drawn as points, and virtual scans cut
from the real clouds.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from bench_judge import DATA, cases

from plotmosaic.align import scene
from plotmosaic.align.pair import register_prepared
from plotmosaic.align.pipeline import prepare_pair
from plotmosaic.align.prepare import prepare_cloud
from plotmosaic.config.align import AlignConfig, default_levels
from plotmosaic.config.cuts import DrawnConfig
from plotmosaic.config.simulate import PRESETS
from plotmosaic.errors import InputError, RegistrationFailed
from plotmosaic.io.las import PointCloud, read_cloud
from plotmosaic.simulate.drawn import drawn_scan
from plotmosaic.simulate.from_cloud import cut_views
from plotmosaic.simulate.run import simulate


def _plane(rng, origin, u, v, spacing: float) -> np.ndarray:
    """Points on the parallelogram origin + a u + b v (a, b in 0-1), about `spacing` apart, 5 mm noise."""
    n = int(np.linalg.norm(u) * np.linalg.norm(v) / spacing**2)
    a, b = rng.random((2, max(n, 1)))
    return origin + a[:, None] * u + b[:, None] * v + rng.normal(0, 0.005, (max(n, 1), 3))


def room(seed: int = 0, spacing: float = 0.03) -> np.ndarray:
    """A box room 8 x 6 x 3 m (floor, ceiling, four walls) with a table and two cupboards."""
    rng = np.random.default_rng(seed)
    X, Y, Z = np.eye(3)
    parts = [
        _plane(rng, np.zeros(3), 8 * X, 6 * Y, spacing),
        _plane(rng, 3 * Z, 8 * X, 6 * Y, spacing),
        _plane(rng, np.zeros(3), 8 * X, 3 * Z, spacing),
        _plane(rng, 6 * Y, 8 * X, 3 * Z, spacing),
        _plane(rng, np.zeros(3), 6 * Y, 3 * Z, spacing),
        _plane(rng, 8 * X, 6 * Y, 3 * Z, spacing),
        _plane(rng, np.array([3.0, 2.5, 0.75]), 2 * X, 1 * Y, spacing),  # table top
    ]
    for x0 in (0.2, 6.8):  # cupboards: four faces each
        o = np.array([x0, 0.1, 0.0])
        parts += [_plane(rng, o + d, a, b, spacing) for d, a, b in _box(1.0, 0.6, 2.0)]
    return np.vstack(parts)


def _box(w: float, d: float, h: float):
    X, Y, Z = np.eye(3)
    return [
        (np.zeros(3), w * X, h * Z),
        (d * Y, w * X, h * Z),
        (np.zeros(3), d * Y, h * Z),
        (w * X, d * Y, h * Z),
        (h * Z, w * X, d * Y),
    ]


def street(seed: int = 0, spacing: float = 0.08) -> np.ndarray:
    """A 60 m street: road, two rows of facades 8-20 m high with recessed windows, lamp posts
    (0.15 m poles, 6 m: stem-like) and parked cars (boxes)."""
    rng = np.random.default_rng(seed)
    X, Y, Z = np.eye(3)
    parts = [_plane(rng, np.array([0.0, -10.0, 0.0]), 60 * X, 20 * Y, spacing)]
    for side in (-8.0, 8.0):
        x = 0.0
        while x < 60:
            w, h = rng.uniform(8, 15), rng.uniform(8, 20)
            facade = _plane(rng, np.array([x, side, 0.0]), w * X, h * Z, spacing)
            # windows: points inside a window cell pushed 0.2 m back
            wx = (facade[:, 0] - x) % 2.5 < 1.2
            wz = (facade[:, 2] % 3.0 > 1.0) & (facade[:, 2] > 3.0)
            facade[wx & wz, 1] += 0.2 * np.sign(side)
            parts.append(facade)
            x += w
        for px in np.arange(5.0, 60.0, 12.0):  # lamp posts
            t = rng.uniform(0, 2 * np.pi, 3000)
            z = rng.uniform(0, 6, 3000)
            c = np.array([px, side - 2 * np.sign(side), 0.0])
            parts.append(np.column_stack([c[0] + 0.075 * np.cos(t), c[1] + 0.075 * np.sin(t), z]))
        for cx in np.arange(2.0, 58.0, 9.0):  # cars
            o = np.array([cx, side - 4 * np.sign(side) - 0.9, 0.0])
            parts += [_plane(rng, o + d, a, b, spacing) for d, a, b in _box(4.2, 1.8, 1.5)]
    return np.vstack(parts)


def uniform_box(seed: int = 0, n: int = 200_000) -> np.ndarray:
    """Uniform random points in a 30 x 30 x 15 m box."""
    return np.random.default_rng(seed).random((n, 3)) * [30.0, 30.0, 15.0]


def blob(seed: int = 0, n: int = 200_000) -> np.ndarray:
    """A gaussian blob, sigma 6 / 6 / 3 m."""
    return np.random.default_rng(seed).normal(0, 1, (n, 3)) * [6.0, 6.0, 3.0]


def scenes() -> dict:
    """name -> (xyz, kind) of every scene that is not a forest."""
    out = {}
    for name in ("pumpAVisualReferenceImage", "bunnyDouble", "ColouredCubeFloat"):
        path = DATA / "e57" / f"{name}.e57"
        if path.exists():
            out[name] = read_cloud(path, attributes=False).xyz
    out.update(room=room(), street=street(), uniform_box=uniform_box(), blob=blob())
    return out


def forests(work: Path, paper: bool) -> dict:
    """name -> xyz of the forest scans the scenes are aligned onto."""
    out = {}
    small = work / "sim_small"
    if not (small / "ground_truth.json").exists():
        simulate(small, "small", seed=0)
    out["sim small P1-S0"] = read_cloud(small / "P1" / "P1-S0.laz", attributes=False).xyz
    if paper:
        big = work / "sim_paper"
        if not (big / "ground_truth.json").exists():
            simulate(big, "paper", seed=0, points_per_scan=400_000)
        out["sim paper P1-S0"] = read_cloud(big / "P1" / "P1-S0.laz", attributes=False).xyz
    for name, path in (
        ("spanner MLS_Clip", DATA / "spanner" / "MLS_Clip.laz"),
        ("treels pine_plot", DATA / "treels" / "pine_plot.laz"),
    ):
        if path.exists():
            out[name] = read_cloud(path, attributes=False).xyz
    return out


def run(name: str, xs, xt, ks: str, kt: str, cfg: AlignConfig, full: bool = True) -> dict:
    """One pair through align's path: prepared both, registered; the outcome and the figures.
    Not `full`: a pair the scene check refuses is not registered (the judge runs the check before it
    weighs any pose, whatever the pose: the outcome is the same, minutes sooner)."""
    t0 = time.perf_counter()
    try:
        ps, pt = prepare_pair(
            PointCloud(xs),
            PointCloud(xt),
            (ks, kt),
            (default_levels(ks), default_levels(kt)),
            cfg,
            0,
        )
    except InputError as exc:  # exit 2: the cloud cannot even be prepared (a few cm across)
        print(f"  {name}: refused (exit 2) {exc}", file=sys.stderr)
        return {"pair": name, "accepted": False, "exit": 2, "error": str(exc), "seconds": 0.0}
    row = {
        "pair": name,
        "source_scene": scene.record(ps, cfg.judge),
        "target_scene": scene.record(pt, cfg.judge),
    }
    try:
        if not full:
            scene.check(ps, pt, cfg.judge)
        r = register_prepared(ps, pt, cfg, None, 0)
        row.update(accepted=True, exit=0, error=None)
    except RegistrationFailed as exc:
        r = getattr(exc, "result", None)
        row.update(accepted=False, exit=3, error=str(exc))
    if r is not None:
        j = r.judge or {}
        row.update(
            fitness=r.fitness,
            overlap=r.overlap,
            confidence=r.confidence,
            score=j.get("score"),
            sharpness=j.get("sharpness"),
            fine_share=j.get("fine_share"),
            margin=j.get("margin"),
        )
    row["seconds"] = time.perf_counter() - t0
    verdict = "ACCEPTED" if row["accepted"] else "refused"
    print(f"  {name}: {verdict} ({row['seconds']:.0f} s) {row['error'] or ''}", file=sys.stderr)
    return row


def describe(s: dict | None) -> str:
    """Scene figures in a table cell: extent m, stems, above-ground lines, ground, crossing planes."""
    if s is None:
        return "-"
    return (
        f"{s['extent_m']:.1f} m, stems {s['stems']}, above-ground lines"
        f" {s['above_linear_share']:.3f}, ground {s['ground_share']:.2f}, branches"
        f" {s['branch_share']:.3f},"
        f" crossing {s['crossing_share']:.2f}"
    )


# every simulator preset, one or two scans of it (the large presets' first plot and positions) and
# its ALS tile; the issue-53 stands at the stem densities measured
PRESET_CASES = [
    ("small", {}, 1),
    ("paper", {"points_per_scan": 400_000}, 1),
    ("region", {"points_per_scan": 200_000, "plot_centres": [(0.0, 0.0)]}, 1),
    ("region10", {"points_per_scan": 200_000, "plot_centres": [(0.0, 0.0)]}, 1),
    ("large", {"points_per_scan": 200_000}, 2),
    ("understorey", {"points_per_scan": 200_000}, 1),
    ("grassland", {"points_per_scan": 200_000}, 2),
    ("prepost", {"points_per_scan": 200_000}, 1),
    ("scattered", {}, 2),
    ("bare-stems", {"tree_density": 50.0}, 2),
    ("bare-stems", {}, 2),
    ("bare-stems", {"tree_density": 400.0}, 2),
]


def forest_clouds(work: Path):
    """(name, kind, xyz) of every forest cloud the scene check must pass."""
    for rel, kind in (
        ("spanner/ALS_Clip.laz", "als"),
        ("spanner/UAS_Clip.laz", "uls"),
        ("spanner/MLS_Clip.laz", "mls"),
        ("treels/pine_plot.laz", "tls"),
    ):
        if (DATA / rel).exists():
            yield rel, kind, read_cloud(DATA / rel, attributes=False).xyz
    for preset, overrides, n_scans in PRESET_CASES:
        layout = PRESETS[preset].scan_layout
        tag = preset + "".join(f" {k}={v}" for k, v in overrides.items() if k != "plot_centres")
        out = work / ("forest_" + tag.replace(" ", "_").replace("=", "-"))
        if not (out / "ground_truth.json").exists():
            simulate(out, preset, seed=0, **overrides, scan_layout=layout[:n_scans])
        for k in range(n_scans):
            plot = "PRE" if preset == "prepost" else "P1"
            path = out / plot / f"{plot}-S{k}.laz"
            yield f"`{tag}` {plot}-S{k}", "tls", read_cloud(path, attributes=False).xyz
        yield f"`{tag}` ALS", "als", read_cloud(out / "als" / "als.laz", attributes=False).xyz
    shares = (0.40, 0.02, 0.48, 0.10)  # crowns of scattered points hold half of it
    yield (
        "forest drawn as points, 300k",
        "tls",
        drawn_scan(0, DrawnConfig(points_per_scan=300_000, shares=shares)),
    )
    yield "forest drawn as points, 1.5M (`simulate --drawn`)", "tls", drawn_scan(1)
    for rel, kind, ranges in (
        ("treels/pine_plot.laz", "tls", (6.0, 15.0)),
        ("spanner/MLS_Clip.laz", "mls", (6.0, 15.0)),
        ("spanner/UAS_Clip.laz", "tls", (6.0, 15.0)),
    ):
        if not (DATA / rel).exists():
            continue
        pts = read_cloud(DATA / rel, attributes=False).xyz
        centre = pts[:, :2].mean(axis=0)
        for j, off in enumerate(([0.0, 0.0], [-4.0, 3.0], [4.0, -3.0])):
            for r in ranges:
                view = cut_views(pts, [centre + off], seed=j, max_range=r)[0]
                yield f"view of {rel} #{j}, {r:.0f} m range", kind, view.points


def forest_table(work: Path) -> str:
    """The figures of every forest cloud, the figure it passes on, and whether it passes."""
    cfg = AlignConfig()
    lines = [
        "| forest cloud | kind | points | extent m | stems | above-ground lines | ground | branches"
        " | crossing planes | decided by |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    refused = 0
    for name, kind, xyz in forest_clouds(work):
        cloud = prepare_cloud(PointCloud(xyz), kind, default_levels(kind), cfg, 0)
        s = scene.figures(cloud, cfg.judge)
        why = scene.problems(s, cfg.judge)
        refused += bool(why)
        decided = scene.decided_by(s, cfg.judge) if not why else "**REFUSED**: " + "; ".join(why)
        lines.append(
            f"| {name} | {kind} | {len(xyz):,} | {s.extent_m:.1f} | {s.stems} |"
            f" {s.above_linear_share:.3f} | {s.ground_share:.2f} | {s.branch_share:.3f} |"
            f" {s.crossing_share:.3f} |"
            f" {decided} |"
        )
        print(lines[-1], file=sys.stderr, flush=True)
    lines.append(f"\nforest clouds refused: {refused} / {len(lines) - 2}")
    return "\n".join(lines)


def table(rows: list, right: bool) -> str:
    """Wrong pairs: any accepted is WRONG. Right pairs: any refused by the scene check is WRONG; one
    refused by the figures (the search did not find the pose) is counted apart, as before the check."""
    head = (
        "| pair | outcome | fitness | overlap | confidence | sharpness | source scene | target scene"
        " | why |"
    )
    lines = [head, "|---|---|---|---|---|---|---|---|---|"]
    bad = figures = 0
    for x in rows:
        by_scene = "not a forest scene" in (x["error"] or "")
        ok = x["accepted"] == right or (right and not by_scene)
        figures += right and not x["accepted"] and not by_scene
        bad += not ok
        out = ("accepted" if x["accepted"] else f"refused (exit {x['exit']})") + (
            "" if ok else " **WRONG**"
        )
        f = [
            "-" if x.get(k) is None else f"{x[k]:.3f}"
            for k in ("fitness", "overlap", "confidence", "sharpness")
        ]
        s = [describe(x.get(k)) for k in ("source_scene", "target_scene")]
        why = (x["error"] or "").replace("pair cannot be registered: ", "")[:140]
        lines.append(f"| {x['pair']} | {out} | {' | '.join(f)} | {s[0]} | {s[1]} | {why} |")
    if right:
        lines.append(
            f"\nright pairs refused by the scene check: {bad} / {len(rows)}; refused by the pose's"
            f" figures (not found): {figures}; accepted: {sum(x['accepted'] for x in rows)}"
        )
    else:
        lines.append(f"\nwrong pairs accepted: {bad} / {len(rows)}")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/plotmosaic-bench-scenes"))
    ap.add_argument("--json", type=Path, help="write the raw rows here")
    ap.add_argument("--only", default="", help="run only the pairs whose name contains this")
    ap.add_argument("--no-paper", action="store_true", help="leave out the 400k paper scan")
    ap.add_argument("--right", action="store_true", help="instead: bench_judge.py's right pairs")
    ap.add_argument("--quick", action="store_true", help="with --right: simulated pairs only")
    ap.add_argument("--table", type=Path, help="instead: print the table of a --json file")
    ap.add_argument(
        "--forests", action="store_true", help="instead: the figures of every forest cloud"
    )
    ap.add_argument(
        "--full", action="store_true", help="register pairs the scene check refuses all the same"
    )
    args = ap.parse_args()
    if args.table:
        print(table(json.loads(args.table.read_text()), args.right))
        return
    args.work.mkdir(parents=True, exist_ok=True)
    if args.forests:
        print(forest_table(args.work))
        return
    cfg = AlignConfig()
    rows = []

    def keep(row):
        rows.append(row)
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1, default=float))

    if args.right:
        for name, xs, xt, ks, kt, _truth, related in cases(args.quick, args.work):
            if related and args.only in name:
                keep(run(name, xs, xt, ks, kt, cfg))
        print(table(rows, True))
        return
    woods = forests(args.work, not args.no_paper)
    for sname, xs in scenes().items():
        for fname, xf in woods.items():
            if fname.startswith("sim paper") and not sname.startswith("pump"):
                continue  # the 400k scan: the case only
            kf = "mls" if "MLS" in fname else "tls"
            for label, a, b, ka, kb in (
                (f"{sname} -> {fname}", xs, xf, "tls", kf),
                (f"{fname} -> {sname}", xf, xs, kf, "tls"),
            ):
                if args.only in label:
                    keep(run(label, a, b, ka, kb, cfg, args.full))
    print(table(rows, False))


if __name__ == "__main__":
    main()
