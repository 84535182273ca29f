"""The documents' relative links resolve: the file exists and, for a Markdown file, the #anchor names
one of its headings (GitHub's rule: lower case, punctuation dropped, spaces to hyphens)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

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
