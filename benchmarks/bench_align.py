"""ForestAlign pairwise benchmark: level purity, accuracy over random initial errors, speed.

    python benchmarks/bench_align.py --sim /tmp/bench_align/sim --trials 50            # simulated small plot
    python benchmarks/bench_align.py --real /work/shared/data/spanner --trials 20      # UAS -> ALS clips
    python benchmarks/bench_align.py --speed SRC.laz TGT.laz --kinds tls tls           # wall/CPU of one pair

Accuracy trials: each pair is prepared once (voxels, normals, levels), then registered from
`trials` initial guesses T_true @ P, with P uniform in +-10 deg on each angle and +-2 m on each
axis (all six together, rotating about the source centroid). Errors: the residual rotation's
angles and the displacement of the source centroid (not of the file origin, which is far away in UTM).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from plotmosaic.align.complexity import level_purity
from plotmosaic.align.pair import register_prepared
from plotmosaic.align.pipeline import AlignRequest, align_files
from plotmosaic.align.prepare import prepare_cloud
from plotmosaic.config.align import AlignConfig
from plotmosaic.errors import RegistrationFailed
from plotmosaic.io.frame import apply_transform
from plotmosaic.io.las import read_cloud

CLASSES = {0: "ground", 1: "stem+branch", 2: "foliage", 3: "understory"}


COARSE = True  # --no-coarse: ICP from the guess alone (the paper's local setting)


def config(mode: str) -> AlignConfig:
    """The pipeline's defaults: the initial guess is a prior that the coarse stage searches around."""
    cfg = AlignConfig(complexity=mode)
    cfg.coarse.enabled = COARSE
    return cfg


def perturbation(rng, centre, max_deg, max_m):
    P = np.eye(4)
    P[:3, :3] = Rotation.from_euler(
        "xyz", rng.uniform(-max_deg, max_deg, 3), degrees=True
    ).as_matrix()
    P[:3, 3] = centre - P[:3, :3] @ centre + rng.uniform(-max_m, max_m, 3)
    return P


def errors(T, T_true, centre):
    D = np.linalg.inv(T_true) @ T
    return np.r_[
        Rotation.from_matrix(D[:3, :3]).as_euler("xyz", degrees=True),
        apply_transform(D, centre[None])[0] - centre,
    ]


def trials(name, ps, pt, T_true, cfg, n, bounds, seed=0, max_deg=10.0, max_m=2.0, reference=None):
    """`reference`: a pose to measure the spread of the results about (e.g. the one reached from the truth)."""
    rng = np.random.default_rng(seed)
    centre = ps.frame.to_global(ps.points.mean(axis=0))
    errs, failed, secs, spread = [], 0, [], []
    for i in range(n):
        P = perturbation(rng, centre, max_deg, max_m)
        t0 = time.perf_counter()
        try:
            res = register_prepared(ps, pt, cfg, init=T_true @ P, seed=i)
        except RegistrationFailed as exc:
            failed += 1
            res = exc.result
        errs.append(errors(res.transform, T_true, centre))
        if reference is not None:
            spread.append(np.abs(errors(res.transform, reference, centre)))
        secs.append(time.perf_counter() - t0)
    e = np.array(errs)
    rmse = np.sqrt(np.mean(e**2, axis=0))
    ok = (np.abs(e[:, :3]).max(axis=1) <= bounds[0]) & (np.abs(e[:, 3:]).max(axis=1) <= bounds[1])
    row = {
        "pair": name,
        "trials": n,
        "rmse_deg": rmse[:3].round(4).tolist(),
        "rmse_m": rmse[3:].round(4).tolist(),
        "within_bounds": int(ok.sum()),
        "exit3": failed,
        "seconds_per_trial": float(np.median(secs)),
        "rmse_within_bounds_deg": np.sqrt(np.mean(e[ok, :3] ** 2, axis=0)).round(4).tolist()
        if ok.any()
        else None,
        "rmse_within_bounds_m": np.sqrt(np.mean(e[ok, 3:] ** 2, axis=0)).round(4).tolist()
        if ok.any()
        else None,
    }
    if spread:
        worst = np.max(spread, axis=0)
        row["max_from_reference_deg"], row["max_from_reference_m"] = (
            worst[:3].round(4).tolist(),
            worst[3:].round(4).tolist(),
        )
        print(
            f"  largest deviation from the reference pose: {worst[:3].max():.3f} deg, {100 * worst[3:].max():.2f} cm"
        )
    print(
        f"| {name} | {n} | "
        + " / ".join(f"{v:.3f}" for v in rmse[:3])
        + " | "
        + " / ".join(f"{100 * v:.1f}" for v in rmse[3:])
        + f" | {ok.sum()}/{n} | {failed} | {np.median(secs):.1f} s |",
        flush=True,
    )
    return row


