"""The HTML shell of a report: one file, inline CSS, inline SVG figures, no script and no network."""

from __future__ import annotations

import json
from collections.abc import Sequence
from html import escape
from typing import Any

__all__ = ["Raw", "figure", "html_page", "missing", "table"]

_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;max-width:1100px;
     padding:0 24px 48px;color:#1b1b1b;line-height:1.45}
h1{font-size:1.6em;margin:24px 0 4px} h2{font-size:1.25em;margin:32px 0 8px;border-bottom:1px solid #ddd}
.sub{color:#555;margin:0 0 12px} nav a{margin-right:12px}
figure.fig{display:inline-block;margin:8px 12px 8px 0;vertical-align:top}
figure.fig svg{display:block;max-width:100%;height:auto;background:#fff}
figcaption{font-size:.9em;color:#444;max-width:720px}
.missing{border:1px dashed #c77;background:#fff6f4;padding:12px 16px;margin:8px 0;color:#733}
table{border-collapse:collapse;font-size:.88em;margin:8px 0}
th,td{border:1px solid #ddd;padding:3px 8px;text-align:left;vertical-align:top}
th{background:#f4f4f4} td.num{text-align:right;font-variant-numeric:tabular-nums}
.kept{color:#05753d;font-weight:bold} .rolled{color:#a33}
code,pre{font-family:ui-monospace,Menlo,Consolas,monospace;font-size:.92em}
pre{white-space:pre-wrap;margin:0;max-width:560px}
details{margin:6px 0} .scroll{overflow-x:auto;max-width:100%} .stat{font-size:1.05em;margin:6px 0}
"""


def html_page(title: str, subtitle: str, sections: Sequence[tuple[str, str, str]]) -> str:
    """The whole document; ``sections`` are ``(anchor, heading, body html)``."""
    nav = " ".join(f'<a href="#{a}">{escape(h)}</a>' for a, h, _ in sections)
    body = "".join(f'<section id="{a}"><h2>{escape(h)}</h2>{b}</section>' for a, h, b in sections)
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\"><title>{escape(title)}</title>"
            f"<style>{_CSS}</style></head><body><h1>{escape(title)}</h1><p class=\"sub\">{subtitle}</p>"
            f"<nav>{nav}</nav>{body}</body></html>\n")


def figure(svg: str, caption: str, name: str) -> str:
    """A figure the browser test finds (``figure.fig``) and checks is drawn."""
    return f'<figure class="fig" data-figure="{escape(name)}">{svg}<figcaption>{caption}</figcaption></figure>'


def missing(text: str) -> str:
    """The box that stands where data is missing: what is missing and which stage makes it."""
    return f'<div class="missing">{escape(text).replace("`", "")}</div>'


def _cell(value: Any) -> str:
    if isinstance(value, bool):
        return f"<td>{'yes' if value else 'no'}</td>"
    if isinstance(value, int):
        return f'<td class="num">{value}</td>'
    if isinstance(value, float):
        return f'<td class="num">{value:.4g}</td>'
    if isinstance(value, (dict, list)):
        return f"<td><pre>{escape(json.dumps(value, indent=1, sort_keys=True))}</pre></td>"
    if isinstance(value, Raw):
        return f"<td>{value.html}</td>"
    return f"<td>{escape(str(value))}</td>"


class Raw:
    """Cell content that is already HTML."""

    def __init__(self, html: str) -> None:
        self.html = html


def table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """An HTML table; numbers right-aligned, dicts and lists as indented JSON."""
    head = "".join(f"<th>{escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(_cell(v) for v in row) + "</tr>" for row in rows)
    return f'<div class="scroll"><table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table></div>'
