"""The dashboard's HTML: Jinja2 templates (``templates/``, autoescaped) and server-drawn SVG
charts. The CSS and the few lines of JavaScript (live refresh, the cancel button) are files
of the package (``static/``), inlined into every page; nothing is loaded from elsewhere."""

from __future__ import annotations

import datetime as dt
import json
from importlib import resources

from jinja2 import Environment, PackageLoader, select_autoescape
from markupsafe import Markup

from farm.state import RATE_WINDOW_S
from shaderball.web import ICON_LINK


def _dur(s) -> str:
    if s is None:
        return "-"
    s = float(s)
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.0f} min"
    return f"{s / 3600:.1f} h"


def _setting(v) -> str:
    """A store setting as people read it: none as "-", yes / no, numbers and text as they
    are, lists and mappings as compact JSON."""
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, dict | list | tuple):
        return json.dumps(v, separators=(", ", ": "))
    return str(v)


def _num(v, fmt: str, scale: float = 1.0) -> str:
    """A number in ``fmt`` after multiplying by ``scale``; "-" when there is none yet."""
    return "-" if v is None else fmt % (float(v) * scale)


def _when(t) -> str:
    return dt.datetime.fromtimestamp(float(t)).strftime("%Y-%m-%d %H:%M:%S") if t else "-"


#: the page templates (``templates/NAME.html``) and the CSS and JavaScript every page inlines
#: (``static/``): package data, read once
ENV = Environment(
    loader=PackageLoader("farm.dashboard", "templates"),
    autoescape=select_autoescape(default=True, default_for_string=True),
)
STATIC = resources.files("farm.dashboard") / "static"
CSS = (STATIC / "dashboard.css").read_text()
JS = (STATIC / "dashboard.js").read_text()
ENV.filters["dur"] = _dur
ENV.filters["when"] = _when
ENV.filters["setting"] = _setting
ENV.filters["num"] = _num
ENV.globals["rate_window"] = f"{RATE_WINDOW_S:.0f}"  # seconds behind each rendered rate


def render(name: str, **ctx) -> str:
    """The page ``templates/NAME.html`` filled with ``ctx``."""
    return ENV.get_template(f"{name}.html").render(
        css=Markup(CSS), js=Markup(JS), icon=Markup(ICON_LINK), **ctx
    )


def line_chart(
    points: list[tuple[float, float]],
    w: int = 640,
    h: int = 160,
    steps: bool = False,
    from_zero: bool = True,
    band: list[tuple[float, float, float]] | None = None,
) -> Markup:
    """An SVG line of ``(x, y)`` points with its y range and x span labelled: x in seconds,
    or with ``steps`` in training steps; y from 0, or without ``from_zero`` over the range
    of the points (a score in dB, whose changes a line from 0 would flatten). ``band``:
    ``(x, low, high)`` of an interval around the line, shaded (two of them at least)."""
    if not points:
        return Markup("<p>no progress points yet</p>")
    if len(points) == 1:  # a line needs two: the one value, and where it was taken
        ((x, y),) = points
        at = f"step {x:.0f}" if steps else f"{x:.0f} s"
        return Markup(f'<p class="one-point">one point so far: <b>{y:.4g}</b> at {at}</p>')
    return _chart([(None, points)], w, h, steps, from_zero, band if band and len(band) > 1 else [])


#: the colours of a chart's lines, in turn
LINE_COLOURS = ("#0b6bcb", "#c62828", "#1a7f37", "#e0a800", "#7b3fb0", "#00838f", "#6d4c41")


def lines_chart(
    series: list[tuple[str, list[tuple[float, float]]]], w: int = 640, h: int = 200
) -> Markup:
    """Labelled lines of ``(step, y)`` points on shared axes, y over the points' range, each
    in its colour, with a legend of the labels under the chart."""
    drawn = [(label, points) for label, points in series if len(points) >= 2]
    if not drawn:
        return Markup("<p>not enough points yet</p>")
    return _chart(drawn, w, h, steps=True, from_zero=False)