def purity_rows(name, cloud, kind, k, mode, seed):
    p = prepare_cloud(cloud, kind, k, config(mode), seed)
    labels = cloud.attrs["label"][
        cKDTree(p.frame.to_local(cloud.xyz)).query(p.level_points, workers=2)[1]
    ]
    rows = level_purity(p.levels, labels, p.k)
    for r, st in zip(rows, p.level_stats):
        shares = ", ".join(
            f"{CLASSES.get(c, c)} {v:.2f}"
            for c, v in sorted(r["classes"].items(), key=lambda kv: -kv[1])
        )
        print(
            f"| {name} | {mode} | {r['level']} | {r['size']:,} | {st['kappa']:.1f} | "
            f"{CLASSES.get(r['majority'], r['majority'])} | {r['purity']:.2f} | {shares} |",
            flush=True,
        )
    return p, rows


def bench_sim(simdir: Path, n: int, modes: list[str]) -> dict:
    from plotmosaic.poses import load_poses

    if not (simdir / "ground_truth.json").exists():
        from plotmosaic.simulate.run import simulate

        simulate(simdir, "small", seed=0)
    truth = load_poses(simdir / "ground_truth.json")
    scans = {
        sid: read_cloud(simdir / "P1" / f"{sid}.laz", attributes=["label"])
        for sid in ("P1-S0", "P1-S1")
    }
    als = read_cloud(simdir / "als" / "als.laz", attributes=["label"])
    out = {"purity": {}, "accuracy": []}
    print(
        "\n| cloud | signal | level | points | kappa | majority | purity | classes |\n|---|---|---|---|---|---|---|---|"
    )
    prepared = {}
    for mode in modes:
        for sid, cloud in scans.items():
            prepared[(mode, sid)], out["purity"][f"{mode}:{sid}"] = purity_rows(
                sid, cloud, "tls", 3, mode, 0
            )
        prepared[(mode, "als")], out["purity"][f"{mode}:als"] = purity_rows(
            "als", als, "als", 2, mode, 1
        )
    print(
        "\n| pair | trials | RMSE deg (x/y/z) | RMSE cm (x/y/z) | within bounds | exit 3 | s/trial |\n|---|---|---|---|---|---|---|"
    )
    for mode in modes:
        for s, t in (("P1-S1", "P1-S0"),):
            T_true = np.linalg.inv(truth.transform(t)) @ truth.transform(s)
            out["accuracy"].append(
                trials(
                    f"{mode}: TLS {s} -> {t}",
                    prepared[(mode, s)],
                    prepared[(mode, t)],
                    T_true,
                    config(mode),
                    n,
                    (0.1, 0.02),
                )
            )
        out["accuracy"].append(
            trials(
                f"{mode}: TLS P1-S0 -> ALS",
                prepared[(mode, "P1-S0")],
                prepared[(mode, "als")],
                truth.transform("P1-S0"),
                config(mode),
                n,
                (0.3, 0.05),
            )
        )
    return out


