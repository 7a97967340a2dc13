"""The pieces of `clothbench report`'s page (reports/html.py puts a study on it): text made
safe, numbers for people, tables, sections and their table of contents, matplotlib SVGs inlined
with ids and styles of their own, and the page around them, whose small stylesheet is inline:
nothing in it is fetched."""

from __future__ import annotations

import html
import math
import re
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from clothbench import __version__

STYLE = """
:root { color-scheme: light; --line: #d0d4da; --soft: #f4f6f8; --ink: #1d232a; --dim: #5b6570; }
body { font: 15px/1.5 system-ui, -apple-system, "Segoe UI", Roboto, "DejaVu Sans", sans-serif;
       color: var(--ink); margin: 0; background: #fff; }
main { max-width: 1240px; margin: 0 auto; padding: 1.5rem 1.5rem 4rem; }
h1 { font-size: 1.8rem; margin: 0 0 .3rem; }
h2 { font-size: 1.35rem; margin: 2.6rem 0 .6rem; padding-bottom: .25rem; border-bottom: 2px solid var(--line); }
h3 { font-size: 1.1rem; margin: 1.8rem 0 .5rem; }
p, li { max-width: 52rem; }
.lead { color: var(--dim); margin-top: 0; }
nav.toc { background: var(--soft); border: 1px solid var(--line); border-radius: 6px; padding: .6rem 1.2rem;
          margin: 1.2rem 0; }
nav.toc h2 { border: 0; margin: .4rem 0; font-size: 1.05rem; }
nav.toc ol { margin: .2rem 0; padding-left: 1.3rem; }
a { color: #1f5fa8; }
table { border-collapse: collapse; margin: .6rem 0 1rem; font-size: .88rem; }
caption { caption-side: top; text-align: left; color: var(--dim); padding-bottom: .3rem; }
th, td { border: 1px solid var(--line); padding: .25rem .55rem; vertical-align: top; }
th { background: var(--soft); text-align: left; font-weight: 600; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
tr.peer td:first-child::after { content: "peer"; font-size: .72rem; color: #8a4b00; background: #fff1dc;
          border: 1px solid #f0c987; border-radius: 3px; padding: 0 .25rem; margin-left: .35rem;
          display: inline-block; font-style: normal; white-space: nowrap; }
tr.peer td { font-style: italic; }
td.best { font-weight: 700; }
figure { margin: 1rem 0 1.6rem; }
figure svg { display: block; width: 100%; height: auto; border: 1px solid var(--line); border-radius: 4px; }
figcaption { color: var(--dim); font-size: .88rem; margin-top: .35rem; max-width: 52rem; }
.notice { background: #fff8e1; border-left: 4px solid #e0a800; padding: .45rem .8rem; margin: .8rem 0; }
code, .mono { font-family: ui-monospace, "DejaVu Sans Mono", monospace; font-size: .85em; }
ul.packages { columns: 3 14rem; padding-left: 1.1rem; font-size: .85rem; }
footer { color: var(--dim); font-size: .8rem; margin-top: 3rem; }
"""


class Html(str):
    """Text already safe to put into the page as it is."""


def esc(value) -> Html:
    return value if isinstance(value, Html) else Html(html.escape(str(value)))


class Exact(float):
    """A value that was set, not measured (a dt, a stiffness): shown without trailing zeros."""


def num(value, digits: int = 3) -> Html:
    """A number for people: `digits` significant digits, thousands grouped, powers of ten
    written as such below 0.001 and from 100,000 up; '–' for a missing value. An Exact
    value drops the trailing zeros (0.001, not 0.00100)."""
    if value is None or value == "":
        return Html("–")
    if isinstance(value, int) and not isinstance(value, bool):
        return Html(f"{value:,}")
    v = float(value)
    if not math.isfinite(v):
        return Html("–")
    if v == 0:
        return Html("0")
    exponent = math.floor(math.log10(abs(v)))
    if isinstance(value, Exact):  # as set: up to 4 significant digits, plain from 0.0001 to millions
        digits, low, high = 4, -4, 7
        trim = lambda t: t.rstrip("0").rstrip(".") if "." in t else t  # noqa: E731
    else:
        low, high, trim = -3, 5, str
    if low <= exponent < high:
        return Html(trim(f"{v:,.{max(0, digits - 1 - exponent)}f}"))
    mantissa = f"{v / 10**exponent:.{digits - 1}f}"
    if mantissa.lstrip("-").startswith("10"):  # 9.996 rounds up a decade
        exponent, mantissa = exponent + 1, f"{v / 10 ** (exponent + 1):.{digits - 1}f}"
    mantissa = trim(mantissa)
    return Html(f"{mantissa}&#8239;×&#8239;10<sup>{str(exponent).replace('-', '−')}</sup>")


def slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "section"


