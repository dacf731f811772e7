// fbgcomp live dashboard: Server-Sent Events in, small hand-written canvas strip charts out.
// No library and no CDN, so the page works on a shop-floor network without internet.
"use strict";

const WINDOW_S = 60;                 // seconds of history shown by the charts
const COLOURS = ["#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000", "#F0E442"];
const AXES = ["dx", "dy", "dz"];

// -------------------------------------------------------------------------- strip chart
class StripChart {
  constructor(canvas, names, unit) {
    this.canvas = canvas;
    this.names = names;
    this.unit = unit;
    this.t = [];                     // sample times, s
    this.y = names.map(() => []);    // one array per series
    this.dirty = true;
  }
  push(t, values) {
    if (this.t.length && t < this.t[this.t.length - 1]) {   // clock went back (replay restarted)
      this.t = []; this.y = this.names.map(() => []);
    }
    this.t.push(t);
    values.forEach((v, i) => this.y[i].push(v === null || v === undefined ? NaN : v));
    const cut = t - WINDOW_S;
    let drop = 0;
    while (drop < this.t.length && this.t[drop] < cut) drop++;
    if (drop) { this.t.splice(0, drop); this.y.forEach(s => s.splice(0, drop)); }
    this.dirty = true;
  }
  draw() {
    if (!this.dirty) return;
    this.dirty = false;
    const c = this.canvas, ratio = window.devicePixelRatio || 1;
    const w = c.clientWidth || c.width, h = c.clientHeight || c.height;
    if (c.width !== Math.round(w * ratio) || c.height !== Math.round(h * ratio)) {
      c.width = Math.round(w * ratio); c.height = Math.round(h * ratio);
    }
    const g = c.getContext("2d");
    g.setTransform(ratio, 0, 0, ratio, 0, 0);
    g.clearRect(0, 0, w, h);
    const left = 58, right = 22, top = 24, bottom = 26;   // right: room for "now"
    const pw = w - left - right, ph = h - top - bottom;
    let lo = Infinity, hi = -Infinity;
    for (const s of this.y) for (const v of s) if (Number.isFinite(v)) { if (v < lo) lo = v; if (v > hi) hi = v; }
    if (!Number.isFinite(lo)) { lo = -1; hi = 1; }
    if (hi - lo < 1e-6) { lo -= 0.5; hi += 0.5; }
    const pad = 0.08 * (hi - lo); lo -= pad; hi += pad;
    const tEnd = this.t.length ? this.t[this.t.length - 1] : 0, tStart = tEnd - WINDOW_S;
    const X = t => left + (t - tStart) / WINDOW_S * pw;
    const Y = v => top + (hi - v) / (hi - lo) * ph;
    // grid and tick labels
    g.font = "12px DejaVu Sans, Helvetica, Arial, sans-serif";
    g.strokeStyle = "#e3e6ea"; g.fillStyle = "#333"; g.lineWidth = 1;
    const step = niceStep((hi - lo) / 5);
    g.textAlign = "right"; g.textBaseline = "middle";
    for (let v = Math.ceil(lo / step) * step; v <= hi; v += step) {
      const y = Math.round(Y(v)) + 0.5;
      g.beginPath(); g.moveTo(left, y); g.lineTo(left + pw, y); g.stroke();
      g.fillText(formatTick(v, step), left - 6, y);
    }
    g.textAlign = "center"; g.textBaseline = "top";
    for (let s = 0; s <= WINDOW_S; s += 10) {
      const x = Math.round(X(tStart + s)) + 0.5;
      g.beginPath(); g.moveTo(x, top); g.lineTo(x, top + ph); g.stroke();
      g.fillText(s === WINDOW_S ? "now" : `${s - WINDOW_S} s`, x, top + ph + 5);
    }
    g.strokeStyle = "#888"; g.strokeRect(left + 0.5, top + 0.5, pw, ph);
    g.save(); g.translate(13, top + ph / 2); g.rotate(-Math.PI / 2);
    g.textAlign = "center"; g.textBaseline = "middle"; g.fillText(this.unit, 0, 0); g.restore();
    // series
    g.save(); g.beginPath(); g.rect(left, top, pw, ph); g.clip();
    this.y.forEach((s, i) => {
      g.strokeStyle = COLOURS[i % COLOURS.length]; g.lineWidth = 2; g.beginPath();
      let pen = false;
      for (let k = 0; k < s.length; k++) {
        if (!Number.isFinite(s[k])) { pen = false; continue; }
        const x = X(this.t[k]), y = Y(s[k]);
        if (pen) g.lineTo(x, y); else { g.moveTo(x, y); pen = true; }
      }
      g.stroke();
    });
    g.restore();
    // legend along the top
    g.textAlign = "left"; g.textBaseline = "middle";
    let x = left;
    this.names.forEach((name, i) => {
      g.fillStyle = COLOURS[i % COLOURS.length]; g.fillRect(x, 8, 16, 4);
      g.fillStyle = "#111"; g.fillText(name, x + 20, 10);
      x += 28 + g.measureText(name).width;
    });
  }
}

