"""The run's report as a self-contained ``report.html``: its markdown lines, figures inline.

:func:`write_html` is called by :func:`clrecon.outputs.report.write_report` after ``report.md``;
:func:`markdown_to_html` knows only the small markdown subset the report uses (headings,
tables, lists, images, inline code, bold and italics).
"""

from __future__ import annotations

import base64
import html
import re
from pathlib import Path

from clrecon.core import atomic


def _inline(text: str, base: Path) -> str:
    t = html.escape(text, quote=False)
    t = re.sub(r"`([^`]+)`", r"<code>\1</code>", t)
    t = re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", t)
    t = re.sub(r"(?<![\w*])\*([^*]+)\*(?![\w*])", r"<i>\1</i>", t)
    return t


def _img(alt: str, src: str, base: Path) -> str:
    p = base / src
    if p.exists():
        data = base64.b64encode(p.read_bytes()).decode()
        src = f"data:image/png;base64,{data}"
    return f'<p><img alt="{html.escape(alt)}" src="{src}" style="max-width:100%"></p>'


def markdown_to_html(lines: list[str], base: Path, title: str = "clrecon report") -> str:
    """The small markdown subset the report uses (headings, tables, lists, images) -> HTML.

    Images under ``base`` are embedded as base64 so the page is self-contained.
    """
    out = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
           "<style>body{font-family:sans-serif;max-width:1200px;margin:auto;padding:1em}"
           "table{border-collapse:collapse}td,th{border:1px solid #bbb;padding:2px 6px;text-align:right}"
           "</style></head><body>"]
    i = 0
    while i < len(lines):
        line = lines[i].rstrip()
        m = re.match(r"^(#{1,6})\s+(.*)$", line)
        img = re.match(r"^!\[([^\]]*)\]\(([^)]+)\)$", line)
        if m:
            n = len(m.group(1))
            out.append(f"<h{n}>{_inline(m.group(2), base)}</h{n}>")
        elif img:
            out.append(_img(img.group(1), img.group(2), base))
        elif line.startswith("|"):
            rows = []
            while i < len(lines) and lines[i].startswith("|"):
                rows.append(lines[i].strip().strip("|").split("|"))
                i += 1
            i -= 1
            out.append("<table>")
            for k, cells in enumerate(rows):
                if all(re.fullmatch(r"\s*-+\s*", c) for c in cells):
                    continue
                tag = "th" if k == 0 else "td"
                out.append("<tr>" + "".join(f"<{tag}>{_inline(c.strip(), base)}</{tag}>" for c in cells) + "</tr>")
            out.append("</table>")
        elif line.startswith("- "):
            out.append("<ul>")
            while i < len(lines) and lines[i].startswith("- "):
                out.append(f"<li>{_inline(lines[i][2:], base)}</li>")
                i += 1
            i -= 1
            out.append("</ul>")
        elif line:
            out.append(f"<p>{_inline(line, base)}</p>")
        i += 1
    out.append("</body></html>")
    return "\n".join(out) + "\n"


def write_html(out_dir, lines: list[str], title: str = "clrecon report", staged: bool = False) -> Path:
    """Write ``out_dir/report.html`` from the report's markdown lines, figures inline; ``staged``:
    under its temporary name, for :func:`clrecon.core.atomic.commit` (returns the final name)."""
    out_dir = Path(out_dir)
    path = out_dir / "report.html"
    atomic.write_text(path, markdown_to_html(lines, out_dir, title), staged=staged)
    return path
