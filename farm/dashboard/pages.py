"""The dashboard's HTML: Jinja2 templates (autoescaped) and server-drawn SVG charts. The CSS
and the few lines of JavaScript (live refresh, the cancel button) are written here; nothing
is loaded from elsewhere."""

from __future__ import annotations

import datetime as dt
import json

from jinja2 import DictLoader, Environment, select_autoescape
from markupsafe import Markup

from farm.state import RATE_WINDOW_S
from farm.web import ICON_LINK

CSS = """
body{font:14px/1.4 system-ui,sans-serif;margin:0;background:#f6f7f9;color:#1d2330}
header{background:#1d2330;color:#fff;padding:10px 20px;display:flex;gap:24px;align-items:center}
header a{color:#cfe0ff;text-decoration:none} main{padding:16px 20px}
h1{font-size:18px;margin:0} h2{font-size:15px;margin:22px 0 8px}
table{border-collapse:collapse;background:#fff;font-size:13px}
td,th{border-bottom:1px solid #e3e6eb;padding:4px 10px;text-align:left;vertical-align:top}
th{background:#eef1f5} .num{text-align:right;font-variant-numeric:tabular-nums}
.s-running{color:#0b6bcb;font-weight:600}.s-done{color:#1a7f37}.s-failed,.s-lost{color:#c62828}
.s-cancelled,.s-interrupted{color:#8a6d00} .err{color:#c62828} .stale{color:#c62828}
.cards{display:flex;gap:12px;flex-wrap:wrap} .card{background:#fff;padding:8px 14px;
border:1px solid #e3e6eb;border-radius:6px} .card b{display:block;font-size:20px}
.card b small{font-size:13px;font-weight:normal;color:#555}
.thumbs img{width:128px;height:128px;margin:0 6px 6px 0;border:1px solid #ccd;image-rendering:auto}
button{background:#c62828;color:#fff;border:0;padding:6px 14px;border-radius:4px;cursor:pointer}
.grid{display:flex;gap:24px;flex-wrap:wrap} svg text{font-size:11px;fill:#555}
.curves{margin-top:12px} .legend{font-size:12px;margin-top:4px}
"""

JS = """
async function refresh() {
  const live = document.getElementById('live');
  if (!live || live.dataset.live !== '1') return;
  try {
    const q = location.search ? '&' + location.search.slice(1) : '';
    const r = await fetch(location.pathname + '?fragment=1' + q);
    if (r.ok) { live.outerHTML = await r.text(); }
  } finally { setTimeout(refresh, 2500); }
}
setTimeout(refresh, 2500);
async function cancelJob(url) {
  if (!confirm('Cancel this job? Tasks in flight finish; whole shards are committed.')) return;
  const secret = document.querySelector('meta[name=secret]').content;
  const r = await fetch(url, {method: 'POST', headers: {'X-Shaderball-Secret': secret}});
  document.getElementById('cancel-msg').textContent = await r.text();
}
"""

BASE = """<!doctype html><html><head><meta charset="utf-8"><title>{{ title }} - shaderball</title>
{{ icon }}<meta name="secret" content="{{ secret }}"><style>{{ css }}</style></head><body>
<header><h1>shaderball farm</h1><a href="/">jobs</a><a href="/runs">runs</a>
<a href="/metrics">metrics</a></header><main>{% block main %}{% endblock %}</main>
<script>{{ js }}</script></body></html>"""