function niceStep(raw) {
  const p = Math.pow(10, Math.floor(Math.log10(raw)));
  const m = raw / p;
  return (m < 1.5 ? 1 : m < 3 ? 2 : m < 7 ? 5 : 10) * p;
}
function formatTick(v, step) {
  const digits = Math.max(0, -Math.floor(Math.log10(step)));
  return (Math.abs(v) < step / 1e6 ? 0 : v).toFixed(Math.min(digits, 6));
}
function fmt(v, digits) {
  return v === null || v === undefined || !Number.isFinite(v) ? "—" : v.toFixed(digits);
}

// -------------------------------------------------------------------------- drift charts
// Windows of 1 min to 36 h from the run log, downsampled by the service (/api/history): each
// bucket carries min, max and mean of every value and how many of its frames were flagged.
function spanText(s) {
  return s >= 3600 ? `${+(s / 3600).toFixed(1)} h` : s >= 60 ? `${+(s / 60).toFixed(1)} min` : `${s} s`;
}
const TICK_STEPS = [10, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200, 10800, 21600, 43200];

function drawFrame(g, w, h, box, windowS, lo, hi, unit) {
  const { left, top, pw, ph } = box;
  const X = t => left + (t + windowS) / windowS * pw;   // t: seconds before the end (<= 0)
  g.font = "12px DejaVu Sans, Helvetica, Arial, sans-serif";
  g.strokeStyle = "#e3e6ea"; g.fillStyle = "#333"; g.lineWidth = 1;
  if (unit) {
    const Y = v => top + (hi - v) / (hi - lo) * ph;
    const step = niceStep((hi - lo) / 5);
    g.textAlign = "right"; g.textBaseline = "middle";
    for (let v = Math.ceil(lo / step) * step; v <= hi; v += step) {
      const y = Math.round(Y(v)) + 0.5;
      g.beginPath(); g.moveTo(left, y); g.lineTo(left + pw, y); g.stroke();
      g.fillText(formatTick(v, step), left - 6, y);
    }
    g.save(); g.translate(13, top + ph / 2); g.rotate(-Math.PI / 2);
    g.textAlign = "center"; g.textBaseline = "middle"; g.fillText(unit, 0, 0); g.restore();
  }
  const step = TICK_STEPS.find(st => windowS / st <= 7) || 43200;
  g.textAlign = "center"; g.textBaseline = "top"; g.fillStyle = "#333";
  for (let s = 0; s <= windowS + 1e-9; s += step) {
    const x = Math.round(X(-s)) + 0.5;
    g.beginPath(); g.moveTo(x, top); g.lineTo(x, top + ph); g.stroke();
    g.fillText(s === 0 ? "now" : `−${spanText(s)}`, x, top + ph + 5);
  }
  g.strokeStyle = "#888"; g.strokeRect(left + 0.5, top + 0.5, pw, ph);
  return X;
}

function prepare(canvas) {
  const ratio = window.devicePixelRatio || 1;
  const w = canvas.clientWidth || canvas.width, h = canvas.clientHeight || canvas.height;
  if (canvas.width !== Math.round(w * ratio) || canvas.height !== Math.round(h * ratio)) {
    canvas.width = Math.round(w * ratio); canvas.height = Math.round(h * ratio);
  }
  const g = canvas.getContext("2d");
  g.setTransform(ratio, 0, 0, ratio, 0, 0);
  g.clearRect(0, 0, w, h);
  return { g, w, h };
}

