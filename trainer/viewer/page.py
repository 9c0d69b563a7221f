"""The viewer's page: one Jinja2 template (autoescaped), its CSS and its JavaScript, all
written here; nothing is loaded from elsewhere.

The script keeps the page's state (material id, edits, light), asks ``/api/frame`` for a new
image whenever any of it changes, with at most one request in flight and the latest state
sent next (so dragging the sun never queues stale frames), and shows the ``Server-Timing``
parts. The sun is dragged on an SVG hemisphere seen from above: the centre is the zenith,
the rim the horizon, the camera at the bottom (it looks along +Y); distance from the centre
is 90° minus the elevation. "Turn the sun" moves it round the sky at its elevation until
stopped (or dragged), as fast as frames come, and shows the frames a second.
"""

from __future__ import annotations

from jinja2 import Environment, select_autoescape

from farm.web import ICON_LINK

CSS = """
*{box-sizing:border-box} body{font:14px/1.4 system-ui,sans-serif;margin:0;background:#16181d;
color:#e4e6eb} header{background:#0d0e11;padding:8px 18px;display:flex;gap:18px;
align-items:baseline} h1{font-size:17px;margin:0} header span{color:#9aa3b2;font-size:12px}
main{display:grid;grid-template-columns:330px 1fr 300px;gap:16px;padding:14px 18px}
section{background:#1f2229;border:1px solid #2c3039;border-radius:8px;padding:10px 12px;
margin-bottom:12px} h2{font-size:13px;margin:0 0 8px;color:#b8c1d1;text-transform:uppercase;
letter-spacing:.04em} #gallery{display:grid;grid-template-columns:repeat(4,1fr);gap:6px;
max-height:300px;overflow:auto} .tile{cursor:pointer;border:2px solid transparent;
border-radius:5px;background:#111;text-align:center;font-size:10px;color:#9aa3b2;
overflow:hidden;white-space:nowrap;text-overflow:ellipsis}.tile img{width:100%;display:block;
aspect-ratio:1} .tile.on{border-color:#5aa0ff} label{display:flex;justify-content:space-between;
align-items:center;gap:8px;margin:4px 0;font-size:13px} input[type=range]{width:150px}
.err{color:#ff7b72;min-height:1.2em;font-size:12px} .ok{color:#7ee787}
#view{text-align:center} #frame{width:min(100%,560px);aspect-ratio:1;background:#000;
border-radius:6px;image-rendering:auto;transition:opacity .2s} #frame.waiting{opacity:.55}
#timing{font:12px ui-monospace,monospace;color:#9aa3b2;
margin:6px 0} button,.button{background:#2f6fd6;color:#fff;border:0;padding:6px 12px;
border-radius:5px;cursor:pointer;font-size:13px;text-decoration:none}
button.quiet{background:#3a3f4a} #sky{touch-action:none;cursor:crosshair;display:block;
margin:0 auto;user-select:none;-webkit-user-select:none}
#suns button{margin:2px;padding:3px 8px;background:#3a3f4a}
#suns button.on{background:#2f6fd6} #truth{display:none} #truth img{width:31%;
image-rendering:auto;border-radius:4px} #truth .row{display:flex;gap:3%;
justify-content:center} #truth .cap{display:flex;gap:3%;justify-content:center;font-size:11px;
color:#9aa3b2} #truth .cap span{width:31%} small{color:#9aa3b2}
"""