JOBS = """{% extends "base" %}{% block main %}
<p>Filter: <a href="/">all</a>{% for s in statuses %} · <a href="/?status={{ s }}">{{ s }}</a>
{% endfor %}</p>
<table id="jobs"><tr><th>store</th><th>status</th><th class="num">frames</th><th class="num">
frames/s</th><th class="num">ETA</th><th class="num">failed materials</th><th class="num">workers
</th><th class="num">age</th></tr>
{% for r in rows %}<tr>{% if r.error %}<td>{{ r.label }}</td><td class="err" colspan="7">
{{ r.error }}</td>{% else %}<td><a href="/job/{{ r.name }}">{{ r.label }}</a></td>
<td class="s-{{ r.status }}">{{ r.status }}</td>
<td class="num">{{ r.frames_done }}/{{ r.frames_total }}</td>
<td class="num">{{ "%.2f"|format(r.frames_per_s) }}{% if r.frames_per_s_now %}
<small title="frames rendered a second in the last {{ rate_window }} s: the ETA's rate">
({{ "%.2f"|format(r.frames_per_s_now) }} now)</small>{% endif %}</td>
<td class="num">{{ r.eta_s|dur }}</td>
<td class="num">{{ r.failed }}</td><td class="num">{{ r.workers }}</td>
<td class="num">{{ r.age_s|dur }}</td>{% endif %}</tr>{% endfor %}</table>
{% if not rows and want %}<p>No jobs match the filter: {{ want }}.</p>
{% elif not rows %}<p>No stores found under
{{ roots|join(", ") }}.</p>{% endif %}{% endblock %}"""

JOB = """{% extends "base" %}{% block main %}{% include "job_live" %}{% endblock %}"""

JOB_LIVE = """<div id="live" data-live="{{ 1 if row.status == 'running' else 0 }}">
<h2 style="margin-top:0">{{ row.label }} <span class="s-{{ row.status }}">{{ row.status }}</span>
{% set cancel = state.cancel_requested if state and row.status == 'running' %}
{% if row.status == 'running' and not cancel %}
<button onclick="cancelJob('/cancel/{{ row.name }}')">cancel</button>{% endif %}
<span id="cancel-msg">{% if cancel %}cancel requested by
{{ cancel.by }} at {{ cancel.at|when }}: the driver stops within a few seconds{% endif %}
</span></h2>
{% if row.error %}<p class="err">{{ row.error }}</p>{% else %}
<div class="cards">
<div class="card">frames<b id="frames">{{ row.frames_done }}/{{ row.frames_total }}</b></div>
<div class="card">progress<b>{{ "%.1f"|format(100 * row.frames_done / row.frames_total) }} %
</b></div>
<div class="card" title="committed frames a second over the run{% if row.frames_per_s_now %};
under it, frames rendered a second in the last {{ rate_window }} s, the ETA's rate{% endif %}">
frames/s<b id="fps">{{ "%.2f"|format(row.frames_per_s) }}{% if row.frames_per_s_now %}
<small id="fps-now"> {{ "%.2f"|format(row.frames_per_s_now) }} in the last
{{ rate_window }} s</small>{% endif %}</b></div>
<div class="card">ETA<b>{{ row.eta_s|dur }}</b></div>
<div class="card">shards<b id="shards">{{ committed }}/{{ row.shards_total }}</b></div>
<div class="card">failed materials<b id="failed">{{ row.failed }}</b></div>
<div class="card" title="placed and alive; starting: not placed by Ray yet (Blender
loading, or no room: a node still joining)">workers<b>{{ row.workers }}{% if row.waiting %}
<small id="waiting"> +{{ row.waiting }} starting</small>{% endif %}</b></div></div>
<p>{% if state %}driver {{ state.driver }} · started {{ state.started|when }} · updated
{{ state.updated|when }}{% endif %}{% if state and state.dashboard %} ·
<a href="{{ state.dashboard }}">Ray dashboard</a>{% endif %}</p>
{% if state and state.stop_error %}<p class="err" id="stop-error">stopped: {{ state.stop_error }}
</p>{% endif %}{% if state and state.screen_uv_error %}<p class="err">the store's screen UV layout
was not made: {{ state.screen_uv_error }} (<code>farm screen-uv</code> makes it)</p>{% endif %}
<h2>Frames rendered per second</h2>{{ chart }}<p><small>each point: the average over
the {{ rate_window }} s before it</small></p>
<h2>Shards</h2>{{ shard_map }}
<h2>Newest renders</h2><div class="thumbs" id="thumbs">{% for s in thumbs %}
<a href="/sheet/{{ row.name }}?sample={{ s }}">
<img alt="sample {{ s }}" src="/thumb/{{ row.name }}?sample={{ s }}"></a>{% endfor %}
{% if not thumbs %}none committed yet{% endif %}</div>
<h2>Failures</h2>{% if failures %}<table><tr><th>material</th><th>kind</th><th>source</th>
<th>outcome</th><th>attempts</th><th>worker: error</th></tr>{% for f in failures %}<tr><td>
{{ f.material if f.material is not none else "shard %d commit"|format(f.shard) }}</td>
<td>{{ f.kind }}</td><td>{{ f.source }}</td><td>{{ f.outcome }}</td><td class="num">{{ f.count
}}</td><td>{% for a in f.attempts %}{{ a.worker }}: {{ a.error }}<br>{% endfor %}</td></tr>
{% endfor %}</table>{% else %}<p>none</p>{% endif %}
<h2>Workers</h2>{% if workers %}<table><tr><th>worker</th><th>host</th><th>pid</th><th>status
</th><th class="num">frames</th><th class="num">s/frame</th><th class="num">failures</th><th
class="num">recycles</th><th class="num">recalled</th><th>last seen</th></tr>
{% for w in workers %}<tr><td>{{ w.worker }}</td>
<td>{{ w.host }}</td><td>{{ w.pid }}</td><td>{{ w.status }}{% if w.stale %} <span class="stale">
(stale)</span>{% endif %}</td><td class="num">{{ w.frames }}</td><td class="num">
{{ "%.2f"|format(w.mean_frame_s) }}</td><td class="num">{{ w.failures }}</td><td class="num">
{{ w.recycled }}</td><td class="num">{{ w.recalled|default(0) }}</td><td>{{ w.last_seen|when
}}</td></tr>{% endfor %}</table>
{% else %}<p>none</p>{% endif %}
<h2>Store</h2><div class="grid"><table>{% for k, v in settings %}<tr><th>{{ k }}</th><td>
{{ v|setting }}</td></tr>{% endfor %}</table><div>{% for name, svg in hists %}<div><b>{{ name }}
</b><br>{{ svg }}</div>{% endfor %}</div></div>{% endif %}</div>"""