// series: [{name, colour, mean, min, max, dash}] on bucket start times t (s, instrument clock)
function drawDrift(canvas, d, series, unit) {
  const { g, w, h } = prepare(canvas);
  const box = { left: 58, top: 24, pw: w - 58 - 26, ph: h - 24 - 26 };
  let lo = Infinity, hi = -Infinity;
  for (const s of series) for (const arr of [s.min, s.max, s.mean]) for (const v of arr)
    if (v !== null && Number.isFinite(v)) { if (v < lo) lo = v; if (v > hi) hi = v; }
  if (!Number.isFinite(lo)) { lo = -1; hi = 1; }
  if (hi - lo < 1e-6) { lo -= 0.5; hi += 0.5; }
  const pad = 0.08 * (hi - lo); lo -= pad; hi += pad;
  const X0 = drawFrame(g, w, h, box, d.window_s, lo, hi, unit);
  const end = d.t_end, half = d.bucket_s / 2;
  const X = t => X0(t + half - end), Y = v => box.top + (hi - v) / (hi - lo) * box.ph;
  const gap = k => k > 0 && d.t[k] - d.t[k - 1] > 1.5 * d.bucket_s;
  g.save(); g.beginPath(); g.rect(box.left, box.top, box.pw, box.ph); g.clip();
  series.forEach(s => {             // min..max band: every excursion inside a bucket stays visible
    g.fillStyle = s.colour; g.globalAlpha = 0.18;
    let k = 0;
    while (k < d.t.length) {
      while (k < d.t.length && (s.min[k] === null || s.max[k] === null)) k++;
      let j = k;
      while (j < d.t.length && s.min[j] !== null && s.max[j] !== null && !(j > k && gap(j))) j++;
      if (j > k) {
        g.beginPath(); g.moveTo(X(d.t[k]), Y(s.max[k]));
        for (let q = k + 1; q < j; q++) g.lineTo(X(d.t[q]), Y(s.max[q]));
        for (let q = j - 1; q >= k; q--) g.lineTo(X(d.t[q]), Y(s.min[q]));
        g.closePath(); g.fill();
      }
      k = Math.max(j, k + 1);
    }
    g.globalAlpha = 1;
  });
  series.forEach(s => {
    g.strokeStyle = s.colour; g.lineWidth = 2; g.setLineDash(s.dash ? [6, 4] : []); g.beginPath();
    let pen = false;
    for (let k = 0; k < d.t.length; k++) {
      const v = s.mean[k];
      if (v === null || gap(k)) pen = false;
      if (v === null) continue;
      if (pen) g.lineTo(X(d.t[k]), Y(v)); else { g.moveTo(X(d.t[k]), Y(v)); pen = true; }
    }
    g.stroke(); g.setLineDash([]);
  });
  g.restore();
  g.textAlign = "left"; g.textBaseline = "middle"; g.font = "12px DejaVu Sans, Helvetica, Arial, sans-serif";
  let x = box.left;
  series.forEach(s => {
    g.fillStyle = s.colour; g.fillRect(x, 8, 16, 4);
    g.fillStyle = "#111"; g.fillText(s.name, x + 20, 10);
    x += 28 + g.measureText(s.name).width;
  });
}

// lanes: [{label, colour, share}]: one row each, a bucket shaded by the share of its frames
function drawHeld(canvas, d, lanes) {
  const { g, w, h } = prepare(canvas);
  const box = { left: 130, top: 6, pw: w - 130 - 26, ph: h - 6 - 26 };
  const X0 = drawFrame(g, w, h, box, d.window_s, 0, 1, null);
  const rowH = box.ph / Math.max(lanes.length, 1);
  const bw = Math.max(box.pw * d.bucket_s / d.window_s, 1);
  g.font = "12px DejaVu Sans, Helvetica, Arial, sans-serif";
  lanes.forEach((lane, i) => {
    const y = box.top + i * rowH;
    g.fillStyle = "#111"; g.textAlign = "right"; g.textBaseline = "middle";
    g.fillText(lane.label, box.left - 6, y + rowH / 2);
    g.fillStyle = lane.colour;
    for (let k = 0; k < d.t.length; k++) {
      const share = lane.share[k];
      if (!share) continue;
      g.globalAlpha = 0.3 + 0.7 * share;
      g.fillRect(X0(d.t[k] - d.t_end), y + 2, bw, rowH - 4);
    }
    g.globalAlpha = 1;
    g.strokeStyle = "#e3e6ea"; g.beginPath(); g.moveTo(box.left, y + rowH); g.lineTo(box.left + box.pw, y + rowH); g.stroke();
  });
}

