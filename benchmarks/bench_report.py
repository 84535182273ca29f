"""CPU seconds of the two report pages of a `plotmosaic demo` folder, written as the demo's runs write them.

    python benchmarks/bench_report.py demo-output --repeat 3

Copies DEMO/register and DEMO/georeferenced into a temporary folder (the demo is never written) and
renders each page there, in this process, imports done first, timed on the process clock:

- register: register-plot's page, from the scans' prepared clouds (as the run reads them);
- georeferenced: tie-to-als's page with the plot judged in register-plot's page (the demo's plot
  moves as one piece, so its cloud-to-cloud distances are not measured again), from the same
  prepared clouds;
- georeferenced, distances: the same page measuring them (what `plotmosaic report DIR` does).

Prints per page the whole page and its computing (reading, slice, distances, ALS fit) apart from
its pictures (PNGs, the 3D view, the page), the minimum over --repeat runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
import tempfile
import time
from pathlib import Path

from plotmosaic.io.pictures import pyplot
from plotmosaic.poses import load_poses
from plotmosaic.report import build, runs
from plotmosaic.report.register_page import render_register
from plotmosaic.report.tie_page import render_tie


def _inputs(reg: Path, geo: Path):
    """(register run, its reader, tie run, tie run judged in the register page, settings)."""
    settings = runs._settings(reg)
    reg_poses = load_poses(reg / "poses.json")
    G = runs.load_graph(reg / "graph.json")
    paths, plots, source = runs._scans(reg, G, reg_poses, None)
    reader = runs._reader(reg, reg_poses, paths, settings)
    reg_run = runs._register_run(reg, G, reg_poses, paths, plots, source)
    geo_poses = load_poses(geo / "poses.json")
    G2 = runs.load_graph(geo / "graph.json")
    paths2, plots2, source2 = runs._scans(geo, G2, geo_poses, None)
    tie = runs._tie_run(geo, G2, geo_poses, paths2, plots2, source2, settings.report.als_margin)
    judged = dataclasses.replace(
        tie,
        judged_in={p: ("../register/report.html", "moved as one piece") for p in plots2},
    )
    return reg_run, reader, tie, judged, settings


def _timed(render, run, settings, reader) -> float:
    t0 = time.process_time()
    render(run, settings.report, settings.posegraph.sure_edge_confidence, 0, reader)
    return time.process_time() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("demo", type=Path, help="a `plotmosaic demo` output folder")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    for sub in ("register", "georeferenced"):
        if not (args.demo / sub / "poses.json").is_file():
            sys.exit(f"error: {args.demo / sub}: no poses.json (not a demo output folder)")
    pyplot()  # matplotlib's import is not the page's
    plot_views = build.plot_views
    spent: dict[str, float] = {}

    def timed_views(inp, cfg, seed):  # the computing, apart from the pictures
        t0 = time.process_time()
        out = plot_views(inp, cfg, seed)
        spent["compute"] = spent.get("compute", 0.0) + time.process_time() - t0
        return out

    build.plot_views = timed_views
    with tempfile.TemporaryDirectory() as tmp:
        reg, geo = Path(tmp) / "register", Path(tmp) / "georeferenced"
        shutil.copytree(args.demo / "register", reg)
        shutil.copytree(args.demo / "georeferenced", geo)
        reg_run, reader, tie, judged, settings = _inputs(reg, geo)
        cases = (
            ("register", render_register, reg_run),
            ("georeferenced", render_tie, judged),
            ("georeferenced, distances", render_tie, tie),
        )
        print("| page | CPU s, whole page | computing | pictures and page |")
        print("|---|---|---|---|")
        for name, render, run in cases:
            best = None
            for _ in range(args.repeat):
                spent.clear()
                whole = _timed(render, run, settings, reader)
                if best is None or whole < best[0]:
                    best = (whole, spent.get("compute", 0.0))
            whole, compute = best
            print(f"| {name} | {whole:.2f} | {compute:.2f} | {whole - compute:.2f} |")


if __name__ == "__main__":
    main()