SCRIPT = """
const S = JSON.parse(document.getElementById('state').textContent);
const secret = document.querySelector('meta[name=secret]').content;
const state = {m: S.materials.length ? S.materials[0].id : null, az: 240, el: 40, t: 3,
  edits: {}, stored: null};
const $ = (id) => document.getElementById(id);
let inFlight = false, pending = false, shown = null;

function query(extra) {
  const p = new URLSearchParams({m: state.m, az: state.az.toFixed(2), el: state.el.toFixed(2),
                                 t: state.t.toFixed(2)});
  for (const [k, v] of Object.entries(state.edits)) p.set(k, v);
  for (const [k, v] of Object.entries(extra || {})) p.set(k, v);
  return p.toString();
}
function timing(header) {
  const parts = {};
  for (const item of (header || '').split(',')) {
    const name = item.trim().split(';')[0];
    const dur = /dur=([0-9.]+)/.exec(item), desc = /desc="([^"]*)"/.exec(item);
    if (dur) parts[name] = [parseFloat(dur[1]), desc ? desc[1] : ''];
  }
  return parts;
}
async function requestFrame() {
  if (!state.m) return;
  if (inFlight) { pending = true; return; }
  inFlight = true;
  const started = performance.now();
  let ticking = null;
  const working = () => {
    const s = ((performance.now() - started) / 1000).toFixed(1);
    $('timing').textContent =
      'working… ' + s + ' s (a material is read from its files when first shown)';
  };
  const slow = setTimeout(() => {  // a large material's first frame reads its files: seconds
    $('frame').classList.add('waiting');
    working();
    ticking = setInterval(working, 100);
  }, 300);
  try {
    const r = await fetch('/api/frame?' + query());
    if (r.ok) {
      const url = URL.createObjectURL(await r.blob());
      $('frame').src = url;
      if (shown) URL.revokeObjectURL(shown);
      shown = url;
      const t = timing(r.headers.get('Server-Timing'));
      const map = t.map ? (t.map[1] === 'cached' ? 'cached' : t.map[0].toFixed(1) + ' ms') : '?';
      const total = (t.map ? t.map[0] : 0) + (t.net ? t.net[0] : 0) + (t.enc ? t.enc[0] : 0);
      $('timing').textContent = 'mapping ' + map + ' · network ' + t.net[0].toFixed(1) +
        ' ms · encoding ' + t.enc[0].toFixed(1) + ' ms · frame ' + total.toFixed(1) + ' ms';
      $('frame-msg').textContent = '';
      $('frame').dataset.frames = String(parseInt($('frame').dataset.frames || '0') + 1);
    } else {
      $('frame-msg').textContent = (await r.json()).error;
    }
  } finally {
    clearTimeout(slow);
    clearInterval(ticking);
    $('frame').classList.remove('waiting');
    inFlight = false;
    if (pending) { pending = false; requestFrame(); }
  }
}

// ---- material -----------------------------------------------------------------------------
function tile(m) {
  const d = document.createElement('div');
  d.className = 'tile'; d.dataset.id = m.id; d.title = m.label;
  const img = document.createElement('img');
  img.loading = 'lazy'; img.src = '/api/thumb?m=' + encodeURIComponent(m.id);
  d.appendChild(img);
  d.appendChild(document.createTextNode(m.label));
  d.onclick = () => pick(m);
  return d;
}
function pick(m) {
  state.m = m.id; state.stored = null;
  for (const el of document.querySelectorAll('.tile'))
    el.classList.toggle('on', el.dataset.id === m.id);
  $('material').textContent = m.label + ' (' + m.kind + ')';
  const suns = $('suns'); suns.innerHTML = '';
  (m.suns || []).forEach((s) => {
    const b = document.createElement('button');
    b.textContent = 'sun ' + (s.k + 1); b.title = 'el ' + s.elevation.toFixed(0) + '° az ' +
      s.azimuth.toFixed(0) + '° T ' + s.turbidity.toFixed(1);
    b.onclick = () => storedSun(m, s);
    suns.appendChild(b);
  });
  $('suns-box').style.display = (m.suns || []).length ? 'block' : 'none';
  hideTruth();
  requestFrame();
}
const byId = {};
S.materials.forEach((m) => { byId[m.id] = m; $('gallery').appendChild(tile(m)); });

$('upload-go').onclick = async () => {
  const files = $('upload').files;
  $('upload-msg').textContent = ''; $('upload-msg').className = 'err';
  if (!files.length) {
    $('upload-msg').textContent = 'choose a 5-panel PNG or per-map images'; return;
  }
  const form = new FormData();
  for (const f of files) form.append('file', f, f.name);
  const r = await fetch('/api/upload', {method: 'POST', body: form,
                                        headers: {'X-Shaderball-Secret': secret}});
  const body = await r.json();
  if (!r.ok) { $('upload-msg').textContent = body.error; return; }
  $('upload-msg').className = 'ok'; $('upload-msg').textContent = 'loaded ' + body.label;
  byId[body.id] = body; $('gallery').prepend(tile(body)); pick(body);
  $('gallery-count').textContent = String($('gallery').children.length);
};

function uniformId() {
  return 'uniform:diffuse=' + $('u-diffuse').value + ';specular=' + $('u-specular').value +
    ';roughness=' + parseFloat($('u-roughness').value).toFixed(3);
}
for (const id of ['u-diffuse', 'u-specular', 'u-roughness'])
  $(id).addEventListener('input', () => {
    $('u-roughness-v').textContent = parseFloat($('u-roughness').value).toFixed(2);
    pick({id: uniformId(), label: 'uniform', kind: 'uniform', suns: []});
  });

// ---- edits ----------------------------------------------------------------------------------
const EDITS = ['diffuse_tint', 'diffuse_scale', 'specular_tint', 'specular_scale',
               'roughness_scale', 'normal_strength', 'tiling'];
function readEdits() {
  state.edits = {};
  for (const k of EDITS) {
    const el = $(k), v = el.value;
    if (el.dataset.default !== v) state.edits[k] = v;
    const out = $(k + '-v'); if (out) out.textContent = parseFloat(v).toFixed(2);
  }
  state.stored = null; hideTruth(); requestFrame();
}
for (const k of EDITS) $(k).addEventListener('input', readEdits);
$('reset').onclick = () => {
  for (const k of EDITS) $(k).value = $(k).dataset.default;
  readEdits();
};

// ---- light ----------------------------------------------------------------------------------
const R = 100, C = 110;
function drawSun() {
  const r = (90 - state.el) / 90 * R, a = state.az * Math.PI / 180;
  $('sun').setAttribute('cx', C + r * Math.cos(a));
  $('sun').setAttribute('cy', C - r * Math.sin(a));
  $('light-v').textContent = 'azimuth ' + state.az.toFixed(0) + '°, elevation ' +
    state.el.toFixed(0) + '°, turbidity ' + state.t.toFixed(1);
  $('turbidity').value = state.t; $('turbidity-v').textContent = state.t.toFixed(1);
}
function dragTo(ev) {
  const box = $('sky').getBoundingClientRect();
  const x = (ev.clientX - box.left) * 220 / box.width - C;
  const y = C - (ev.clientY - box.top) * 220 / box.height;
  const r = Math.min(Math.hypot(x, y), R * 89.5 / 90);
  state.el = 90 - r / R * 90;
  state.az = ((Math.atan2(y, x) * 180 / Math.PI) + 360) % 360;
  state.stored = null; hideTruth(); drawSun(); requestFrame();
}
$('sky').addEventListener('pointerdown', (ev) => {
  ev.preventDefault(); turnSun(false);
  $('sky').setPointerCapture(ev.pointerId); dragTo(ev);
  $('sky').onpointermove = dragTo;
});
$('sky').addEventListener('pointerup', () => { $('sky').onpointermove = null; });
$('turbidity').addEventListener('input', () => {
  state.t = parseFloat($('turbidity').value); state.stored = null; hideTruth(); drawSun();
  requestFrame();
});

// the sun turning round the sky at its elevation, a turn in TURN_S seconds: each animation
// frame moves it by the time passed, and requestFrame sends the newest light when the last
// frame is in, so the network, not a timer, sets the frame rate shown
const TURN_S = 12;
let turning = null;
function turnStep(now) {
  if (!turning) return;
  state.az = (state.az + 360 * (now - turning.last) / 1000 / TURN_S) % 360;
  turning.last = now;
  state.stored = null; hideTruth(); drawSun(); requestFrame();
  const got = parseInt($('frame').dataset.frames) - turning.frames;
  const s = (now - turning.start) / 1000;
  if (s > 1) $('turn-rate').textContent = (got / s).toFixed(1) + ' frames/s';
  requestAnimationFrame(turnStep);
}
function turnSun(on) {
  const now = performance.now();
  turning = on ? {start: now, last: now, frames: parseInt($('frame').dataset.frames)} : null;
  $('turn').textContent = on ? '■ stop the sun' : '▶ turn the sun';
  $('turn').classList.toggle('quiet', !on);
  if (on) requestAnimationFrame(turnStep); else $('turn-rate').textContent = '';
}
$('turn').onclick = () => turnSun(!turning);

// ---- ground truth ---------------------------------------------------------------------------
function hideTruth() {
  $('truth').style.display = 'none';
  for (const b of document.querySelectorAll('#suns button')) b.classList.remove('on');
}
async function storedSun(m, s) {
  turnSun(false);
  state.az = s.azimuth; state.el = s.elevation; state.t = s.turbidity;
  drawSun(); requestFrame();
  for (const [i, b] of [...document.querySelectorAll('#suns button')].entries())
    b.classList.toggle('on', i === s.k);
  if (Object.keys(state.edits).length) {
    $('truth-msg').textContent = 'ground truth is for the unedited material: reset the edits';
    return;
  }
  $('truth-msg').textContent = '';
  const r = await fetch('/api/truth?' + new URLSearchParams({m: m.id, k: s.k}));
  const body = await r.json();
  if (!r.ok) { $('truth-msg').textContent = body.error; return; }
  $('truth-cycles').src = body.truth; $('truth-net').src = body.network;
  $('truth-err').src = body.error;
  $('truth-psnr').textContent = 'PSNR ' + body.psnr.toFixed(2) + ' dB (network vs Cycles)';
  $('truth').style.display = 'block';
}

// ---- save -----------------------------------------------------------------------------------
$('save').onclick = () => {
  const a = document.createElement('a');
  a.href = '/api/frame?' + query({fmt: 'png', download: '1'});
  a.download = '';
  document.body.appendChild(a); a.click(); a.remove();
};

drawSun();
if (S.materials.length) pick(S.materials[0]);
else pick({id: uniformId(), label: 'uniform', kind: 'uniform', suns: []});
"""

