"""Refresh docs/cli.md from the installed `plotmosaic ... --help` (the text blocks only; prose stays).

    .venv/bin/python scripts/cli_help.py            # rewrite docs/cli.md
    .venv/bin/python scripts/cli_help.py --check    # exit 1 if docs/cli.md is out of date

Each `## COMMAND` section's first ```text block is replaced by `plotmosaic COMMAND --help` at 80 columns,
and the table row of each command by the first line of its help.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "docs" / "cli.md"
BLOCK = re.compile(r"(## (?P<name>[a-z-]+)\n\n```text\n)(?P<body>.*?)(```)", re.S)
ROW = re.compile(r"^\| \[`(?P<name>[a-z-]+)`\]\(#[a-z-]+\) \| (?P<what>.*) \|$", re.M)


def help_text(*command: str) -> str:
    env = {**os.environ, "COLUMNS": "80", "TERMINAL_WIDTH": "80", "NO_COLOR": "1"}
    argv = [
        str(Path(sys.executable).parent / "plotmosaic"),
        *command,
        "--help",
    ]  # the installed script
    out = subprocess.run(argv, capture_output=True, text=True, env=env, check=True).stdout
    return "\n".join(line.rstrip() for line in out.strip().splitlines()) + "\n"


def summary(text: str) -> str:
    """The help's first paragraph after the usage line, on one line."""
    paragraphs = [p for p in text.split("\n\n")[1:] if p.strip()]
    return " ".join(paragraphs[0].split()) if paragraphs else ""


def refreshed(doc: str) -> str:
    helps: dict[str, str] = {}

    def block(m: re.Match) -> str:
        helps[m["name"]] = help_text(m["name"])
        return m.group(1) + helps[m["name"]] + m.group(4)

    doc = BLOCK.sub(block, doc)

    def row(m: re.Match) -> str:
        what = summary(helps[m["name"]]) if m["name"] in helps else m["what"]
        return f"| [`{m['name']}`](#{m['name']}) | {what} |"

    return ROW.sub(row, doc)


def main() -> None:
    old = DOC.read_text()
    new = refreshed(old)
    if "--check" in sys.argv[1:]:
        sys.exit(0 if new == old else 1)
    DOC.write_text(new)


if __name__ == "__main__":
    main()
