"""The documents' relative links resolve: the file exists and, for a Markdown file, the #anchor names
one of its headings (GitHub's rule: lower case, punctuation dropped, spaces to hyphens)."""

from __future__ import annotations

import re
from pathlib import Path
from types import SimpleNamespace

import pytest

from plotmosaic.commands.align import LEVEL_NAMES, output_plan
from plotmosaic.commands.bench import BENCH_NAMES
from plotmosaic.commands.register import register_plan, tie_plan
from plotmosaic.commands.report import PAGES, PAIR_FIGURES
from plotmosaic.demo import DEMO_NAMES

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = sorted(
    [ROOT / "README.md", ROOT / "benchmarks" / "README.md"]
    + list((ROOT / "docs").glob("*.md"))
    + list((ROOT / "benchmarks" / "results").glob("*.md"))
)
FENCED = re.compile(r"```.*?```", re.S)
LINK = re.compile(r"\]\(([^)\s]+)\)")
HEADING = re.compile(r"^#+ (.*)$", re.M)


def slug(heading: str) -> str:
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    return {slug(h) for h in HEADING.findall(FENCED.sub("", path.read_text()))}


def links(path: Path) -> list[str]:
    text = FENCED.sub("", path.read_text())
    return [m for m in LINK.findall(text) if not m.startswith(("http://", "https://", "mailto:"))]


def test_slug_follows_github():
    assert slug("One pair: 8M + 8M points from anywhere") == "one-pair-8m--8m-points-from-anywhere"
    assert slug("The `large` plot's ALS placements") == "the-large-plots-als-placements"


def broken_links(doc: Path) -> list[str]:
    broken = []
    for link in links(doc):
        target, _, anchor = link.partition("#")
        path = (doc.parent / target).resolve() if target else doc
        if not path.exists():
            broken.append(f"{link}: no such file")
        elif anchor and path.suffix == ".md" and anchor not in anchors(path):
            broken.append(f"{link}: no heading for #{anchor}")
    return broken


def test_broken_links_are_found(tmp_path):
    (tmp_path / "b.md").write_text("# Where it is\n")
    doc = tmp_path / "a.md"
    doc.write_text(
        "[ok](b.md#where-it-is) [gone](c.md) [moved](b.md#elsewhere) [web](https://x.org/#y)\n"
        "```\n[in code](nowhere.md)\n```\n"
    )
    assert broken_links(doc) == ["c.md: no such file", "b.md#elsewhere: no heading for #elsewhere"]


@pytest.mark.parametrize("doc", DOCUMENTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(doc: Path):
    broken = broken_links(doc)
    assert not broken, f"{doc.relative_to(ROOT)}: " + "; ".join(broken)


def test_cli_md_names_every_file_each_command_writes(tmp_path):
    """docs/cli.md's table of outputs names every file a command's output plan lists."""
    text = (ROOT / "docs" / "cli.md").read_text()
    table = text.split("## What each command writes", 1)[1].split("\n## ", 1)[0]
    align = output_plan(None, None, None, None, tmp_path / "R.json", None, False)
    names = [p.name for p in align.files] + list(LEVEL_NAMES)
    empty = SimpleNamespace(plots=[], scans=[], als=[], source=None)
    poses = tmp_path / "p.json"
    for plan in (
        register_plan(empty, None, tmp_path, False),
        tie_plan(empty, poses, None, tmp_path, False),
    ):
        names += list(plan.names)
    names += [*BENCH_NAMES, *DEMO_NAMES, *PAGES, *PAIR_FIGURES]
    missing = [n for n in names if f"`{n}" not in table]
    assert not missing, missing