PAGE = """<!doctype html><html><head><meta charset="utf-8"><title>shaderball viewer</title>
{{ icon }}<meta name="secret" content="{{ secret }}"><style>{{ css }}</style></head><body>
<header><h1>shaderball viewer</h1><span>{{ info.checkpoint }} ·{% if info.step is not none %}
step {{ info.step }} ·{% endif %}{% if info.weights == "average" %} averaged weights ·{% endif %}
{{ info.model }} {{ info.resolution }}² · {{ info.device }}{% if not info.mapping %} · stored
materials only (no screen UV layout){% endif %}</span></header>
<main>
<div>
<section><h2>Material</h2><div id="gallery"></div>
<p><small><span id="gallery-count">{{ materials|length }}</span> in the gallery; pick one,
upload one, or build one.</small></p>
</section>
<section><h2>Upload</h2>
<input type="file" id="upload" multiple accept="image/*,.exr,.tif,.tiff,.tga">
<button id="upload-go">load</button>
<div><small>a 5-panel PNG (photo, normal, diffuse, roughness, specular) or a material's
per-map images</small></div><div id="upload-msg" class="err"></div></section>
<section><h2>Uniform</h2>
<label>diffuse <input type="color" id="u-diffuse" value="#b03a2e"></label>
<label>specular <input type="color" id="u-specular" value="#0a0a0a"></label>
<label>roughness <input type="range" id="u-roughness" min="0.02" max="1" step="0.01"
value="0.3"><span id="u-roughness-v">0.30</span></label></section>
</div>
<div id="view"><section>
<div id="material"></div>
<img id="frame" alt="the network's render" data-frames="0">
<div id="timing">…</div><div id="frame-msg" class="err"></div>
<button id="save">save PNG</button>
</section>
<section id="truth"><h2>Cycles ground truth</h2>
<div class="row"><img id="truth-cycles" alt="Cycles"><img id="truth-net" alt="network">
<img id="truth-err" alt="error"></div>
<div class="cap"><span>Cycles</span><span>network</span><span>|error| × 4</span></div>
<div id="truth-psnr"></div></section>
</div>
<div>
<section><h2>Light</h2>
<svg id="sky" width="220" height="220" viewBox="0 0 220 220">
<circle cx="110" cy="110" r="100" fill="#243047" stroke="#4a5872"/>
<circle cx="110" cy="110" r="66.7" fill="none" stroke="#3a4761" stroke-dasharray="3 3"/>
<circle cx="110" cy="110" r="33.3" fill="none" stroke="#3a4761" stroke-dasharray="3 3"/>
<text x="110" y="218" fill="#9aa3b2" font-size="10" text-anchor="middle">camera</text>
<text x="112" y="106" fill="#6d7a92" font-size="9">90°</text>
<text x="112" y="40" fill="#6d7a92" font-size="9">30°</text>
<circle id="sun" r="9" fill="#ffd75e" stroke="#fff6c8" stroke-width="2"/></svg>
<div id="light-v" style="text-align:center;font-size:12px;color:#9aa3b2"></div>
<div style="text-align:center;margin:4px 0"><button class="quiet" id="turn">▶ turn the sun</button>
<small id="turn-rate"></small></div>
<label>turbidity <input type="range" id="turbidity" min="1" max="10" step="0.1" value="3">
<span id="turbidity-v">3.0</span></label>
<div id="suns-box" style="display:none"><small>stored suns (Cycles ground truth):</small>
<div id="suns"></div></div><div id="truth-msg" class="err"></div></section>
<section><h2>Edit</h2>
<label>diffuse tint <input type="color" id="diffuse_tint" value="#ffffff"
data-default="#ffffff"></label>
<label>diffuse × <input type="range" id="diffuse_scale" min="0" max="2" step="0.01" value="1"
data-default="1"><span id="diffuse_scale-v">1.00</span></label>
<label>specular tint <input type="color" id="specular_tint" value="#ffffff"
data-default="#ffffff"></label>
<label>specular × <input type="range" id="specular_scale" min="0" max="4" step="0.01"
value="1" data-default="1"><span id="specular_scale-v">1.00</span></label>
<label>roughness × <input type="range" id="roughness_scale" min="0" max="3" step="0.01"
value="1" data-default="1"><span id="roughness_scale-v">1.00</span></label>
<label>normal strength <input type="range" id="normal_strength" min="0" max="3" step="0.01"
value="1" data-default="1"><span id="normal_strength-v">1.00</span></label>
<label>tiling <input type="range" id="tiling" min="0.25" max="4" step="0.05" value="1"
data-default="1"><span id="tiling-v">1.00</span></label>
<button class="quiet" id="reset">reset edits</button></section>
</div></main>
<script type="application/json" id="state">{{ state|tojson }}</script>
<script>{{ script }}</script></body></html>"""

_ENV = Environment(autoescape=select_autoescape(default=True, default_for_string=True))
_PAGE = _ENV.from_string(PAGE)


def render(secret: str, info: dict, materials: list[dict]) -> str:
    from markupsafe import Markup

    return _PAGE.render(
        secret=secret,
        info=info,
        materials=materials,
        state={"materials": materials, "info": info},
        css=Markup(CSS),
        script=Markup(SCRIPT),
        icon=Markup(ICON_LINK),
    )
