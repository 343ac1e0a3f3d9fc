"""Markdown (the subset the report writes) to one self-contained HTML page.

Supported: ATX headings (``#`` to ``######``), paragraphs, pipe tables (header,
separator, rows; ``\\|`` for a literal pipe), bullet lists (``- ``), images on
a line of their own (``![alt](figures/x.png)``, embedded as base64 PNG), and
inline ``code`` and ``**bold**``. Everything else is escaped text.
"""

from __future__ import annotations

import base64
import html
import re
from pathlib import Path

from .errors import ReportError

#: Inline CSS of the page.
CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; max-width: 1200px;
       margin: 2em auto; padding: 0 1em; line-height: 1.45; color: #222; }
h1 { border-bottom: 2px solid #ccc; padding-bottom: .2em; }
h2 { border-bottom: 1px solid #ddd; padding-bottom: .15em; margin-top: 1.8em; }
table { border-collapse: collapse; margin: .8em 0; font-size: 0.85em; }
th, td { border: 1px solid #ccc; padding: .25em .55em; text-align: left; vertical-align: top; }
th { background: #f2f2f2; }
tr:nth-child(even) td { background: #fafafa; }
code { background: #f4f4f4; padding: 0 .2em; border-radius: 3px; font-size: 0.9em; }
figure { margin: 1em 0; }
figure img { max-width: 100%; height: auto; border: 1px solid #eee; }
""".strip()

_HEADING = re.compile(r"^(#{1,6})\s+(.*)$")
_IMAGE = re.compile(r"^!\[([^\]]*)\]\(([^)\s]+)\)\s*$")
_SEPARATOR = re.compile(r"^\|?\s*:?-{3,}:?\s*(\|\s*:?-{3,}:?\s*)*\|?\s*$")
_CODE = re.compile(r"(`[^`]+`)")
_BOLD = re.compile(r"\*\*(.+?)\*\*")


def inline(text: str) -> str:
    """HTML of one line of Markdown text: escaped, with ``code`` and ``**bold**``."""
    out = []
    for tok in _CODE.split(text):
        if len(tok) >= 2 and tok.startswith("`") and tok.endswith("`"):
            out.append(f"<code>{html.escape(tok[1:-1])}</code>")
        else:
            out.append(_BOLD.sub(r"<strong>\1</strong>", html.escape(tok)))
    return "".join(out)


def split_row(line: str) -> list[str]:
    """Cells of a pipe-table row (``\\|`` is a literal pipe inside a cell)."""
    s = line.strip()
    if s.startswith("|"):
        s = s[1:]
    if s.endswith("|") and not s.endswith("\\|"):
        s = s[:-1]
    return [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", s)]


def _table(lines: list[str]) -> str:
    head = split_row(lines[0])
    body = lines[2:] if len(lines) > 1 and _SEPARATOR.match(lines[1].strip()) else lines[1:]
    out = ["<table>", "<thead><tr>" + "".join(f"<th>{inline(c)}</th>" for c in head) + "</tr></thead>", "<tbody>"]
    out += ["<tr>" + "".join(f"<td>{inline(c)}</td>" for c in split_row(r)) + "</tr>" for r in body]
    out.append("</tbody></table>")
    return "\n".join(out)


def _image(alt: str, src: str, base_dir: Path) -> str:
    path = base_dir / src
    if not src.lower().endswith(".png") or not path.is_file():
        raise ReportError(f"figure {src!r} referenced in the report is not a PNG file in {str(base_dir)!r}")
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return (f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(alt, quote=True)}">'
            "</figure>")


def _starts_block(line: str) -> bool:
    s = line.strip()
    return bool(_HEADING.match(s) or _IMAGE.match(s) or s.startswith("|") or s.startswith("- "))


def markdown_to_html(md: str, base_dir, title: str | None = None) -> str:
    """A complete HTML page from the Markdown ``md``; images are read relative to ``base_dir``.

    Raises
    ------
    ReportError
        An image is missing or not a PNG (the message names it).
    """
    base_dir = Path(base_dir)
    lines = md.splitlines()
    body, i = [], 0
    while i < len(lines):
        s = lines[i].strip()
        if not s:
            i += 1
            continue
        m = _HEADING.match(s)
        if m:
            n = len(m.group(1))
            title = title or (m.group(2) if n == 1 else None)
            body.append(f"<h{n}>{inline(m.group(2))}</h{n}>")
            i += 1
            continue
        m = _IMAGE.match(s)
        if m:
            body.append(_image(m.group(1), m.group(2), base_dir))
            i += 1
            continue
        if s.startswith("|"):
            j = i
            while j < len(lines) and lines[j].strip().startswith("|"):
                j += 1
            body.append(_table([ln.strip() for ln in lines[i:j]]))
            i = j
            continue
        if s.startswith("- "):
            items = []
            while i < len(lines) and lines[i].strip() and (lines[i].strip().startswith("- ") or not
                                                           _starts_block(lines[i])):
                t = lines[i].strip()
                if t.startswith("- "):
                    items.append(t[2:])
                else:
                    items[-1] += " " + t
                i += 1
            body.append("<ul>\n" + "\n".join(f"<li>{inline(t)}</li>" for t in items) + "\n</ul>")
            continue
        para = []
        while i < len(lines) and lines[i].strip() and not _starts_block(lines[i]):
            para.append(lines[i].strip())
            i += 1
        body.append(f"<p>{inline(' '.join(para))}</p>")
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{html.escape(title or 'report')}</title>\n<style>\n{CSS}\n</style>\n</head>\n<body>\n"
            + "\n".join(body) + "\n</body>\n</html>\n")
