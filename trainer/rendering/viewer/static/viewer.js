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
