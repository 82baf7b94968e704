// spindle-chtc operator dashboard: polls /api/v1 and draws on canvases. Vanilla JS, no build step, no CDN.
// A read token (if the API needs one) can be given once as #token=... in the URL; it stays in sessionStorage.
"use strict";

const API = "/api/v1";
const POLL_MS = { chtc: 1000, sensors: 2000, condition: 5000, health: 5000, field: 10000, idents: 10000 };
const HISTORY_MAX = 900; // samples per channel kept client-side (30 min at 2 s)
const COLORS = ["#58a6ff", "#f78166", "#3fb950", "#d2a8ff", "#e3b341", "#39c5cf", "#ff7b72", "#a5d6ff"];

const state = {
  etag: null, chtc: null, field: null, fieldKey: null, history: new Map(), conditions: [], lastOk: {},
  rendered: { h: false, field: false, sensors: false },
};

const $ = (id) => document.getElementById(id);

function token() {
  const m = location.hash.match(/token=([^&]+)/);
  if (m) sessionStorage.setItem("chtc-token", decodeURIComponent(m[1]));
  return sessionStorage.getItem("chtc-token");
}

async function api(path, { etag } = {}) {
  const headers = {};
  const t = token();
  if (t) headers.Authorization = "Bearer " + t;
  if (etag) headers["If-None-Match"] = etag;
  const res = await fetch(API + path, { headers, cache: "no-store" });
  if (res.status === 304) return { status: 304, headers: res.headers, body: null };
  let body = null;
  try { body = await res.json(); } catch (e) { body = null; }
  return { status: res.status, headers: res.headers, body };
}

function fmt(v, digits = 1) { return v === null || v === undefined ? "–" : Number(v).toFixed(digits); }
function utc(iso) { return iso ? iso.replace("T", " ").replace(/\.\d+/, "").replace("Z", " UTC") : "–"; }
function ageText(s) {
  if (s === null || s === undefined) return "–";
  if (s < 120) return s.toFixed(1) + " s";
  if (s < 7200) return (s / 60).toFixed(1) + " min";
  return (s / 3600).toFixed(1) + " h";
}

function setupCanvas(canvas) {
  const ctx = canvas.getContext("2d");
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  ctx.font = "12px system-ui, sans-serif";
  return ctx;
}

function niceTicks(lo, hi, n = 5) {
  const span = hi - lo || 1;
  const step0 = Math.pow(10, Math.floor(Math.log10(span / n)));
  const step = [1, 2, 5, 10].map((k) => k * step0).find((s) => span / s <= n) || step0 * 10;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9; v += step) out.push(+v.toFixed(10));
  return out;
}

// ---------- status banner ----------
function setStatus(status, text) {
  const pill = $("status");
  pill.className = "pill pill-" + status;
  pill.textContent = text || status;
  const banner = $("banner");
  const c = state.chtc?.condition;
  const msgs = {
    stale: "STALE: no recent data. The H values below are the last identified ones and must not be trusted.",
    "no-data": "NO DATA: the service has no samples yet.",
    error: "API unreachable or failing: values on this page are not being updated.",
    identifying: "IDENTIFYING: the operating condition changed; the H values below are still those of condition " +
      (c ? `#${c.id} (${fmt(c.speed_rpm, 0)} rpm)` : "before the change") + " until the new identification finishes.",
  };
  banner.className = status === "identifying" ? "banner banner-warn" : "banner";
  if (msgs[status]) { banner.hidden = false; banner.textContent = msgs[status]; } else { banner.hidden = true; }
}

