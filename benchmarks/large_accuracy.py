"""Each scan's pose from register-plot against the simulator's truth, in the reference scan's frame.

    python benchmarks/large_accuracy.py OUT/poses.json SIM/ground_truth.json [--tol-cm 2 --tol-deg 0.1]

poses.json (frame "plot") maps each scan's file coordinates into the reference scan's; the truth maps
each scan into UTM, so scan i's true pose in the reference frame is inv(G_ref) @ G_i. Printed per
scan: distance from the reference scanner (m), error of the scanner position (cm, and along x / y / z
of the reference frame) and of the rotation (deg); then the worst, and how many are within bounds.

The reference frame carries the reference scan's own error to every scan (a 0.01 deg tilt is 1.7 cm at
100 m), so a gauge-free figure is printed beside it: the same errors after the one rigid motion that
best fits all the estimated poses onto the truth, as trajectory benchmarks align before an absolute
error. The first is what a user of the plot frame gets; both are reported, neither replaces the other.

Given tie-to-als poses (frame "crs"), each scan's pose is compared with the truth as it is, in UTM:
what a user of the georeferenced result gets, the ALS registration's own error included. Distances are
then from the plot's centre (the mean true scanner position) and there is no reference scan.
"""

from __future__ import annotations

import argparse
import json
import re

import numpy as np


def _natural(name: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def _load(poses: dict, truth: dict) -> tuple[str | None, dict, dict]:
    """(reference id, estimated poses, true poses in the reference's true frame), by scan id; in CRS
    mode (no reference) both sets moved by the same translation to the plot's centre."""
    est = {k: np.asarray(v["transform"], dtype=float) for k, v in poses["scans"].items()}
    true = {k: np.asarray(v["transform"], dtype=float) for k, v in truth["scans"].items()}
    if poses.get("frame") == "crs":
        centre = np.eye(4)
        centre[:3, 3] = -np.mean([true[k][:3, 3] for k in est], axis=0)
        return None, {k: centre @ T for k, T in est.items()}, {k: centre @ true[k] for k in est}
    ref = next(k for k, T in est.items() if np.allclose(T, np.eye(4)))
    inv_ref = np.linalg.inv(true[ref])
    return ref, est, {k: inv_ref @ true[k] for k in est}


def _rows(est: dict, rel: dict) -> list[dict]:
    rows = []
    for sid in sorted(est, key=_natural):
        d = est[sid][:3, 3] - rel[sid][:3, 3]  # the scanner (scan origin) in the reference frame
        dR = est[sid][:3, :3] @ rel[sid][:3, :3].T
        deg = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0))))
        rows.append(
            {
                "scan": sid,
                "distance_m": float(np.linalg.norm(rel[sid][:3, 3])),
                "error_cm": float(100 * np.linalg.norm(d)),
                "d_cm": (100 * d).tolist(),
                "error_deg": deg,
            }
        )
    return rows


def best_fit(est: dict, rel: dict) -> np.ndarray:
    """The rigid motion M that best maps the estimated poses onto the true ones: one Procrustes over
    the scanner positions (m) and the rotations' chordal offsets (one unit a scan), no scale."""
    ids = sorted(est)
    P = np.array([est[k][:3, 3] for k in ids])
    Q = np.array([rel[k][:3, 3] for k in ids])
    H = (P - P.mean(axis=0)).T @ (Q - Q.mean(axis=0))
    H = H + sum(est[k][:3, :3] @ rel[k][:3, :3].T for k in ids)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    M = np.eye(4)
    M[:3, :3] = Vt.T @ D @ U.T
    M[:3, 3] = Q.mean(axis=0) - M[:3, :3] @ P.mean(axis=0)
    return M


def scan_errors(poses: dict, truth: dict) -> tuple[str | None, list[dict], list[dict]]:
    """(reference id or None in CRS mode, rows in the poses' frame, rows after the best-fit motion); a
    row per placed scan: id, distance_m, error_cm, d_cm (x / y / z), error_deg."""
    ref, est, rel = _load(poses, truth)
    M = best_fit(est, rel)
    return ref, _rows(est, rel), _rows({k: M @ T for k, T in est.items()}, rel)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("poses")
    ap.add_argument("truth")
    ap.add_argument("--tol-cm", type=float, default=2.0)
    ap.add_argument("--tol-deg", type=float, default=0.1)
    a = ap.parse_args()
    poses = json.load(open(a.poses))
    truth = json.load(open(a.truth))
    ref, rows, fitted = scan_errors(poses, truth)
    missing = sorted(set(truth["scans"]) - set(poses["scans"]), key=_natural)
    where = f"reference {ref}" if ref else "CRS (tie-to-als poses against the true UTM poses)"
    print(
        f"{where}; {len(rows)} of {len(truth['scans'])} scans placed; unplaced: {missing or 'none'}"
    )
    print(
        f"| scan | from {'ref' if ref else 'centre'} (m) | error (cm) | dx / dy / dz (cm) | rotation (deg) | within |"
        " best fit: error (cm) / rotation (deg) |"
    )
    print("|---|---|---|---|---|---|---|")
    for r, f in zip(rows, fitted, strict=True):
        ok = r["error_cm"] <= a.tol_cm and r["error_deg"] <= a.tol_deg
        dx, dy, dz = r["d_cm"]
        print(
            f"| {r['scan']} | {r['distance_m']:.1f} | {r['error_cm']:.2f} | {dx:+.2f} / {dy:+.2f} / {dz:+.2f}"
            f" | {r['error_deg']:.4f} | {'yes' if ok else 'NO'}"
            f" | {f['error_cm']:.2f} / {f['error_deg']:.4f} |"
        )
    for label, rs in (("reference frame" if ref else "UTM", rows), ("best fit", fitted)):
        within = sum(r["error_cm"] <= a.tol_cm and r["error_deg"] <= a.tol_deg for r in rs)
        worst_t = max(rs, key=lambda r: r["error_cm"])
        worst_r = max(rs, key=lambda r: r["error_deg"])
        print(
            f"{label}: worst {worst_t['error_cm']:.2f} cm ({worst_t['scan']}),"
            f" {worst_r['error_deg']:.4f} deg ({worst_r['scan']}); {within} of"
            f" {len(truth['scans'])} scans within {a.tol_cm:g} cm / {a.tol_deg:g} deg"
        )


if __name__ == "__main__":
    main()
