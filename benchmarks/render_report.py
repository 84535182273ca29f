"""Render a report.html in headless Chromium to a PNG: what a user sees when opening the page.

    python benchmarks/render_report.py demo-output/georeferenced/report.html --out docs/report_page.png
    python benchmarks/render_report.py --slices SIM_DIR --out docs/report_slice_doubled.png
    python benchmarks/render_report.py --als-fit SIM_DIR --raise 0.10

The second form takes a `plotmosaic simulate` folder, draws the breast-height slice at the true
poses and with one scan moved by 5 cm / 0.2 deg, and prints the ring spreads of both. The third
prints the georeferenced page's fit to the ALS at the true poses and with each plot raised.

Needs Debian's `chromium` (apt-get install -y chromium). The page is opened from its file (no
server), which also checks that it is self-contained. The screenshot is shrunk with Pillow to
--width pixels and saved as an 8-bit palette PNG, so it stays a few hundred kB for docs/.
Prints the page size, the render time and the PNG size.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def find_chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        path = shutil.which(name)
        if path:
            return path
    sys.exit("error: no chromium found (Debian: apt-get install -y chromium)")


def render(page: Path, out: Path, window: tuple[int, int], width: int, colours: int) -> dict:
    from PIL import Image

    chromium = find_chromium()
    with tempfile.TemporaryDirectory() as tmp:
        shot = Path(tmp) / "shot.png"
        cmd = [
            chromium,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            f"--user-data-dir={tmp}/profile",
            f"--window-size={window[0]},{window[1]}",
            f"--screenshot={shot}",
            page.resolve().as_uri(),
        ]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        seconds = time.perf_counter() - t0
        if not shot.is_file():
            sys.exit(
                f"error: chromium wrote no screenshot (exit {proc.returncode}): {proc.stderr.strip()[-500:]}"
            )
        img = Image.open(shot).convert("RGB")
        full = img.size
        if img.width > width:
            img = img.resize((width, round(img.height * width / img.width)), Image.LANCZOS)
        out.parent.mkdir(parents=True, exist_ok=True)
        img.quantize(colors=colours, method=Image.Quantize.FASTOCTREE).save(
            out, optimize=True
        )  # octree keeps the scan colours
    return {
        "page_bytes": page.stat().st_size,
        "render_s": seconds,
        "screenshot": full,
        "png": img.size,
        "png_bytes": out.stat().st_size,
    }


def slices(sim: Path, out: Path, moved: str, width: int) -> None:
    """Breast-height slices at the true poses and with `moved` off by 5 cm / 0.2 deg; prints the ring spreads."""
    from PIL import Image

    from plotmosaic.bench.protocol import params_to_matrix
    from plotmosaic.config.report import ReportConfig
    from plotmosaic.io.las import read_cloud
    from plotmosaic.poses import load_poses
    from plotmosaic.report.build import collect
    from plotmosaic.report.figures import origin_of
    from plotmosaic.report.slice import ring_spread
    from plotmosaic.report.views import plot_breast_slice, scan_colours

    truth = load_poses(sim / "ground_truth.json")
    poses = {k: v.transform for k, v in truth.scans.items()}
    paths = {k: sim / v.plot / f"{k}.laz" for k, v in truth.scans.items()}
    raw = {p: read_cloud(p, attributes=False).xyz for p in paths.values()}
    ids = sorted(poses)
    off = dict(poses)
    off[moved] = poses[moved] @ params_to_matrix([0, 0, 0.2, 0.03, 0.04, 0])
    cfg = ReportConfig()
    pngs = []
    for name, P in (("true poses", poses), (f"{moved} moved by 5 cm / 0.2 deg", off)):
        t0 = time.perf_counter()
        v = collect("P1", ids, paths, P, raw.__getitem__, cfg, 0)
        seconds = time.perf_counter() - t0
        print(
            f"{name}: {len(v.stems)} stems, median ring spread {ring_spread(v.stems) * 100:.2f} cm, "
            f"of the stems {moved} sees {ring_spread(v.stems, moved) * 100:.2f} cm ({seconds:.1f} s)"
        )
        png = out.with_name(out.stem + f"_{len(pngs)}.png")
        plot_breast_slice(
            png,
            v.slices,
            v.stems,
            f"breast-height slice, {name}",
            origin_of(v.thinned),
            4,
            scan_colours(ids),
        )
        pngs.append(png)
    ims = [Image.open(p).convert("RGB") for p in pngs]
    w = min(width, min(i.width for i in ims))
    ims = [i.resize((w, round(i.height * w / i.width)), Image.LANCZOS) for i in ims]
    both = Image.new("RGB", (w, sum(i.height for i in ims)), "white")
    y = 0
    for i in ims:
        both.paste(i, (0, y))
        y += i.height
    both.quantize(colors=256, method=Image.Quantize.FASTOCTREE).save(out, optimize=True)
    for p in pngs:
        p.unlink()
    print(f"wrote {out}: {both.width}x{both.height}, {out.stat().st_size / 1e3:.0f} kB")


def als_fit(sim: Path, raise_m: float) -> None:
    """The fit to the ALS at the true poses and with the plot raised by `raise_m`: prints the
    ground and canopy-top medians and NMADs the georeferenced page shows."""
    from plotmosaic.config.report import ReportConfig
    from plotmosaic.io.las import read_cloud
    from plotmosaic.poses import load_poses
    from plotmosaic.report.collect import collect, with_als_fit

    truth = load_poses(sim / "ground_truth.json")
    paths = {k: sim / v.plot / f"{k}.laz" for k, v in truth.scans.items()}
    raw = {p: read_cloud(p, attributes=False).xyz for p in paths.values()}
    als = read_cloud(sim / "als" / "als.laz", attributes=False).xyz
    cfg = ReportConfig()
    for plot in sorted({v.plot for v in truth.scans.values()}):
        ids = sorted(k for k, v in truth.scans.items() if v.plot == plot)
        for dz in (0.0, raise_m):
            poses = {k: truth.transform(k).copy() for k in ids}
            for T in poses.values():
                T[2, 3] += dz
            t0 = time.perf_counter()
            v = with_als_fit(collect(plot, ids, paths, poses, raw.__getitem__, cfg, 0), als, cfg)
            g, c = v.als.ground, v.als.canopy
            print(
                f"plot {plot} raised {dz * 100:+.0f} cm: ground {g.median * 100:+.1f} cm, NMAD "
                f"{g.nmad * 100:.1f} cm ({g.count} cells); canopy top {c.median:+.2f} m, NMAD "
                f"{c.nmad:.2f} m ({c.count} cells); {time.perf_counter() - t0:.1f} s"
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("page", type=Path, nargs="?", help="a report.html")
    ap.add_argument(
        "--slices",
        type=Path,
        help="a `plotmosaic simulate` folder: single vs doubled breast-height slices",
    )
    ap.add_argument(
        "--moved", default="P1-S2", help="with --slices: the scan moved by 5 cm / 0.2 deg"
    )
    ap.add_argument(
        "--als-fit",
        type=Path,
        help="a `plotmosaic simulate` folder: the fit to the ALS at the truth and raised",
    )
    ap.add_argument("--raise", dest="raise_m", type=float, default=0.10, help="with --als-fit (m)")
    ap.add_argument("--out", type=Path, default=Path("docs/report_page.png"))
    ap.add_argument(
        "--window",
        type=int,
        nargs=2,
        default=(1300, 4200),
        metavar=("W", "H"),
        help="browser window in CSS pixels; the height is how much of the page is captured",
    )
    ap.add_argument("--width", type=int, default=1000, help="width of the saved PNG (pixels)")
    ap.add_argument("--colours", type=int, default=256, help="palette size of the saved PNG")
    args = ap.parse_args()
    if args.slices is not None:
        slices(args.slices, args.out, args.moved, args.width)
        return
    if args.als_fit is not None:
        als_fit(args.als_fit, args.raise_m)
        return
    if args.page is None or not args.page.is_file():
        sys.exit(f"error: {args.page}: no such file")
    r = render(args.page, args.out, tuple(args.window), args.width, args.colours)
    print(
        f"page {args.page}: {r['page_bytes'] / 1e6:.2f} MB; chromium render + screenshot {r['render_s']:.1f} s "
        f"({r['screenshot'][0]}x{r['screenshot'][1]}); wrote {args.out}: {r['png'][0]}x{r['png'][1]}, {r['png_bytes'] / 1e3:.0f} kB"
    )


if __name__ == "__main__":
    main()