// ---------- H1..H7 ----------
function drawH(c) {
  const canvas = $("h-chart");
  const ctx = setupCanvas(canvas);
  const W = canvas.width, H = canvas.height, L = 48, R = 12, T = 14, B = 28;
  const zones = c.zones;
  const hiVal = Math.max(...zones.map((z) => z.ci95_hi_w_m2k ?? z.h_w_m2k ?? 0), 1) * 1.1;
  const y = (v) => T + (H - T - B) * (1 - Math.max(v, 0) / hiVal); // H > 0: a CI reaching below 0 is clipped
  ctx.strokeStyle = "#2b3642"; ctx.fillStyle = "#8b98a5"; ctx.textAlign = "right";
  for (const tv of niceTicks(0, hiVal)) {
    ctx.beginPath(); ctx.moveTo(L, y(tv)); ctx.lineTo(W - R, y(tv)); ctx.stroke();
    ctx.fillText(String(tv), L - 6, y(tv) + 4);
  }
  const slot = (W - L - R) / zones.length;
  zones.forEach((z, i) => {
    const x = L + slot * i + slot * 0.2, w = slot * 0.6;
    if (z.h_w_m2k !== null) {
      ctx.fillStyle = z.identified ? "#58a6ff" : "rgba(210,153,34,0.55)";
      ctx.fillRect(x, y(z.h_w_m2k), w, y(0) - y(z.h_w_m2k));
    }
    if (z.ci95_lo_w_m2k !== null && z.ci95_hi_w_m2k !== null) {
      const cx = x + w / 2;
      ctx.strokeStyle = "#e6edf3"; ctx.lineWidth = 1.5; ctx.beginPath();
      ctx.moveTo(cx, y(z.ci95_lo_w_m2k)); ctx.lineTo(cx, y(z.ci95_hi_w_m2k));
      ctx.moveTo(cx - 6, y(z.ci95_lo_w_m2k)); ctx.lineTo(cx + 6, y(z.ci95_lo_w_m2k));
      ctx.moveTo(cx - 6, y(z.ci95_hi_w_m2k)); ctx.lineTo(cx + 6, y(z.ci95_hi_w_m2k));
      ctx.stroke(); ctx.lineWidth = 1;
    }
    ctx.fillStyle = "#e6edf3"; ctx.textAlign = "center";
    ctx.fillText(z.name, x + w / 2, H - 10);
    if (z.h_w_m2k !== null) ctx.fillText(fmt(z.h_w_m2k), x + w / 2, Math.max(y(z.ci95_hi_w_m2k ?? z.h_w_m2k) - 4, 12));
  });
  const rows = zones.map((z) => `<tr data-zone="${z.name}"><td>${z.name}</td><td id="h-${z.name}">${fmt(z.h_w_m2k, 2)}</td>` +
    `<td>${fmt(z.ci95_lo_w_m2k)} – ${fmt(z.ci95_hi_w_m2k)}</td><td class="${z.identified ? "" : "no"}">` +
    `${z.identified ? "yes" : "no (weakly identifiable)"}</td></tr>`).join("");
  $("h-table").querySelector("tbody").innerHTML = rows;
  $("h-unit").textContent = c.unit;
  $("h-meta").textContent = `identification #${c.identification_id} at ${utc(c.identified_at)} · ${c.method} · ` +
    `RMSE ${fmt(c.rmse_c, 2)} °C · fit ${fmt(c.fit, 3)} · model ${c.model_version} · ` +
    `newest sample ${ageText(c.sample_age_s)} old`;
  state.rendered.h = true;
}

async function pollChtc() {
  try {
    const r = await api("/chtc", { etag: state.etag });
    if (r.status === 304 && state.chtc) {
      // the server's clock may differ from ours (or run faster in a demo): age from its last answer
      const age = state.chtc.sample_age_s === null ? null : state.chtc.sample_age_s + (Date.now() - state.chtcAt) / 1000;
      setStatus(state.chtc.status, `${state.chtc.status} · ${ageText(age)}`);
      return;
    }
    if (r.status === 503) { setStatus("no-data", "waiting for first identification"); return; }
    if (r.status !== 200) { setStatus("error", r.body?.error?.message || "HTTP " + r.status); return; }
    state.etag = r.headers.get("ETag");
    state.chtc = r.body;
    state.chtcAt = Date.now();
    setStatus(r.body.status, `${r.body.status} · ${ageText(r.body.sample_age_s)}`);
    drawH(r.body);
    const key = r.body.identification_id + "|" + $("field-at").value;
    if (key !== state.fieldKey) pollField();
  } catch (e) { setStatus("error", "API unreachable"); }
  markRendered();
}

