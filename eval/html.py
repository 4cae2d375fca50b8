"""The report's HTML page: its markdown (headings, pipe tables, images, paragraphs) as one standalone page."""

from __future__ import annotations

import html
from pathlib import Path


def to_html(md: str, out: Path) -> str:
    """Minimal markdown (headings, pipe tables, images, paragraphs) to a standalone HTML page."""
    import base64

    lines, body, table = md.split("\n"), [], False
    for ln in lines:
        if ln.startswith("|"):
            cells = [c.strip() for c in ln.strip("|").split("|")]
            if all(set(c) <= {"-"} and c for c in cells):
                continue
            if not table:
                body.append("<table border=1 cellspacing=0 cellpadding=3>")
                table = True
            body.append("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in cells) + "</tr>")
            continue
        if table:
            body.append("</table>")
            table = False
        if ln.startswith("#"):
            lvl = len(ln) - len(ln.lstrip("#"))
            body.append(f"<h{lvl}>{html.escape(ln[lvl:].strip())}</h{lvl}>")
        elif ln.startswith("!["):
            src = ln[ln.index("(") + 1 : ln.rindex(")")]
            b64 = base64.b64encode((out / src).read_bytes()).decode() if (out / src).exists() else ""
            body.append(f'<img alt="{html.escape(src)}" src="data:image/png;base64,{b64}">')
        elif ln.strip():
            body.append(f"<p>{html.escape(ln)}</p>")
    if table:
        body.append("</table>")
    page = "<!doctype html><html><head><meta charset='utf-8'><title>hivemap report</title></head><body>"
    page += "\n".join(body) + "</body></html>"
    return page
