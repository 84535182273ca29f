"""Circle normals on stems against plane normals, on real views thinned until the sparse rule holds.

    python benchmarks/sparse_stems.py --data ../shared/data [--cases treels-2views:0.1,mls-2views:1] [--draws 8]

Each draw cuts the case's two virtual scans (exact truth), keeps a seeded share of each view's points
(`case:share`; so that a normal's 0.25 m sphere holds too few and the 1 m radius is used: the MLS
views are that sparse already), prepares both
with the defaults and again with `[align.stem_normals] kinds = []`, and runs the final ICP from the
truth moved by 3 cm / 0.05 deg. Printed per case and setting: rotation and translation error (mean,
rms, worst) of the final pose against the truth.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial.transform import Rotation

from plotmosaic.align.fine import final_icp
from plotmosaic.align.prepare import prepare_cloud
from plotmosaic.bench.real_cases import build_case
from plotmosaic.config.align import AlignConfig
from plotmosaic.io.frame import to_global_transform, to_local_transform
from plotmosaic.io.las import PointCloud

SETTINGS = {"circles": AlignConfig(), "planes": AlignConfig(stem_normals={"kinds": []})}


def _nudge(rng: np.random.Generator) -> np.ndarray:
    """A rigid motion of 3 cm and 0.05 deg in random directions."""
    T = np.eye(4)
    axis, d = rng.normal(size=3), rng.normal(size=3)
    T[:3, :3] = Rotation.from_rotvec(np.radians(0.05) * axis / np.linalg.norm(axis)).as_matrix()
    T[:3, 3] = 0.03 * d / np.linalg.norm(d)
    return T


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="../shared/data")
    ap.add_argument("--cases", default="treels-2views:0.1,mls-2views:1", help="case:share kept")
    ap.add_argument("--draws", type=int, default=8)
    a = ap.parse_args()
    print(
        "| case | normals | sparse | rotation mean / rms / worst (deg) | translation mean / rms / worst (cm) |"
    )
    print("|---|---|---|---|---|")
    for item in a.cases.split(","):
        name, _, share = item.partition(":")
        keep = float(share or 1)
        errs = {k: [] for k in SETTINGS}
        sparse = {k: 0 for k in SETTINGS}
        for draw in range(a.draws):
            case = build_case(name, a.data, draw)
            rng = np.random.default_rng(draw)
            src_xyz = case.source.xyz[rng.random(len(case.source)) < keep]
            tgt_xyz = case.target.xyz[rng.random(len(case.target)) < keep]
            start = _nudge(rng) @ case.truth
            for key, cfg in SETTINGS.items():
                src = prepare_cloud(PointCloud(src_xyz), "tls", 3, cfg, draw)
                tgt = prepare_cloud(PointCloud(tgt_xyz), "tls", 3, cfg, draw + 1)
                sparse[key] += src.normal_radius > cfg.normal_radius
                T0 = to_local_transform(start, src.frame, tgt.frame)
                T = to_global_transform(final_icp(src, tgt, T0, cfg).T, src.frame, tgt.frame)
                E = np.linalg.inv(case.truth) @ T
                rot = np.degrees(np.linalg.norm(Rotation.from_matrix(E[:3, :3]).as_rotvec()))
                errs[key].append((rot, 100 * np.linalg.norm(T[:3, 3] - case.truth[:3, 3])))
        for key, rows in errs.items():
            A = np.asarray(rows)
            figs = [f"{c.mean():.4f} / {np.sqrt((c**2).mean()):.4f} / {c.max():.4f}" for c in A.T]
            print(
                f"| {name} x {keep:g} | {key} | {sparse[key]} / {a.draws} | {figs[0]} | {figs[1]} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
