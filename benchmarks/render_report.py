"""Render a report.html in headless Chromium to a PNG: what a user sees when opening the page.

    python benchmarks/render_report.py demo-output/georeferenced/report.html --out docs/report_page.png

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
        cmd = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", f"--user-data-dir={tmp}/profile",
               f"--window-size={window[0]},{window[1]}", f"--screenshot={shot}", page.resolve().as_uri()]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        seconds = time.perf_counter() - t0
        if not shot.is_file():
            sys.exit(f"error: chromium wrote no screenshot (exit {proc.returncode}): {proc.stderr.strip()[-500:]}")
        img = Image.open(shot).convert("RGB")
        full = img.size
        if img.width > width:
            img = img.resize((width, round(img.height * width / img.width)), Image.LANCZOS)
        out.parent.mkdir(parents=True, exist_ok=True)
        img.quantize(colors=colours, method=Image.Quantize.MEDIANCUT).save(out, optimize=True)
    return {"page_bytes": page.stat().st_size, "render_s": seconds, "screenshot": full, "png": img.size,
            "png_bytes": out.stat().st_size}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("page", type=Path, help="a report.html")
    ap.add_argument("--out", type=Path, default=Path("docs/report_page.png"))
    ap.add_argument("--window", type=int, nargs=2, default=(1300, 4200), metavar=("W", "H"),
                    help="browser window in CSS pixels; the height is how much of the page is captured")
    ap.add_argument("--width", type=int, default=1000, help="width of the saved PNG (pixels)")
    ap.add_argument("--colours", type=int, default=256, help="palette size of the saved PNG")
    args = ap.parse_args()
    if not args.page.is_file():
        sys.exit(f"error: {args.page}: no such file")
    r = render(args.page, args.out, tuple(args.window), args.width, args.colours)
    print(f"page {args.page}: {r['page_bytes'] / 1e6:.2f} MB; chromium render + screenshot {r['render_s']:.1f} s "
          f"({r['screenshot'][0]}x{r['screenshot'][1]}); wrote {args.out}: {r['png'][0]}x{r['png'][1]}, {r['png_bytes'] / 1e3:.0f} kB")


if __name__ == "__main__":
    main()