def table(
    head: list[str],
    rows: list[list],
    caption: str = "",
    row_classes: list[str] | None = None,
    best: set[tuple[int, int]] = frozenset(),
    right: set[int] = frozenset(),
) -> Html:
    """A table; numbers (and the `right` columns) right-aligned, numbers formatted by num(),
    None shown as '–'; `best` marks (row, column) cells."""
    out = ["<table>"]
    if caption:
        out.append(f"<caption>{esc(caption)}</caption>")
    out.append("<thead><tr>" + "".join(f"<th>{esc(h)}</th>" for h in head) + "</tr></thead><tbody>")
    for i, cells in enumerate(rows):
        cls = f' class="{row_classes[i]}"' if row_classes and row_classes[i] else ""
        tds = []
        for j, c in enumerate(cells):
            numeric = c is None or isinstance(c, (int, float)) and not isinstance(c, bool)
            classes = " ".join(k for k, on in (("num", numeric or j in right), ("best", (i, j) in best)) if on)
            attr = f' class="{classes}"' if classes else ""
            tds.append(f"<td{attr}>{num(c) if numeric else esc(c)}</td>")
        out.append(f"<tr{cls}>{''.join(tds)}</tr>")
    out.append("</tbody></table>")
    return Html("".join(out))


def paragraph(text) -> Html:
    return Html(f"<p>{esc(text)}</p>")


def notice(text) -> Html:
    return Html(f'<p class="notice">{esc(text)}</p>')


@dataclass
class Section:
    title: str
    id: str
    body: list[Html] = field(default_factory=list)
    children: list[Section] = field(default_factory=list)

    def render(self, level: int = 2) -> Html:
        parts = [f'<section id="{self.id}"><h{level}>{esc(self.title)}</h{level}>', *self.body]
        parts += [c.render(level + 1) for c in self.children]
        return Html("".join(parts) + "</section>")

    def toc(self) -> Html:
        inner = "".join(c.toc() for c in self.children)
        return Html(
            f'<li><a href="#{self.id}">{esc(self.title)}</a>' + (f"<ol>{inner}</ol>" if inner else "") + "</li>"
        )


# What makes a matplotlib SVG a document of its own, and what it names
_PROLOG = re.compile(r"<\?xml[^>]*\?>|<!DOCTYPE[^>]*>|<metadata>.*?</metadata>", re.S)
_ID_USE = re.compile(r'(\bid="|href="#|url\(#)([^")]+)')
_STYLE = re.compile(r"(<style[^>]*>)(.*?)(</style>)", re.S)
_ROOT = re.compile(r"<svg\b[^>]*>")
_LENGTH = re.compile(r'\s(width|height)="([\d.]+)(pt|px)?"')
PX_PER_PT = 4 / 3


class Figures:
    """Draws figures into a temporary folder and puts their SVG into the page, each with ids
    of its own (several matplotlib SVGs in one page would otherwise share glyph and clip ids)
    and its stylesheet confined to it."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.count = 0

    def folder_for(self, name: str) -> Path:
        path = self.folder / f"{len(list(self.folder.iterdir())):02d}-{slug(name)}"
        path.mkdir()
        return path

    def inline(self, svg_path: Path, title: str, caption: str = "") -> Html:
        self.count += 1
        fig_id = f"fig{self.count}"
        text = _PROLOG.sub("", Path(svg_path).read_text(encoding="utf-8"))
        ids = set(re.findall(r'\bid="([^"]+)"', text))
        text = _ID_USE.sub(lambda m: m[1] + (f"{fig_id}-{m[2]}" if m[2] in ids else m[2]), text)
        text = _STYLE.sub(lambda m: m[1] + _scoped(m[2], fig_id) + m[3], text)
        root = _ROOT.search(text)
        if root is None:
            raise ValueError(f"{svg_path} is not an SVG")
        sizes = {k: float(v) * (PX_PER_PT if unit == "pt" else 1) for k, v, unit in _LENGTH.findall(root[0])}
        width = f' style="max-width:{sizes["width"]:.0f}px"' if "width" in sizes else ""
        opened = _LENGTH.sub("", root[0])[:-1] + (
            f' id="{fig_id}" class="figure" role="img" aria-label="{esc(title)}"{width}>'
        )
        svg = text[: root.start()] + opened + text[root.end() :]
        cap = f"<figcaption><b>{esc(title)}.</b> {esc(caption)}</figcaption>" if title or caption else ""
        return Html(f'<figure id="{fig_id}-figure">{svg.strip()}{cap}</figure>')


def _scoped(css: str, fig_id: str) -> str:
    """Every rule of an SVG's own stylesheet confined to that SVG."""

    def rule(m) -> str:
        selectors = ", ".join(f"#{fig_id} {s.strip()}" for s in m[1].split(","))
        return f"{selectors} {{{m[2]}}}"

    return re.sub(r"([^{}]+)\{([^{}]*)\}", rule, css)


def page(title: str, intro: list[Html], sections: list[Section]) -> str:
    toc = '<nav class="toc"><h2>Contents</h2><ol>' + "".join(s.toc() for s in sections) + "</ol></nav>"
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{esc(title)}</title><style>{STYLE}</style></head>\n<body><main>"
        f"<h1>{esc(title)}</h1>{''.join(intro)}{toc}{''.join(s.render() for s in sections)}"
        f"<footer>Written by clothbench {esc(__version__)} on {stamp}; self-contained: nothing in this "
        "page is fetched from elsewhere.</footer></main></body></html>\n"
    )


__all__ = ["Html", "Exact", "esc", "num", "slug", "table", "paragraph", "notice", "Section", "Figures", "page"]
