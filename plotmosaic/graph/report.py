"""report.md and pictures for register-plot / tie-to-als: what was kept, dropped, and where scans sit."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import networkx as nx  # noqa: E402
import numpy as np  # noqa: E402

from plotmosaic.io.atomic import atomic_output  # noqa: E402
from plotmosaic.io.frame import apply_transform  # noqa: E402


def _savefig(fig, path: Path) -> Path:
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _fmt(value, scale=1.0, digits=1) -> str:
    return "-" if value is None else f"{value * scale:.{digits}f}"


def yaw_deg(T: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(T[1, 0], T[0, 0])))


def plot_scans(path: Path, clouds: dict[str, np.ndarray], title: str, origin: np.ndarray | None = None) -> Path:
    """Top and side view of every placed scan (points already in the common frame), one colour per scan."""
    origin = np.zeros(3) if origin is None else origin
    fig, (top, side) = plt.subplots(1, 2, figsize=(13, 5.5), gridspec_kw={"width_ratios": [1, 1.3]})
    cmap = plt.get_cmap("tab10" if len(clouds) <= 10 else "tab20")
    for n, (name, xyz) in enumerate(clouds.items()):
        xyz = xyz - origin
        colour = "lightgrey" if name == "ALS" else cmap(n % cmap.N)  # the reference stays in the background
        top.scatter(xyz[:, 0], xyz[:, 1], s=0.3, color=colour, label=name, rasterized=True)
        side.scatter(xyz[:, 0], xyz[:, 2], s=0.3, color=colour, rasterized=True)
    top.set_aspect("equal")
    top.set_title("top view (x, y)")
    side.set_title("side view (x, z)")
    for ax in (top, side):
        ax.set_xlabel("x (m)" if not origin.any() else f"x - {origin[0]:.0f} (m)")
    top.set_ylabel("y (m)" if not origin.any() else f"y - {origin[1]:.0f} (m)")
    side.set_ylabel("z (m)" if not origin.any() else f"z - {origin[2]:.0f} (m)")
    top.legend(markerscale=12, fontsize=8, loc="best")
    fig.suptitle(title)
    return _savefig(fig, path)


def plot_graph(path: Path, G: nx.Graph, poses: dict[str, np.ndarray], title: str, origin: np.ndarray | None = None) -> Path:
    """Scans at their placed positions (top view); edges coloured by final translation residual, dropped dashed."""
    origin = np.zeros(3) if origin is None else origin
    fig, ax = plt.subplots(figsize=(7, 6.5))
    pos = {n: (poses[n][:3, 3] - origin)[:2] for n in G.nodes if n in poses}
    if pos:  # unplaced scans in a row below the placed ones
        xy = np.array(list(pos.values()))
        x0, y0 = xy[:, 0].min(), xy[:, 1].min() - 0.15 * (np.ptp(xy[:, 1]) + 5)
    else:
        x0, y0 = 0.0, 0.0
    step = 0
    for n in G.nodes:
        if n not in pos:
            pos[n] = np.array([x0 + step, y0])
            step += 4.0
    cmap = plt.get_cmap("viridis")
    res = [e["residual_after"]["translation"] * 100 for _, _, e in G.edges(data=True) if not e.get("dropped") and e.get("residual_after")]
    vmax = max(res + [1.0])
    for u, v, e in G.edges(data=True):
        (x1, y1), (x2, y2) = pos[u], pos[v]
        r = e.get("residual_after")
        if e.get("dropped"):
            ax.plot([x1, x2], [y1, y2], "--", color="red", lw=1.5)
            label = f"dropped ({e.get('drop_reason')})"
        else:
            cm = (r["translation"] * 100) if r else 0.0
            ax.plot([x1, x2], [y1, y2], "-", color=cmap(cm / vmax), lw=2.5)
            label = f"{cm:.1f} cm" if r else ""
        ax.text((x1 + x2) / 2, (y1 + y2) / 2, label, fontsize=7, ha="center", va="center",
                bbox={"fc": "white", "ec": "none", "alpha": 0.7, "pad": 0.5})
    for n, (x, y) in pos.items():
        placed = n in poses
        ax.scatter([x], [y], s=140, color="tab:blue" if placed else "lightgrey", edgecolor="black", zorder=3)
        ax.text(x, y, f" {n}" + ("" if placed else " (unplaced)"), fontsize=9, va="bottom", zorder=4)
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, vmax))
    fig.colorbar(sm, ax=ax, label="edge residual after optimisation (cm)", shrink=0.8)
    ax.set_aspect("equal")
    ax.set_title(title)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    return _savefig(fig, path)


def edge_table(G: nx.Graph) -> list[str]:
    rows = ["| source | target | fitness | RMSE (cm) | overlap | before (cm / deg) | after (cm / deg) | chi2 after | status |",
            "|---|---|---|---|---|---|---|---|---|"]
    for u, v, e in sorted(G.edges(data=True), key=lambda t: (t[2]["source"], t[2]["target"])):
        b, a = e.get("residual_before"), e.get("residual_after")
        status = f"**dropped** ({e.get('drop_reason')})" if e.get("dropped") else "kept"
        rows.append(
            f"| {e['source']} | {e['target']} | {_fmt(e.get('fitness'), 1, 3)} | {_fmt(e.get('inlier_rmse'), 100, 2)} "
            f"| {_fmt(e.get('overlap'), 1, 3)} | {_fmt(b and b['translation'], 100, 2)} / {_fmt(b and b['rotation_deg'], 1, 3)} "
            f"| {_fmt(a and a['translation'], 100, 2)} / {_fmt(a and a['rotation_deg'], 1, 3)} | {_fmt(a and a['chi2'], 1, 1)} | {status} |"
        )
    return rows


def pose_table(names: list[str], poses: dict[str, np.ndarray], sigmas: dict[str, np.ndarray]) -> list[str]:
    rows = ["| scan | x (m) | y (m) | z (m) | yaw (deg) | tilt (deg) | sigma xyz (mm) | sigma rot (deg) |",
            "|---|---|---|---|---|---|---|---|"]
    for n in names:
        if n not in poses:
            rows.append(f"| {n} | unplaced | | | | | | |")
            continue
        T, s = poses[n], sigmas.get(n)
        R = T[:3, :3]
        tilt = float(np.degrees(np.arccos(np.clip(R[2, 2], -1, 1))))
        sig_t = "-" if s is None else " / ".join(f"{v * 1000:.1f}" for v in s[3:])
        sig_r = "-" if s is None else " / ".join(f"{np.degrees(v):.4f}" for v in s[:3])
        rows.append(f"| {n} | {T[0, 3]:.3f} | {T[1, 3]:.3f} | {T[2, 3]:.3f} | {yaw_deg(T):.2f} | {tilt:.2f} | {sig_t} | {sig_r} |")
    return rows


def sample_clouds(paths: dict[str, Path], poses: dict[str, np.ndarray], n_points: int, seed: int,
                  reader: Callable[[Path], np.ndarray]) -> dict[str, np.ndarray]:
    """A seeded random subset of each placed scan, moved into the common frame."""
    rng = np.random.default_rng(seed)
    out = {}
    for name, path in paths.items():
        if name not in poses:
            continue
        xyz = reader(path)
        if len(xyz) > n_points:
            xyz = xyz[rng.choice(len(xyz), n_points, replace=False)]
        out[name] = apply_transform(poses[name], xyz)
    return out


def residual_summary(G: nx.Graph) -> dict:
    kept = [e["residual_after"] for _, _, e in G.edges(data=True) if not e.get("dropped") and e.get("residual_after")]
    if not kept:
        return {"edges": 0}
    t = np.array([r["translation"] for r in kept])
    r = np.array([r["rotation_deg"] for r in kept])
    return {"edges": len(kept), "translation_rms": float(np.sqrt(np.mean(t**2))), "translation_max": float(t.max()),
            "rotation_rms_deg": float(np.sqrt(np.mean(r**2))), "rotation_max_deg": float(r.max())}