const HELD_COLOURS = { ALARM: "#c00", DEGRADED: "#b35900", ZEROING: "#6b7280", "output disabled": "#555",
  RATE_LIMITED: "#0072B2", MAX_LIMITED: "#D55E00", CLAMPED: "#CC79A7", SHRUNK: "#009E73", LOAD_REFUSED: "#E69F00" };

function showDrift(d) {
  const bucketsWith = share => share.filter(v => v > 0).length;
  const n = d.n;
  const sh = counts => (counts || []).map((c, k) => n[k] ? c / n[k] : 0);
  const lanes = [];
  for (const name of ["ALARM", "DEGRADED", "ZEROING"])
    if (d.counts[`health:${name}`]) lanes.push({ label: name, share: sh(d.counts[`health:${name}`]) });
  lanes.push({ label: "output disabled", share: sh(d.counts.disabled) });
  for (const name of d.flag_names || []) lanes.push({ label: name, share: sh(d.counts[`flag:${name}`]) });
  for (const s of d.sensors || []) {
    const share = sh(d.counts[`sensor:${s}`]);
    if (bucketsWith(share)) lanes.push({ label: `${s} not OK`, share });
  }
  lanes.forEach(l => { l.colour = HELD_COLOURS[l.label] || "#c00"; });
  const first = d.t.length ? d.t[0] : null;
  state.drift = {
    window_s: d.window_s, bucket_s: d.bucket_s, points: d.t.length, frames: d.frames,
    complete: d.complete, t_end: d.t_end,
    span_s: d.t.length ? d.t[d.t.length - 1] + d.bucket_s - first : 0,
    lanes: Object.fromEntries(lanes.map(l => [l.label, bucketsWith(l.share)])),
    temperatures: [], drawn: 0,
  };
  if (!d.t.length) {
    $("drift-note").textContent = "no logged frames in this window yet";
    return;
  }
  AXES.forEach((a, j) => {
    const c = d.series[`corr_${a}_um`], p = d.series[`dev_${a}_um`];
    const neg = arr => arr.map(v => v === null ? null : -v);
    drawDrift($(`drift-${a}`), d, [
      { name: "applied correction", colour: COLOURS[j], mean: c.mean, min: c.min, max: c.max },
      { name: "model's correction (−predicted)", colour: "#000000", mean: neg(p.mean),
        min: neg(p.max), max: neg(p.min), dash: true }], "µm");
  });
  const probes = d.ambient && d.ambient.length ? d.ambient : d.probes;
  state.drift.temperatures = probes;
  $("drift-temperature-caption").textContent = d.ambient && d.ambient.length
    ? `Ambient temperature ${d.ambient.join(", ")} (°C)` : "Temperatures, every probe (no ambient probe named) (°C)";
  drawDrift($("drift-temperature"), d, probes.map((name, i) => {
    const s = d.series[`${name}_C`];
    return { name, colour: COLOURS[(i + 4) % COLOURS.length], mean: s.mean, min: s.min, max: s.max };
  }), "T (°C)");
  drawHeld($("drift-held"), d, lanes);
  state.drift.drawn += 1;
  $("drift-note").textContent = `${spanText(d.window_s)} window · ${d.t.length} buckets of ${spanText(+d.bucket_s.toFixed(3))}`
    + ` · ${d.frames.toLocaleString("en")} frames` + (d.complete ? "" : " · still reading the log…");
}

let driftTimer = null, driftWindow = 3600, driftAsked = 0;
async function loadDrift() {
  clearTimeout(driftTimer);
  const asked = ++driftAsked, windowS = driftWindow;
  const r = await api(`/api/history?window_s=${windowS}&points=600`);
  if (asked !== driftAsked) return;              // another window was chosen meanwhile
  let next = 5000;
  if (r.ok && r.data) {
    showDrift(r.data);
    next = r.data.complete ? 1000 * Math.min(Math.max(r.data.bucket_s, 2), 30) : 300;
  } else {
    $("drift-note").textContent = (r.data && r.data.error) || `history unavailable (${r.status})`;
  }
  driftTimer = setTimeout(loadDrift, next);
}

function setWindow(seconds) {
  driftWindow = seconds;
  for (const b of $("windows").children) b.setAttribute("aria-pressed", String(+b.dataset.windowS === seconds));
  return loadDrift();
}

