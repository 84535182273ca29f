"""Each scan's pose from register-plot against the simulator's truth, in the reference scan's frame.

    python benchmarks/large_accuracy.py OUT/poses.json SIM/ground_truth.json [--tol-cm 2 --tol-deg 0.1]

poses.json (frame "plot") maps each scan's file coordinates into the reference scan's; the truth maps
each scan into UTM, so scan i's true pose in the reference frame is inv(G_ref) @ G_i. Printed per
scan: distance from the reference scanner (m), error of the scanner position (cm, and along x / y / z
of the reference frame) and of the rotation (deg); then the worst, and how many are within bounds.
"""

from __future__ import annotations

import argparse
import json
import re

import numpy as np


def _natural(name: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def scan_errors(poses: dict, truth: dict) -> tuple[str, list[dict]]:
    """(reference id, one row per placed scan: id, distance_m, error_cm, dx/dy/dz_cm, error_deg)."""
    est = {k: np.asarray(v["transform"], dtype=float) for k, v in poses["scans"].items()}
    true = {k: np.asarray(v["transform"], dtype=float) for k, v in truth["scans"].items()}
    ref = next(k for k, T in est.items() if np.allclose(T, np.eye(4)))
    inv_ref = np.linalg.inv(true[ref])
    rows = []
    for sid in sorted(est, key=_natural):
        T_true = inv_ref @ true[sid]
        d = est[sid][:3, 3] - T_true[:3, 3]  # the scanner (scan origin) in the reference frame
        dR = est[sid][:3, :3] @ T_true[:3, :3].T
        deg = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0))))
        rows.append(
            {
                "scan": sid,
                "distance_m": float(np.linalg.norm(T_true[:3, 3])),
                "error_cm": float(100 * np.linalg.norm(d)),
                "d_cm": (100 * d).tolist(),
                "error_deg": deg,
            }
        )
    return ref, rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("poses")
    ap.add_argument("truth")
    ap.add_argument("--tol-cm", type=float, default=2.0)
    ap.add_argument("--tol-deg", type=float, default=0.1)
    a = ap.parse_args()
    poses = json.load(open(a.poses))
    truth = json.load(open(a.truth))
    ref, rows = scan_errors(poses, truth)
    missing = sorted(set(truth["scans"]) - set(poses["scans"]), key=_natural)
    print(
        f"reference {ref}; {len(rows)} of {len(truth['scans'])} scans placed; unplaced: {missing or 'none'}"
    )
    print("| scan | from ref (m) | error (cm) | dx / dy / dz (cm) | rotation (deg) | within |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        ok = r["error_cm"] <= a.tol_cm and r["error_deg"] <= a.tol_deg
        dx, dy, dz = r["d_cm"]
        print(
            f"| {r['scan']} | {r['distance_m']:.1f} | {r['error_cm']:.2f} | {dx:+.2f} / {dy:+.2f} / {dz:+.2f}"
            f" | {r['error_deg']:.4f} | {'yes' if ok else 'NO'} |"
        )
    within = sum(r["error_cm"] <= a.tol_cm and r["error_deg"] <= a.tol_deg for r in rows)
    worst_t = max(rows, key=lambda r: r["error_cm"])
    worst_r = max(rows, key=lambda r: r["error_deg"])
    print(
        f"worst {worst_t['error_cm']:.2f} cm ({worst_t['scan']}), {worst_r['error_deg']:.4f} deg"
        f" ({worst_r['scan']}); {within} of {len(truth['scans'])} scans within {a.tol_cm:g} cm /"
        f" {a.tol_deg:g} deg"
    )


if __name__ == "__main__":
    main()