def _chart(
    series: list, w: int, h: int, steps: bool, from_zero: bool, band: list | None = None
) -> Markup:
    """The SVG of :func:`line_chart` and :func:`lines_chart`; a legend when lines are named,
    a shaded ``band`` under the first line when given."""
    band = band or []
    xs = [x for _, points in series for x, _ in points]
    ys = [y for _, points in series for _, y in points]
    ys += [v for _, lo, hi in band for v in (lo, hi)]
    x0, x1 = min(xs), max(xs)
    y0 = 0.0 if from_zero else min(ys)
    y1 = max(max(ys), y0 + 1e-9)
    pad = 30

    def at(points) -> str:
        return " ".join(
            f"{pad + (x - x0) / max(x1 - x0, 1e-9) * (w - pad - 5):.1f},"
            f"{h - 15 - (y - y0) / (y1 - y0) * (h - 25):.1f}"
            for x, y in points
        )

    lines = []
    if band:  # the interval's upper edge left to right, then its lower edge back
        edge = [(x, hi) for x, _, hi in band] + [(x, lo) for x, lo, _ in reversed(band)]
        lines.append(
            f'<polygon class="band" fill="#0b6bcb" fill-opacity="0.15" points="{at(edge)}"/>'
        )
    legend = []
    for i, (label, points) in enumerate(series):
        colour = LINE_COLOURS[i % len(LINE_COLOURS)]
        coords = at(points)
        lines.append(
            f'<polyline fill="none" stroke="{colour}" stroke-width="1.5" points="{coords}"/>'
        )
        if label is not None:
            legend.append(Markup('<span style="color:{}">&#9632;</span> {}').format(colour, label))
    span = f"steps {x0:.0f} to {x1:.0f}" if steps else f"{_dur(x1 - x0)} shown"
    svg = Markup(
        f'<svg class="chart" width="{w}" height="{h}" viewBox="0 0 {w} {h}" '
        f'style="background:#fff;border:1px solid #e3e6eb">{"".join(lines)}'
        f'<text x="2" y="12">{y1:.3g}</text><text x="2" y="{h - 15}">{y0:.3g}</text>'
        f'<text x="{pad}" y="{h - 2}">{span}</text></svg>'
    )
    if not legend:
        return svg
    return svg + Markup('<div class="legend">') + Markup("<br>").join(legend) + Markup("</div>")


COLOURS = {
    "committed": "#1a7f37",
    "pending": "#e0a800",
    "queued": "#c9d3e0",
    "failed": "#c62828",
    "empty": "#eceff3",
}


def shard_map(states: list[str], cell: int = 10, per_row: int = 80) -> Markup:
    """One square per shard, coloured by state, with a legend; a single SVG path per state
    keeps a map of thousands of shards small and fast to draw."""
    paths: dict[str, list[str]] = {k: [] for k in COLOURS}
    for i, st in enumerate(states):
        x, y = (i % per_row) * cell, (i // per_row) * cell
        paths[st].append(f"M{x} {y}h{cell - 1}v{cell - 1}h-{cell - 1}z")
    rows = -(-len(states) // per_row)
    w, h = per_row * cell, rows * cell
    body = "".join(
        f'<path fill="{COLOURS[k]}" d="{"".join(v)}"><title>{k}</title></path>'
        for k, v in paths.items()
        if v
    )
    counts = " · ".join(f'<span style="color:{COLOURS[k]}">■</span> {k} {states.count(k)}'
                        for k in COLOURS if k in states)  # fmt: skip
    return Markup(f'<svg id="shardmap" width="{w}" height="{h}">{body}</svg><p>{counts}</p>')


def bar_chart(bins: list[tuple[float, float, int]], w: int = 240, h: int = 110) -> Markup:
    if not bins:
        return Markup("<p>no samples yet</p>")
    peak = max(c for _, _, c in bins) or 1
    bw = w / len(bins)
    bars = "".join(
        f'<rect x="{i * bw + 1:.1f}" y="{h - 15 - c / peak * (h - 25):.1f}" width="{bw - 2:.1f}" '
        f'height="{c / peak * (h - 25):.1f}" fill="#0b6bcb"><title>{a:.3g}-{b:.3g}: {c}</title>'
        "</rect>"
        for i, (a, b, c) in enumerate(bins)
    )
    lo, hi = bins[0][0], bins[-1][1]
    return Markup(
        f'<svg width="{w}" height="{h}" style="background:#fff">{bars}'
        f'<text x="0" y="{h - 2}">{lo:.3g}</text><text x="{w - 20}" y="{h - 2}">{hi:.3g}</text>'
        "</svg>"
    )
