"""The one page builder of every ``report.html`` (calibrate, identify-legs, diagnose, track): one
template, one style sheet, and the small pieces the report writers share (escaping, numbers, table
rows, figures as PNG data URIs).

A page is self-contained: inline CSS, figures embedded as ``data:image/png;base64`` URIs, nothing
fetched from the network; the one script is the 3-D view's, inline (:mod:`graphcal.report.scene_view`).
The report writers build their sections as HTML fragments (:class:`markupsafe.Markup`, escaped with
:func:`esc`) and :func:`render_page` puts them into the template (jinja2, autoescaping every plain
string).
"""

from __future__ import annotations

import base64
import math
from typing import Iterable, Sequence

import jinja2
from markupsafe import Markup, escape

__all__ = ["CSS", "Markup", "Section", "esc", "num", "row", "table", "figure", "figure_png_html", "warnings_box",
           "render_page"]

#: the one style sheet of every graphcal page
CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:2em auto;max-width:1000px;color:#222;
padding:0 1em;line-height:1.4}
h1{font-size:1.6em}h2{font-size:1.25em;border-bottom:1px solid #ddd;padding-bottom:.2em;margin-top:1.6em}
h3{font-size:1.05em}
table{border-collapse:collapse;margin:.5em 0 1em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right;vertical-align:top}
th{background:#f3f3f3}td.l,th.l{text-align:left}
ul.facts{padding-left:1.2em}ul.facts li{margin:.15em 0}
.warn{background:#fff4e5;border:1px solid #f0a030;border-left:6px solid #f0a030;padding:.6em 1em;margin:.6em 0}
.ok{color:#2a7a2a}
pre{background:#f6f6f6;border:1px solid #ddd;padding:.6em;font-size:.8em;white-space:pre-wrap;overflow-wrap:anywhere}
code{font-size:.92em}
figure{margin:1em 0}figure img{max-width:100%;height:auto;border:1px solid #eee}
figcaption{font-size:.85em;color:#555}
.small{font-size:.85em;color:#555}
.flag{color:#a00000;font-weight:bold}
"""

_TEMPLATE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{{ title }}</title>
<style>{{ css }}</style>
</head>
<body>
<h1>{{ title }}</h1>
{% if subtitle %}<p class="small">{{ subtitle }}</p>
{% endif %}{% if warnings %}{{ warnings }}
{% endif %}{% for s in sections %}{% if s.heading %}<h2>{{ s.heading }}</h2>
{% endif %}{{ s.body }}
{% endfor %}<p class="small">{{ footer }}</p>
</body>
</html>
"""

_ENV = jinja2.Environment(autoescape=True, keep_trailing_newline=True, undefined=jinja2.StrictUndefined)
_PAGE = _ENV.from_string(_TEMPLATE)


class Section:
    """One ``<h2>`` section of a page: its heading (plain text) and its body (HTML fragments)."""

    __slots__ = ("heading", "body")

    def __init__(self, heading: str | None, *parts: str | Markup):
        self.heading = heading
        self.body = Markup("\n").join(p if isinstance(p, Markup) else Markup(p) for p in parts)


def esc(x) -> Markup:
    """``x`` as text in HTML (escaped, quotes too)."""
    return escape(str(x))


def num(x, fmt: str = ".3f") -> str:
    """A number for a table cell: ``format(x, fmt)``; NaN as an en dash, infinities as ∞; no "-0.000"."""
    try:
        x = float(x)
    except (TypeError, ValueError):
        return str(esc(x))
    if math.isnan(x):
        return "–"
    if math.isinf(x):
        return "∞" if x > 0 else "−∞"
    text = format(x, fmt)
    if text.lstrip("+-").strip("0.") == "":  # -0.000 -> 0.000
        text = text.lstrip("+-")
    return text


def row(cells: Sequence, header: bool = False, first_left: bool = True) -> str:
    """One table row of HTML cells (already escaped); the first cell left-aligned (a label)."""
    tag = "th" if header else "td"
    out = []
    for i, c in enumerate(cells):
        cls = ' class="l"' if (i == 0 and first_left) else ""
        out.append(f"<{tag}{cls}>{c}</{tag}>")
    return "<tr>" + "".join(out) + "</tr>"


def table(rows: Iterable[str]) -> Markup:
    """``<table>`` of rows made by :func:`row`."""
    return Markup("<table>" + "".join(rows) + "</table>")


def figure_png_html(png: bytes, caption: str) -> Markup:
    """A ``<figure>``: the PNG as a data URI, ``caption`` as its alt text and caption (plain text)."""
    data = base64.b64encode(png).decode("ascii")
    return Markup(f'<figure><img src="data:image/png;base64,{data}" alt="{esc(caption)}">'
                  f"<figcaption>{esc(caption)}</figcaption></figure>")


def figure(fig, caption: str) -> Markup:
    """A matplotlib figure as a ``<figure>`` (rendered by :func:`graphcal.report.plots.figure_png`)."""
    from graphcal.report.plots import figure_png

    return figure_png_html(figure_png(fig), caption)


def warnings_box(warnings: Sequence[str], heading: str = "Warnings") -> Markup:
    """The orange box of warnings (plain-text items); empty when there are none."""
    if not warnings:
        return Markup("")
    items = "".join(f"<li>{esc(w)}</li>" for w in warnings)
    return Markup(f'<div class="warn"><strong>{esc(heading)}</strong><ul>{items}</ul></div>')


def render_page(title: str, sections: Sequence[Section], *, subtitle: str | Markup = "",
                warnings: Sequence[str] = (), footer: str = "") -> str:
    """The whole page: ``title`` (plain text) as ``<title>`` and ``<h1>``, ``subtitle`` under it,
    the ``warnings`` box, the sections in order, then ``footer`` (plain text) in small print."""
    return _PAGE.render(title=title, css=Markup(CSS), subtitle=subtitle, warnings=warnings_box(warnings),
                        sections=sections, footer=footer)