RUNS = """{% extends "base" %}{% block main %}
{% if compare %}<h2>Held-out PSNR of every run (dB)</h2>{{ compare }}{% endif %}{% if mixed %}
<p class="err" id="mixed">These runs do not all score the same held-out samples (another store,
--holdout-fraction, --holdout-seed or --val-samples; "-": a run that does not name them): compare
their curves with that in mind.</p>{% endif %}{% for c in commands %}
<p class="compare-command">{{ c.labels|join(", ") }} score the same held-out samples: compare
their latest checkpoints sample by sample, with 95 % intervals, by <code>{{ c.command }}</code>
</p>{% endfor %}
{% for t in tuned %}<p class="tuned-command">
{{ t.label }} is fine-tuned. What it gained, on its held-out samples:<br><code>{{ t.gained }}</code>
<br>What it forgot, on those of the network it starts from:<br><code>{{ t.forgot }}</code></p>{%
endfor %}
{% if differ %}<h2>Settings that differ</h2><table><tr><th>run</th>{% for k in differ
%}<th>{{ k }}</th>{% endfor %}</tr>{% for r in runs %}<tr><td>{{
r.label }}</td>{% for k in differ %}<td>{{ r.settings.get(k)|setting }}</td>{% endfor %}</tr>{%
endfor %}</table>{% endif %}
{% for r in runs %}<h2>{{ r.label }} <small>{{ r.path }}</small></h2>
{% if r.settings %}<p class="settings">{% for k, v in r.settings.items() %}{{ k }} <b>{{ v|setting
}}</b>{% if not loop.last %} · {% endif %}{% endfor %}</p>{% endif %}
<div class="cards"><div class="card">step<b>{{ r.step|setting }}</b></div><div class="card">
epoch<b>{{ (r.epoch + 1) if r.epoch is not none else "-" }}</b></div><div class="card">loss<b>
{{ r.loss|num("%.4f") }}</b></div><div class="card">images/s<b>{{ r.images_per_second|num("%.1f")
}}</b></div><div class="card">data wait<b>{{ r.data_wait|num("%.1f %%", 100) }}</b></div>
{% if r.val_last %}<div class="card" title="step {{ r.val_last.step }}, {{ r.val_last.samples
}} held-out samples; best {{ "%.2f"|format(r.val_best.psnr) }} dB at step {{ r.val_best.step
}}">held-out PSNR<b>{{ r.val_last.psnr|num("%.2f dB") }}{% if r.val_last.psnr_low is number %}
<small>[{{ "%.2f"|format(r.val_last.psnr_low) }}, {{ "%.2f"|format(r.val_last.psnr_high) }}] over
{{ r.val_last.materials }} materials</small>{% endif %}{% if r.val_last.vs_best %}<small
class="vs-best"><br>{{ "%+.2f"|format(r.val_last.vs_best.mean) }} dB{% if r.val_last.vs_best.low
is number %} [{{ "%+.2f"|format(r.val_last.vs_best.low) }}, {{ "%+.2f"|format(
r.val_last.vs_best.high) }}]{% endif %} on step {{ r.val_last.vs_best.step }}'s, the best
before</small>{% endif %}</b></div><div class="card">held-out
SSIM<b>{{ r.val_last.ssim|num("%.4f") }}</b></div>{% if "trained_psnr" in r.val_last %}<div
class="card" title="the trained weights, scored beside the moving average the checkpoints render
with">trained weights' PSNR<b>{{ r.val_last.trained_psnr|num("%.2f dB") }}</b></div>{% endif %}{%
endif %}</div>
<div class="grid curves">{% for name, svg in r.curves %}<div><b>{{ name }}</b><br>{{ svg }}</div>
{% endfor %}</div>{% if r.val_grid and r.val_last %}
<p>held-out samples at step {{ r.val_last.step }}, the last score:</p><img
alt="held-out grid" style="max-width:100%"
src="/runfile/{{ r.name }}?file=val.png&amp;step={{ r.val_last.step }}">{% endif %}
<p>checkpoints: {% for c in r.checkpoints %}{{ c.name }} ({{ (c.bytes / 1e6)|round(1) }} MB) {%
else %}none{% endfor %}</p>{% if r.eval %}{% set o = r.eval.overall %}<p>eval at step
{{ r.eval.checkpoint_step }}: PSNR {{ "%.2f"|format(o.psnr) }} dB{% if o.psnr_low is number %}
<span title="95 % interval over materials">[{{ "%.2f"|format(o.psnr_low) }},
{{ "%.2f"|format(o.psnr_high) }}]</span>{% endif %}, SSIM {{ "%.4f"|format(o.ssim) }} on
{{ o.n }} held-out samples{% if o.materials is defined %} of {{ o.materials }}
material{{ "s" if o.materials != 1 }}{% endif %}</p>{% endif %}{% if r.eval_grid %}<img
alt="eval grid" style="max-width:100%" src="/runfile/{{ r.name }}?file=eval.png">{% endif %}
{% else %}<p>No runs (start with --runs DIR).</p>{% endfor %}{% endblock %}"""


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


ENV = Environment(
    loader=DictLoader({"base": BASE, "jobs": JOBS, "job": JOB, "job_live": JOB_LIVE, "runs": RUNS}),
    autoescape=select_autoescape(default=True, default_for_string=True),
)
ENV.filters["dur"] = _dur
ENV.filters["when"] = _when
ENV.filters["setting"] = _setting
ENV.filters["num"] = _num
ENV.globals["rate_window"] = f"{RATE_WINDOW_S:.0f}"  # seconds behind each rendered rate


def render(name: str, **ctx) -> str:
    return ENV.get_template(name).render(
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