function startDrift(meta) {
  if (!meta.history) return;
  $("drift").hidden = false;
  const box = $("windows");
  box.textContent = "";
  for (const s of meta.windows_s) {
    const b = document.createElement("button");
    b.type = "button"; b.dataset.windowS = s; b.textContent = spanText(s);
    b.addEventListener("click", () => setWindow(s));
    box.appendChild(b);
  }
  const wanted = +new URLSearchParams(location.search).get("window_s");
  setWindow(meta.windows_s.includes(wanted) ? wanted : 3600);
}

// -------------------------------------------------------------------------- page state
const state = { meta: null, charts: {}, updates: 0, last: null, times: [], user: null,
                enabledVersion: -1, started: false };
window.fbgcomp = state;              // for the browser tests and curious engineers
state.setWindow = seconds => setWindow(seconds);

const $ = id => document.getElementById(id);

async function api(path, body) {
  const opts = body === undefined ? {} : {
    method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body),
    credentials: "same-origin" };
  const r = await fetch(path, opts);
  let data = null;
  try { data = await r.json(); } catch (e) { data = null; }
  return { ok: r.ok, status: r.status, data };
}

function buildSensorTable(names) {
  const body = $("sensors").tBodies[0];
  body.textContent = "";
  names.forEach((name, i) => {
    const tr = document.createElement("tr");
    tr.dataset.sensor = name;
    for (const cls of ["name", "status", "num wl", "num dl"]) {
      const td = document.createElement("td"); td.className = cls; tr.appendChild(td);
    }
    tr.cells[0].textContent = name;
    tr.cells[0].style.borderLeft = `6px solid ${COLOURS[i % COLOURS.length]}`;
    body.appendChild(tr);
  });
}

function showUser(user) {
  state.user = user;
  const meta = state.meta || {};
  const mustReadLogin = !!meta.read_login && !user;
  $("login-form").hidden = !!user || !meta.login_possible;
  $("user-line").hidden = !user;
  $("user").textContent = user || "";
  const canControl = !!user && meta.control_available;
  $("toggle").disabled = !canControl;
  $("control-note").textContent = mustReadLogin
    ? "This dashboard is reachable from the network: log in to see the live values."
    : !meta.control_available ? "This service has no control output."
    : user ? "You may enable or disable the compensation."
    : meta.login_possible ? "Log in to enable or disable the compensation."
    : "No dashboard users are configured: control is off.";
  $("access-note").textContent = meta.read_login ? "Login needed to read" : "Read-only without login";
  if (mustReadLogin) { $("link").textContent = "log in"; $("link").dataset.state = "LOGIN"; }
}

function showEnabled(enabled, version) {
  // frames and the answer to a switch arrive in any order: keep the newest state
  if (version !== undefined) {
    if (version < state.enabledVersion) return;
    state.enabledVersion = version;
  }
  const text = enabled ? "ENABLED" : "DISABLED";
  $("enabled-badge").textContent = `output ${text.toLowerCase()}`;
  $("enabled-badge").dataset.state = text;
  $("enabled-text").textContent = text.toLowerCase();
  $("toggle").textContent = enabled ? "disable compensation" : "enable compensation";
  $("toggle").dataset.enabled = enabled ? "true" : "false";
}

