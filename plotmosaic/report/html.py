"""One self-contained HTML page: PNG figures embedded as base64, tables, no script, no server."""

from __future__ import annotations

import base64
import html
from pathlib import Path

from plotmosaic.io.atomic import write_text_atomic

STYLE = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:1.5em auto;max-width:1300px;color:#222;padding:0 1em}
h1{margin-bottom:.2em} h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.6em 0;font-size:.88em} td,th{border:1px solid #ccc;padding:3px 7px;text-align:right}
th{background:#f2f2f2} td:first-child,th:first-child{text-align:left}
.summary{background:#f7f9fc;border:1px solid #d5deeb;padding:.6em 1.2em;border-radius:6px}
.warn{color:#9a3b00} .ok{color:#1d6b2a} figure{margin:1em 0} figcaption{font-size:.9em;color:#555}
img{max-width:100%;border:1px solid #eee} .read{color:#333;font-style:italic}
pre{background:#f7f7f7;padding:.5em;font-size:.9em}
"""


def esc(text: object) -> str:
    return html.escape(str(text))


def image(png: Path, caption: str, read: str = "") -> str:
    """A figure with the PNG inlined (data URI), so the page needs no other file; `read` is one
    line on how to read it."""
    data = base64.b64encode(Path(png).read_bytes()).decode("ascii")
    how = f'<br><span class="read">How to read: {esc(read)}</span>' if read else ""
    return (
        f'<figure><img src="data:image/png;base64,{data}" alt="{esc(caption)}">'
        f"<figcaption>{esc(caption)}{how}</figcaption></figure>"
    )


def table(header: list[str], rows: list[list[object]], caption: str | None = None) -> str:
    cap = f"<caption>{esc(caption)}</caption>" if caption else ""
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table>{cap}<thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def markdown_table(lines: list[str], caption: str | None = None) -> str:
    """An HTML table from the markdown table rows report.md carries (| a | b | ... with a --- line)."""
    rows = [
        [c.strip().replace("**", "") for c in ln.strip().strip("|").split("|")]
        for ln in lines
        if ln.strip().startswith("|")
    ]
    rows = [r for r in rows if not all(set(c) <= set("-: ") for c in r)]
    return table(rows[0], rows[1:], caption) if rows else ""


def bullets(items: list[str], cls: str = "") -> str:
    attr = f' class="{cls}"' if cls else ""
    return "<ul>" + "".join(f"<li{attr}>{esc(i)}</li>" for i in items) + "</ul>"


class Page:
    """Sections appended in reading order, written atomically as one file."""

    def __init__(self, title: str):
        self.title = title
        self.parts: list[str] = []

    def heading(self, text: str, level: int = 2) -> None:
        self.parts.append(f"<h{level}>{esc(text)}</h{level}>")

    def paragraph(self, text: str) -> None:
        self.parts.append(f"<p>{esc(text)}</p>")

    def raw(self, fragment: str) -> None:
        self.parts.append(fragment)

    def link(self, href: str, text: str) -> None:
        self.parts.append(f'<p><a href="{esc(href)}">{esc(text)}</a></p>')

    def write(self, path: Path) -> Path:
        doc = (
            f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{esc(self.title)}</title>'
            f"<style>{STYLE}</style></head><body><h1>{esc(self.title)}</h1>\n"
            + "\n".join(self.parts)
            + "\n</body></html>\n"
        )
        return write_text_atomic(path, doc)