def bench_real(spanner: Path, n: int, modes: list[str]) -> dict:
    uas = read_cloud(spanner / "UAS_Clip.laz", attributes=False)
    als = read_cloud(spanner / "ALS_Clip.laz", attributes=False)
    out = {"accuracy": []}
    print(
        "\n| pair | trials | RMSE deg (x/y/z) | RMSE cm (x/y/z) | within bounds | exit 3 | s/trial |\n|---|---|---|---|---|---|---|"
    )
    for mode in modes:
        cfg = config(mode)
        ps, pt = prepare_cloud(uas, "uls", 2, cfg, 0), prepare_cloud(als, "als", 2, cfg, 1)
        # truth: the clips' own georeference (identity), itself good to a few cm; the reference is the
        # pose ForestAlign reaches when it starts there, so the spread shows how repeatable the trials are
        local = AlignConfig(complexity=mode)
        local.coarse.enabled = False
        reference = register_prepared(ps, pt, local, init=np.eye(4), seed=0).transform
        c = ps.frame.to_global(ps.points.mean(axis=0))
        e = errors(reference, np.eye(4), c)
        print(
            f"reached from the truth: {' / '.join(f'{v:+.3f}' for v in e[:3])} deg, {' / '.join(f'{100 * v:+.1f}' for v in e[3:])} cm"
        )
        out["accuracy"].append(
            trials(
                f"{mode}: UAS -> ALS vs identity",
                ps,
                pt,
                np.eye(4),
                cfg,
                n,
                (0.3, 0.05),
                reference=reference,
            )
        )
    return out


def bench_speed(
    src: Path, tgt: Path, kinds: list[str], mode: str, init: Path | None, gt: str | None
) -> dict:
    """One pair from anywhere (or from `init`, a JSON 4x4 prior), reading included; `gt`: a poses file
    (or identity) to print the pose error against."""
    from plotmosaic.bench.pairs import load_truth
    from plotmosaic.commands.align import load_init

    T0 = load_init(init) if init else None
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        request = AlignRequest(
            source_kind=kinds[0], target_kind=kinds[1], config=config(mode), init=T0
        )
        res = align_files(src, tgt, request)
    except RegistrationFailed as exc:
        print(f"exit 3: {exc}")
        res = exc.result
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(
        f"speed {src.name} -> {tgt.name}: wall {wall:.1f} s, CPU {cpu:.1f} s, fitness {res.fitness:.3f}"
    )
    print(json.dumps(res.timings, indent=1, default=float))
    out = {"wall": wall, "cpu": cpu, "timings": res.timings}
    if gt:
        T_true = load_truth(gt, src, tgt)
        centre = read_cloud(src, attributes=False).xyz[::97].mean(axis=0)
        e = errors(res.transform, T_true, centre)
        out["error_deg"], out["error_m"] = float(np.abs(e[:3]).max()), float(np.abs(e[3:]).max())
        print(
            f"error against the truth: {out['error_deg']:.4f} deg, {100 * out['error_m']:.2f} cm (largest angle / axis)"
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--sim", type=Path, help="simulated plot folder (the small preset is made there if missing)"
    )
    ap.add_argument("--real", type=Path, help="the spanner clips folder")
    ap.add_argument("--speed", type=Path, nargs=2, metavar=("SOURCE", "TARGET"))
    ap.add_argument(
        "--purity",
        type=Path,
        nargs="+",
        metavar="SCAN",
        help="simulated TLS scans (with labels): level purity only",
    )
    ap.add_argument("--kinds", nargs=2, default=["tls", "tls"])
    ap.add_argument(
        "--gt", help="--speed: ground-truth poses file (or 'identity') for the pose error"
    )
    ap.add_argument("--init", type=Path, help="--speed: initial guess JSON")
    ap.add_argument("--trials", type=int, default=50)
    ap.add_argument("--modes", nargs="+", default=["vmf+eigen", "vmf"])
    ap.add_argument("--json", type=Path, help="also write the figures as JSON")
    ap.add_argument(
        "--no-coarse",
        action="store_true",
        help="ICP from the initial guess alone (paper's local setting)",
    )
    args = ap.parse_args()
    global COARSE
    COARSE = not args.no_coarse
    out = {}
    if args.sim:
        out["sim"] = bench_sim(args.sim, args.trials, args.modes)
    if args.real:
        out["real"] = bench_real(args.real, args.trials, args.modes)
    if args.purity:
        print(
            "\n| cloud | signal | level | points | kappa | majority | purity | classes |\n|---|---|---|---|---|---|---|---|"
        )
        out["purity"] = {
            f"{mode}:{path.stem}": purity_rows(
                path.stem, read_cloud(path, attributes=["label"]), "tls", 3, mode, 0
            )[1]
            for path in args.purity
            for mode in args.modes
        }
    if args.speed:
        out["speed"] = bench_speed(*args.speed, args.kinds, args.modes[0], args.init, args.gt)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1, default=float))


if __name__ == "__main__":
    main()