function onFrame(f) {
  state.updates += 1;
  state.last = f;
  const now = performance.now();
  state.times.push(now);
  while (state.times.length && state.times[0] < now - 5000) state.times.shift();
  AXES.forEach((a, j) => {
    $(`corr-${a}`).textContent = fmt(f.correction_um[j], 3);
    $(`dev-${a}`).textContent = fmt(f.deviation_um[j], 3);
    $(`hw-${a}`).textContent = fmt(f.half_width_um[j], 3);
    const names = (f.output_flag_names || [])[j] || [];
    $(`flags-${a}`).textContent = names.join(" · ");
    $(`flags-${a}`).title = names.length ? "held back: " + names.join(", ") : "";
  });
  $("limited").hidden = !f.limited;
  $("health").textContent = f.health + (f.alarm ? " · alarm" : "");
  $("health").dataset.state = f.health;
  $("fallback").textContent = f.fallback ? `without ${f.fallback}` : "none (full model)";
  $("model-id").textContent = f.model_id;
  $("source").textContent = f.source_status || "—";
  $("latency").textContent = fmt(f.latency_ms, 1);
  $("processing").textContent = fmt(f.processing_ms, 1);
  $("frames").textContent = f.frames;
  $("rate").textContent = (state.times.length > 1
    ? (state.times.length - 1) / ((state.times[state.times.length - 1] - state.times[0]) / 1000) : 0).toFixed(1);
  showEnabled(f.enabled, f.enabled_version);
  const rows = $("sensors").tBodies[0].rows;
  for (let i = 0; i < rows.length; i++) {
    const st = f.sensor_status[i] || "—";
    rows[i].cells[1].textContent = st;
    rows[i].cells[1].className = st === "OK" ? "status status-OK" : "status status-bad";
    rows[i].cells[2].textContent = fmt(f.wavelength_nm[i], 4);
    rows[i].cells[3].textContent = fmt(f.elongation_um[i], 3);
  }
  state.charts.elongation.push(f.t, f.elongation_um);
  state.charts.temperature.push(f.t, f.temperature_C);
  state.charts.deviation.push(f.t, f.deviation_um);
  state.charts.correction.push(f.t, f.correction_um);
}

let source = null;
function connect() {
  const es = new EventSource("/api/stream");
  source = es;
  es.onopen = () => { $("link").textContent = "live"; $("link").dataset.state = "LIVE"; };
  es.onmessage = ev => onFrame(JSON.parse(ev.data));
  es.onerror = () => {
    $("link").textContent = "reconnecting"; $("link").dataset.state = "LOST";
    // the browser retries by itself after a lost connection, not after an HTTP error
    // (401 once a session has expired, 503 when full): ask the server what to do
    if (es.readyState === EventSource.CLOSED) setTimeout(recheck, 3000);
  };
}

async function recheck() {
  const meta = (await api("/api/meta")).data;
  if (!meta) { setTimeout(recheck, 3000); return; }
  state.meta = Object.assign(state.meta || {}, meta);
  showUser(meta.user);
  if (!(meta.read_login && !meta.user)) connect();
}

function frameLoop() {
  for (const c of Object.values(state.charts)) c.draw();
  requestAnimationFrame(frameLoop);
}

// the page proper: charts, table, stream (once the server lets this browser read)
function start(meta) {
  state.started = true;
  $("max-rate").textContent = meta.max_rate_hz;
  buildSensorTable(meta.sensors);
  state.charts.elongation = new StripChart($("chart-elongation"), meta.sensors, "ΔS (µm)");
  state.charts.temperature = new StripChart($("chart-temperature"), meta.probes, "T (°C)");
  state.charts.deviation = new StripChart($("chart-deviation"), meta.axes, "deviation (µm)");
  state.charts.correction = new StripChart($("chart-correction"), meta.axes, "correction (µm)");
  showEnabled(meta.enabled, meta.enabled_version);
  connect();
  startDrift(meta);
}

async function loadMeta() {
  const meta = (await api("/api/meta")).data || {};
  state.meta = meta;
  showUser(meta.user);
  if (!state.started && !(meta.read_login && !meta.user)) start(meta);
}

async function init() {
  $("login-form").addEventListener("submit", async ev => {
    ev.preventDefault();
    $("control-error").textContent = "";
    const r = await api("/api/login", { username: $("username").value, password: $("password").value });
    $("password").value = "";
    if (!r.ok) $("control-error").textContent = (r.data && r.data.error) || `login failed (${r.status})`;
    else if (!state.started) await loadMeta();   // reads needed this login: the page starts now
    else showUser(r.data.user);
  });
  $("logout").addEventListener("click", async () => {
    await api("/api/logout", {});
    if (state.meta && state.meta.read_login) { location.reload(); return; }   // nothing stays shown
    showUser(null);
  });
  $("toggle").addEventListener("click", async () => {
    $("control-error").textContent = "";
    const want = $("toggle").dataset.enabled !== "true";
    const r = await api("/api/enabled", { enabled: want });
    if (r.ok) showEnabled(r.data.enabled, r.data.enabled_version);
    else {
      $("control-error").textContent = (r.data && r.data.error) || `refused (${r.status})`;
      if (r.status === 401) showUser(null);
    }
  });
  await loadMeta();
  requestAnimationFrame(frameLoop);
}

document.addEventListener("DOMContentLoaded", init);
