"""PNG pictures of a simulation: plot top/side views by label, one scan's occlusion, ALS profile."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

from plotmosaic.io.frame import apply_transform  # noqa: E402
from plotmosaic.io.las import PointCloud  # noqa: E402
from plotmosaic.io.pictures import savefig  # noqa: E402
from plotmosaic.poses import ScanPose  # noqa: E402
from plotmosaic.simulate.mesh import LABEL_NAMES  # noqa: E402
from plotmosaic.simulate.scene import World  # noqa: E402

COLOURS = np.array([[0.62, 0.50, 0.36], [0.45, 0.20, 0.10], [0.15, 0.55, 0.20], [0.85, 0.75, 0.20]])


def _legend(ax) -> None:
    handles = [
        Line2D([], [], marker="o", ls="", color=COLOURS[k], label=n) for k, n in LABEL_NAMES.items()
    ]
    ax.legend(handles=handles, loc="upper right", fontsize=7, markerscale=1.2, framealpha=0.85)


def _scatter(ax, x, y, labels, size=0.05, order=None) -> None:
    idx = np.argsort(order, kind="stable") if order is not None else np.arange(len(x))
    ax.scatter(
        x[idx], y[idx], c=COLOURS[np.minimum(labels[idx], 3)], s=size, linewidths=0, rasterized=True
    )


def _save(fig, path: Path) -> Path:
    return savefig(fig, path, dpi=150)


def _world_points(
    world: World,
    samples: dict[str, PointCloud],
    poses: dict[str, ScanPose],
    plot_id: str,
    cap: int = 1_500_000,
):
    """Sampled points of one plot's scans in the local frame, with labels."""
    xyz, lab = [], []
    for sid, cloud in samples.items():
        if poses[sid].plot != plot_id:
            continue
        xyz.append(apply_transform(poses[sid].transform, cloud.xyz) - world.origin)
        lab.append(cloud.attrs["label"])
    xyz, lab = np.concatenate(xyz), np.concatenate(lab)
    if len(xyz) > cap:
        keep = np.random.default_rng(0).choice(len(xyz), cap, replace=False)
        xyz, lab = xyz[keep], lab[keep]
    return xyz, lab


def plot_top_side(
    world: World,
    xyz: np.ndarray,
    lab: np.ndarray,
    sites_xy: np.ndarray,
    title: str,
    out_top: Path,
    out_side: Path,
) -> list[Path]:
    hag = xyz[:, 2] - world.terrain.height(xyz[:, 0], xyz[:, 1])
    fig, axes = plt.subplots(1, 2, figsize=(13, 6.2))
    _scatter(axes[0], xyz[:, 0], xyz[:, 1], lab, order=xyz[:, 2])
    axes[0].set_title(f"{title}: all points, seen from above")
    low = hag < 3.0
    _scatter(axes[1], xyz[low, 0], xyz[low, 1], lab[low], order=lab[low])
    axes[1].set_title("points below 3 m above ground (stems, understory, occlusion)")
    for ax in axes:
        ax.plot(sites_xy[:, 0], sites_xy[:, 1], "k^", ms=6, mfc="white")
        ax.set_aspect("equal")
        ax.set(xlabel="x (m, local)", ylabel="y (m, local)")
        ax.set(xlim=(-40, 40), ylim=(-40, 40))
    _legend(axes[1])
    paths = [_save(fig, out_top)]
    fig, ax = plt.subplots(figsize=(13, 5))
    yc = float(np.median(sites_xy[:, 1]))
    slab = np.abs(xyz[:, 1] - yc) < 2.0
    _scatter(ax, xyz[slab, 0], xyz[slab, 2], lab[slab], size=0.15, order=-np.abs(xyz[slab, 1] - yc))
    ax.set_title(f"{title}: side view of a 4 m slab through the scan positions (y = {yc:.0f} m)")
    ax.set_aspect("equal")
    ax.set_xlim(-40, 40)
    ax.set(xlabel="x (m, local)", ylabel="z (m, local)")
    _legend(ax)
    paths.append(_save(fig, out_side))
    return paths


def plot_scan(world: World, cloud: PointCloud, pose: ScanPose, title: str, out: Path) -> Path:
    """One scan from above, near the ground: trunks cast long shadows where the scanner saw nothing."""
    xyz = apply_transform(pose.transform, cloud.xyz) - world.origin
    lab = cloud.attrs["label"]
    hag = xyz[:, 2] - world.terrain.height(xyz[:, 0], xyz[:, 1])
    low = hag < 2.5
    c = pose.transform[:3, 3] - world.origin
    fig, ax = plt.subplots(figsize=(8, 8))
    _scatter(ax, xyz[low, 0], xyz[low, 1], lab[low], size=0.12, order=lab[low])
    ax.plot([c[0]], [c[1]], "r*", ms=14)
    ax.set(xlim=(c[0] - 30, c[0] + 30), ylim=(c[1] - 30, c[1] + 30))
    ax.set_aspect("equal")
    ax.set_title(f"{title}: one TLS scan, points < 2.5 m above ground (red star: scanner)")
    ax.set(xlabel="x (m, local)", ylabel="y (m, local)")
    _legend(ax)
    return _save(fig, out)


def plot_als(world: World, als: PointCloud, out: Path) -> Path:
    xyz = als.xyz - world.origin
    lab = als.attrs["label"]
    yc = float(np.median(xyz[:, 1]))
    slab = np.abs(xyz[:, 1] - yc) < 3.0
    fig, axes = plt.subplots(2, 1, figsize=(13, 8), constrained_layout=True)
    _scatter(axes[0], xyz[slab, 0], xyz[slab, 2], lab[slab], size=1.0)
    axes[0].set_title(
        f"ALS: side view of a 6 m slab, coloured by label ({len(als)} points in the sample)"
    )
    nr = als.attrs["return_number"][slab]
    sc = axes[1].scatter(
        xyz[slab, 0],
        xyz[slab, 2],
        c=nr,
        s=1.0,
        cmap="viridis",
        vmin=1,
        vmax=max(3, int(nr.max())),
        rasterized=True,
    )
    axes[1].set_title(
        "the same slab coloured by return number (later returns reach the ground through gaps)"
    )
    fig.colorbar(sc, ax=list(axes), label="return number (lower panel)", shrink=0.6)
    for ax in axes:
        ax.set_aspect("equal")
        ax.set(xlabel="x (m, local)", ylabel="z (m)")
    _legend(axes[0])
    return _save(fig, out)


def make_figures(
    outdir: Path,
    world: World,
    samples: dict[str, PointCloud],
    poses: dict[str, ScanPose],
    als: PointCloud,
) -> list[Path]:
    outdir = Path(outdir)
    paths = []
    pid = world.plot_ids[0]
    site_xy = np.array([s.xy for s in world.sites if s.plot_id == pid])
    xyz, lab = _world_points(world, samples, poses, pid)
    paths += plot_top_side(
        world,
        xyz,
        lab,
        site_xy,
        f"{world.config.name} plot {pid}",
        outdir / "sim_plot_top.png",
        outdir / "sim_plot_side.png",
    )
    first = next(s.scan_id for s in world.sites if s.plot_id == pid)
    paths.append(
        plot_scan(world, samples[first], poses[first], first, outdir / "sim_scan_occlusion.png")
    )
    paths.append(plot_als(world, als, outdir / "sim_als_side.png"))
    return paths