// ---------- temperature field ----------
const CMAP = [[48, 18, 59], [65, 69, 171], [70, 117, 237], [57, 162, 252], [27, 207, 212], [36, 236, 166],
  [97, 252, 108], [164, 252, 59], [209, 232, 52], [243, 198, 58], [254, 155, 45], [243, 99, 21],
  [217, 56, 6], [177, 25, 1], [122, 4, 3]]; // turbo, 15 stops

function colour(u) {
  const x = Math.min(Math.max(u, 0), 1) * (CMAP.length - 1);
  const i = Math.min(Math.floor(x), CMAP.length - 2), f = x - i;
  const c = CMAP[i].map((v, k) => Math.round(v + f * (CMAP[i + 1][k] - v)));
  return `rgb(${c[0]},${c[1]},${c[2]})`;
}

function drawField(f) {
  const canvas = $("field");
  const ctx = setupCanvas(canvas);
  const W = canvas.width, H = canvas.height, pad = 16, scaleW = 70;
  const r = f.nodes_r_m, z = f.nodes_z_m, T = f.temps_c;
  const zmin = Math.min(...z), zmax = Math.max(...z), rmax = Math.max(...r);
  const s = Math.min((W - 2 * pad - scaleW) / (zmax - zmin), (H - 2 * pad) / (2 * rmax));
  const x0 = pad, yAxis = H / 2;
  state.fieldMap = { x0, yAxis, s, zmin };
  const lo = f.t_min_c, hi = f.t_max_c, span = (hi - lo) || 1;
  for (const sign of [-1, 1]) { // both halves of the axisymmetric section
    for (const [a, b, c] of f.triangles) {
      const tv = (T[a] + T[b] + T[c]) / 3;
      ctx.fillStyle = ctx.strokeStyle = colour((tv - lo) / span);
      ctx.beginPath();
      ctx.moveTo(x0 + (z[a] - zmin) * s, yAxis - sign * r[a] * s);
      ctx.lineTo(x0 + (z[b] - zmin) * s, yAxis - sign * r[b] * s);
      ctx.lineTo(x0 + (z[c] - zmin) * s, yAxis - sign * r[c] * s);
      ctx.closePath(); ctx.fill(); ctx.stroke();
    }
  }
  ctx.setLineDash([6, 4]); ctx.strokeStyle = "#8b98a5"; ctx.beginPath();
  ctx.moveTo(x0 - 6, yAxis); ctx.lineTo(x0 + (zmax - zmin) * s + 6, yAxis); ctx.stroke(); ctx.setLineDash([]);
  for (const sr of state.sensorsNow || []) { // sensor positions, upper half
    ctx.fillStyle = "#fff"; ctx.strokeStyle = "#000"; ctx.beginPath();
    ctx.arc(x0 + (sr.z_m - zmin) * s, yAxis - sr.r_m * s, 2.5, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
  }
  const sx = W - scaleW + 14, sy = pad, sh = H - 2 * pad; // colour scale
  for (let i = 0; i < sh; i++) { ctx.fillStyle = colour(1 - i / sh); ctx.fillRect(sx, sy + i, 14, 1); }
  ctx.fillStyle = "#e6edf3"; ctx.textAlign = "left";
  for (const tv of niceTicks(lo, hi, 6)) ctx.fillText(tv.toFixed(1), sx + 18, sy + sh * (1 - (tv - lo) / span) + 4);
  ctx.fillText("°C", sx - 2, sy + sh + 12);
  ctx.fillStyle = "#8b98a5";
  ctx.fillText(`z: ${zmin.toFixed(2)}–${zmax.toFixed(2)} m, r ≤ ${rmax.toFixed(3)} m`, pad, H - 4);
  $("field-meta").textContent = `${f.at === "now" ? "current" : "steady-state"} field of identification ` +
    `#${f.identification_id} at ${utc(f.t)} · ${fmt(lo)}–${fmt(hi)} °C · ${f.nodes_r_m.length} nodes`;
  state.rendered.field = true;
}

async function pollField() {
  const at = $("field-at").value;
  try {
    const r = await api(`/temperature-field?format=mesh&at=${at}`);
    if (r.status !== 200) { $("field-meta").textContent = r.body?.error?.message || "no field yet"; return; }
    state.field = r.body;
    state.fieldKey = r.body.identification_id + "|" + at;
    drawField(r.body);
  } catch (e) { $("field-meta").textContent = "field unavailable"; }
  markRendered();
}

async function probeField(ev) { // click on the section: T at that (r, z) from the API (format=points)
  const m = state.fieldMap;
  if (!m) return;
  const canvas = $("field"), rect = canvas.getBoundingClientRect();
  const px = (ev.clientX - rect.left) * canvas.width / rect.width;
  const py = (ev.clientY - rect.top) * canvas.height / rect.height;
  const r = Math.abs(m.yAxis - py) / m.s, z = m.zmin + (px - m.x0) / m.s;
  const at = $("field-at").value;
  const res = await api(`/temperature-field?format=points&at=${at}&points=${r.toFixed(5)},${z.toFixed(5)}`);
  const p = res.body?.points?.[0];
  $("field-probe").textContent = !p ? (res.body?.error?.message || "probe failed")
    : `r = ${(p.r_m * 1e3).toFixed(1)} mm, z = ${(p.z_m * 1e3).toFixed(1)} mm: ` +
      (p.inside ? `${fmt(p.temp_c, 2)} °C` : "outside the section");
}

// ---------- measured vs predicted ----------
function chosenChannels() {
  return $("channels").value.split(",").map((s) => parseInt(s, 10)).filter((n) => n >= 1 && n <= 64);
}

function drawSensors() {
  const canvas = $("sensor-chart");
  const ctx = setupCanvas(canvas);
  const W = canvas.width, H = canvas.height, L = 48, R = 250, T = 10, B = 24;
  const chans = chosenChannels().filter((c) => state.history.has(c));
  const all = chans.flatMap((c) => state.history.get(c));
  if (!all.length) { ctx.fillStyle = "#8b98a5"; ctx.fillText("no samples yet", L, H / 2); return; }
  const t1 = Math.max(...all.map((p) => p.t)), t0 = Math.min(...all.map((p) => p.t), t1 - 60e3); // ms
  const vals = all.flatMap((p) => [p.m, p.p]).filter((v) => v !== null);
  let lo = Math.min(...vals), hi = Math.max(...vals);
  if (hi - lo < 1) { lo -= 0.5; hi += 0.5; }
  const x = (t) => L + (W - L - R) * (t - t0) / ((t1 - t0) || 1);
  const y = (v) => T + (H - T - B) * (1 - (v - lo) / (hi - lo));
  ctx.strokeStyle = "#2b3642"; ctx.fillStyle = "#8b98a5"; ctx.textAlign = "right";
  for (const tv of niceTicks(lo, hi)) {
    ctx.beginPath(); ctx.moveTo(L, y(tv)); ctx.lineTo(W - R, y(tv)); ctx.stroke(); ctx.fillText(tv.toFixed(1), L - 6, y(tv) + 4);
  }
  ctx.textAlign = "center";
  ctx.fillText(`${((t1 - t0) / 60e3).toFixed(1)} min window, ending ${new Date(t1).toISOString().slice(11, 19)} UTC`, (L + W - R) / 2, H - 6);
  chans.forEach((c, k) => {
    const pts = state.history.get(c), col = COLORS[k % COLORS.length];
    for (const [key, dash] of [["m", []], ["p", [5, 4]]]) {
      ctx.strokeStyle = col; ctx.setLineDash(dash); ctx.lineWidth = key === "m" ? 1.8 : 1.2; ctx.beginPath();
      let pen = false;
      for (const p of pts) {
        if (p[key] === null) { pen = false; continue; }
        if (pen) ctx.lineTo(x(p.t), y(p[key])); else ctx.moveTo(x(p.t), y(p[key]));
        pen = true;
      }
      ctx.stroke();
    }
    ctx.setLineDash([]); ctx.lineWidth = 1; ctx.fillStyle = col;
    for (const p of pts.slice(-120)) {
      if (p.m !== null) { ctx.beginPath(); ctx.arc(x(p.t), y(p.m), 2, 0, 2 * Math.PI); ctx.fill(); }
    }
    const last = pts[pts.length - 1];
    ctx.fillStyle = col; ctx.textAlign = "left";
    ctx.fillText(`ch ${c} ${last.name.slice(0, 14)}: ${fmt(last.m, 2)} / ${fmt(last.p, 2)}`, W - R + 8, T + 14 + 16 * k);
  });
  ctx.fillStyle = "#8b98a5"; ctx.fillText("— measured / - - predicted, °C", W - R + 8, H - 8);
  state.rendered.sensors = true;
}

async function pollSensors() {
  try {
    const r = await api("/sensors");
    if (r.status !== 200) { $("sensor-meta").textContent = r.body?.error?.message || "HTTP " + r.status; return; }
    state.sensorsNow = r.body.channels;
    for (const s of r.body.channels) {
      const buf = state.history.get(s.channel) || [];
      const t = Date.parse(s.t);
      if (!buf.length || buf[buf.length - 1].t !== t) buf.push({ t, m: s.measured_c, p: s.predicted_c, name: s.name });
      if (buf.length > HISTORY_MAX) buf.shift();
      state.history.set(s.channel, buf);
    }
    const bad = r.body.channels.filter((s) => s.quality !== "ok").map((s) => `${s.channel} (${s.quality})`);
    const res = r.body.channels.map((s) => s.residual_c).filter((v) => v !== null);
    const rms = res.length ? Math.sqrt(res.reduce((a, v) => a + v * v, 0) / res.length) : null;
    $("sensor-meta").textContent = `sample ${utc(r.body.t)} (${ageText(r.body.sample_age_s)} old) · ` +
      `RMS residual ${fmt(rms, 2)} °C over ${res.length} channels` + (bad.length ? ` · masked: ${bad.join(", ")}` : "");
    drawSensors();
  } catch (e) { $("sensor-meta").textContent = "sensors unavailable"; }
  markRendered();
}

// ---------- condition timeline ----------
function drawConditions(current, recent, servedAt) {
  $("condition-now").innerHTML = `<b>${fmt(current.speed_rpm, 0)} rpm</b> · ${fmt(current.torque_nm, 2)} N·m · ` +
    `ambient ${fmt(current.ambient_c, 1)} °C · <span class="${current.state === "stable" ? "" : "no"}">${current.state}</span>` +
    ` <span class="muted">since ${utc(current.since)}</span>`;
  const canvas = $("condition-chart");
  const ctx = setupCanvas(canvas);
  const W = canvas.width, H = canvas.height, L = 48, R = 10, T = 10, B = 22;
  const segs = [...recent].reverse();
  const now = Date.parse(servedAt); // the server's clock, not ours
  const t0 = Math.min(...segs.map((c) => Date.parse(c.since)), now - 600e3);
  const maxS = Math.max(...segs.map((c) => c.speed_rpm), 1000) * 1.15;
  const x = (t) => L + (W - L - R) * (t - t0) / ((now - t0) || 1);
  const y = (v) => T + (H - T - B) * (1 - v / maxS);
  ctx.strokeStyle = "#2b3642"; ctx.fillStyle = "#8b98a5"; ctx.textAlign = "right";
  for (const tv of niceTicks(0, maxS, 3)) { ctx.beginPath(); ctx.moveTo(L, y(tv)); ctx.lineTo(W - R, y(tv)); ctx.stroke(); ctx.fillText(String(tv), L - 6, y(tv) + 4); }
  segs.forEach((c, i) => {
    const a = x(Date.parse(c.since)), b = i + 1 < segs.length ? x(Date.parse(segs[i + 1].since)) : x(now);
    ctx.fillStyle = COLORS[c.id % COLORS.length] + "aa";
    ctx.fillRect(a, y(c.speed_rpm), Math.max(b - a, 1), y(0) - y(c.speed_rpm));
    ctx.fillStyle = "#e6edf3"; ctx.textAlign = "left";
    if (b - a > 50) ctx.fillText(`#${c.id} ${c.speed_rpm.toFixed(0)} rpm`, a + 4, y(c.speed_rpm) + 14);
  });
  ctx.fillStyle = "#8b98a5"; ctx.textAlign = "center";
  ctx.fillText(`speed, rpm · last ${((now - t0) / 60e3).toFixed(0)} min`, (L + W) / 2, H - 6);
}

async function pollCondition() {
  try {
    const r = await api("/condition?limit=20");
    if (r.status === 200) drawConditions(r.body.current, r.body.recent, r.body.served_at);
    else $("condition-now").textContent = r.body?.error?.message || "no condition yet";
  } catch (e) { $("condition-now").textContent = "condition unavailable"; }
}

// ---------- health and identifications ----------
async function pollHealth() {
  try {
    const [h, rd] = await Promise.all([api("/healthz"), api("/readyz")]);
    if (h.status === 200) {
      $("health-table").querySelector("tbody").innerHTML = h.body.devices.map((d) =>
        `<tr><td>${d.name}</td><td class="st-${d.status}">${d.status}</td><td>${d.age_s === null ? "–" : ageText(d.age_s) + " ago"}</td>` +
        `<td class="muted">${Object.entries(d.counters).map(([k, v]) => `${k} ${v}`).join(", ")}${d.message ? " · " + d.message : ""}</td></tr>`).join("");
    }
    $("ready-meta").textContent = rd.status === 200 ? "ready" : "NOT READY: " + (rd.body?.error?.message || rd.status);
  } catch (e) { $("ready-meta").textContent = "health unavailable"; }
}

async function pollIdents() {
  try {
    const r = await api("/identifications?limit=6");
    if (r.status !== 200) return;
    $("ident-table").querySelector("tbody").innerHTML = r.body.items.map((i) =>
      `<tr><td>${i.id}</td><td>${utc(i.finished_at)}</td><td>${fmt(i.condition.speed_rpm, 0)} rpm, ` +
      `${fmt(i.condition.ambient_c, 1)} °C</td><td>${fmt(i.rmse_c, 2)} °C</td><td>${i.method} (${i.outcome})</td></tr>`).join("");
  } catch (e) { /* shown by the other panels */ }
}

function markRendered() {
  if (state.rendered.h && state.rendered.field && state.rendered.sensors) document.body.dataset.rendered = "1";
}

function every(fn, ms) { fn(); setInterval(fn, ms); }

function start() {
  setInterval(() => { // the server's time (its clock can run faster in a demo), else ours
    const t = state.chtc ? Date.parse(state.chtc.served_at) + (Date.now() - state.chtcAt) : Date.now();
    $("clock").textContent = new Date(t).toISOString().slice(0, 19).replace("T", " ") + " UTC";
  }, 1000);
  $("field-at").addEventListener("change", pollField);
  $("field").addEventListener("click", probeField);
  $("channels").addEventListener("change", drawSensors);
  every(pollSensors, POLL_MS.sensors);
  every(pollChtc, POLL_MS.chtc);
  every(pollCondition, POLL_MS.condition);
  every(pollHealth, POLL_MS.health);
  every(pollIdents, POLL_MS.idents);
  setInterval(pollField, POLL_MS.field);
}

start();
