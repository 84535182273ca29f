"""The fine stage of a register-plot run's TLS pairs, run again from their stored poses, against the truth.

    python benchmarks/large_pairs.py OUT SIM [--blind]

OUT is a register-plot folder (its pairs/*.json), SIM the simulated plot (manifest.toml and
ground_truth.json). Each scan is read and prepared once with the default settings (`--blind`: no
scanner positions, so no side test in the final ICP); each verified TLS -> TLS pair's final ICP is
run from its stored pose. Printed: the mean / std / median |.| / max |.| over the pairs of the
source scanner's error along the baseline, across it and in height (cm), its whole error (cm) and
the rotation error (deg). A pair's fine stage alone, without the graph: what one setting of the
final ICP changes on the same pairs.
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from plotmosaic.align.fine import final_icp
from plotmosaic.align.prepare import prepare_cloud
from plotmosaic.config.align import AlignConfig
from plotmosaic.io.frame import to_global_transform, to_local_transform
from plotmosaic.io.las import read_cloud
from plotmosaic.manifest import load_manifest

COLUMNS = ("along (cm)", "across (cm)", "height (cm)", "error (cm)", "rotation (deg)")


def pair_errors(T: np.ndarray, Gs: np.ndarray, Gt: np.ndarray) -> list[float]:
    """The source scanner's error along / across the baseline and in height (cm, world axes), its
    norm (cm) and the rotation error (deg) of T (source file -> target file) against the truth."""
    true = np.linalg.inv(Gt) @ Gs
    d = Gt[:3, :3] @ (T[:3, 3] - true[:3, 3])
    b = Gt[:3, 3] - Gs[:3, 3]
    b[2] = 0.0
    u = b / np.linalg.norm(b)
    v = np.array([-u[1], u[0], 0.0])
    deg = np.degrees(np.linalg.norm(Rotation.from_matrix(T[:3, :3] @ true[:3, :3].T).as_rotvec()))
    return [100 * d @ u, 100 * d @ v, 100 * d[2], 100 * np.linalg.norm(d), float(deg)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("sim")
    ap.add_argument("--blind", action="store_true", help="no scanner positions (no side test)")
    a = ap.parse_args()
    sim = Path(a.sim)
    truth = json.loads((sim / "ground_truth.json").read_text())["scans"]
    truth = {k: np.asarray(v["transform"], dtype=float) for k, v in truth.items()}
    manifest = load_manifest(sim / "manifest.toml")
    scans = {s.id: s for s in manifest.scans}
    config, prepared = AlignConfig(), {}

    def get(sid: str):
        if sid not in prepared:
            s = scans[sid]
            cloud = read_cloud(manifest.resolve(s.path), attributes=False)
            c = prepare_cloud(cloud, s.kind.value, s.k, config, 0, sid)
            prepared[sid] = dataclasses.replace(c, viewpoint=None) if a.blind else c
        return prepared[sid]

    rows, with_view = [], 0
    for f in sorted(glob.glob(str(Path(a.out) / "pairs" / "*.json"))):
        d = json.loads(Path(f).read_text())
        s, t = d.get("source"), d.get("target")
        if (
            d.get("status") != "ok"
            or d.get("source_kind") != "tls"
            or d.get("target_kind") != "tls"
        ):
            continue
        src, tgt = get(s), get(t)
        with_view += src.viewpoint is not None and tgt.viewpoint is not None
        T0 = to_local_transform(np.asarray(d["transform"], dtype=float), src.frame, tgt.frame)
        T = to_global_transform(final_icp(src, tgt, T0, config).T, src.frame, tgt.frame)
        rows.append(pair_errors(T, truth[s], truth[t]))
    A = np.asarray(rows)
    print(f"{len(A)} TLS pairs ({with_view} with both scanners known); {Path(a.out)}")
    print("| figure | " + " | ".join(COLUMNS) + " |")
    print("|---|" + "---|" * len(COLUMNS))
    for name, v in (
        ("mean", A.mean(axis=0)),
        ("std", A.std(axis=0)),
        ("median |.|", np.median(np.abs(A), axis=0)),
        ("max |.|", np.abs(A).max(axis=0)),
    ):
        print(f"| {name} | " + " | ".join(f"{x:.4f}" for x in v) + " |")


if __name__ == "__main__":
    main()
