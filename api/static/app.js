// spindle-chtc operator dashboard: polls /api/v1 and draws on canvases. Vanilla JS, no build step, no CDN.
// The first screen is the compensation: the growth to correct, whether it may be applied and what to do when
// not, exactly as /api/v1/compensation serves it (status, usable_for_compensation, reason_code, reason,
// action). The page decides nothing itself and parses no reason text.
// Tokens: a read token (if the API needs one) can be given once as #token=... in the URL, a write token as
// #write-token=... (chtc demo prints such a URL). A fragment is never sent to the server; the page keeps the
// tokens in sessionStorage (this tab only) and removes the fragment from the address bar. The write token for
// "Identify now", "Take baseline" and "Set zero" is otherwise asked for in a dialog.
"use strict";

// An instance hosting several spindles serves each one's page at /spindles/<id>/ and its API under
// /api/v1/spindles/<id> (docs/design/fleet.md); a one-spindle instance serves both at the root.
const SPINDLE_PAGE = location.pathname.match(/^\/spindles\/([A-Za-z][A-Za-z0-9_-]{0,62})\//);
const API = SPINDLE_PAGE ? `/api/v1/spindles/${SPINDLE_PAGE[1]}` : "/api/v1";
const POLL_MS = { chtc: 1000, sensors: 2000, condition: 5000, health: 3000, field: 10000, idents: 10000, growth: 2000, deformed: 5000, hmap: 5000 };
const HISTORY_MAX = 2160; // samples asked for on a (re)load; the page keeps as many as the server does
const COLORS = ["#4c9be8", "#f0883e", "#3fb950", "#c297ff", "#e3b341", "#39c5cf", "#ff7b72", "#a5d6ff"];
const GRID = "#2a333c", AXIS = "#5b6773", TEXT = "#c9d1d9", MUTED = "#8f9ba8";

const state = {
  etag: null, chtc: null, chtcAt: 0, field: null, fieldKey: null, layout: null, sensorsNow: null,
  hist: null, health: null, ready: null, apiError: null, job: null, growth: [], growthNow: null, deformed: null,
  hmap: null, hmapEtag: null, hmapAt: 0, hmapOff: false, hmapHidden: new Set(), clockInfo: null,
  rendered: { h: false, field: false, sensors: false },
};

const $ = (id) => document.getElementById(id);
const esc = (s) => String(s ?? "").replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" })[c]);

function readFragment() { // #token=...&write-token=... -> sessionStorage, then out of the address bar
  const frag = new URLSearchParams(location.hash.slice(1));
  const read = frag.get("token"), write = frag.get("write-token");
  if (read) sessionStorage.setItem("chtc-token", read);
  if (write) sessionStorage.setItem("chtc-write-token", write);
  if (read || write) history.replaceState(null, "", location.pathname + location.search);
}

function token() { return sessionStorage.getItem("chtc-token"); }

async function api(path, { etag, method = "GET", body, bearer } = {}) {
  const headers = {};
  const t = bearer || token();
  if (t) headers.Authorization = "Bearer " + t;
  if (etag) headers["If-None-Match"] = etag;
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const res = await fetch(API + path, {
    method, headers, cache: "no-store", body: body === undefined ? undefined : JSON.stringify(body),
  });
  if (res.status === 304) return { status: 304, headers: res.headers, body: null };
  let data = null;
  try { data = await res.json(); } catch (e) { data = null; }
  return { status: res.status, headers: res.headers, body: data };
}

function fmt(v, digits = 1) { return v === null || v === undefined || Number.isNaN(v) ? "–" : Number(v).toFixed(digits); }
// A bound or value with 3 significant digits, never in e-notation: 0.0123, 1.23, 123, 1230; beyond 10^6 or
// below 10^-3 it says so (a served CI that wide carries no information).
function sig3(v) {
  if (v === null || v === undefined || !Number.isFinite(Number(v))) return "–";
  const x = Number(v), a = Math.abs(x);
  if (a === 0) return "0";
  if (a >= 1e6) return (x < 0 ? "< −" : "> ") + "10⁶";
  if (a < 1e-3) return (x < 0 ? "> −" : "< ") + "0.001";
  const d = Math.max(0, 2 - Math.floor(Math.log10(a)));
  return Number(x.toPrecision(3)).toFixed(d).replace("-", "−");
}
function signed(v, digits = 1) { // +1.2 / −1.2 (a real minus sign)
  if (v === null || v === undefined || !Number.isFinite(Number(v))) return "–";
  const t = Math.abs(Number(v)).toFixed(digits);
  return (Number(t) === 0 ? "" : Number(v) < 0 ? "−" : "+") + t;
}
function timeTitle() { return state.clockInfo?.simulated ? "plant time (simulated), UTC" : "time, UTC"; }
// 3 significant digits, no exponent (service/serve/numbers.py format_sig)
function fmtSig(v, digits = 3) {
  if (v === null || v === undefined || !Number.isFinite(Number(v))) return "–";
  const x = Number(v);
  if (x === 0) return "0";
  const dec = Math.max(0, digits - 1 - Math.floor(Math.log10(Math.abs(x))));
  return x.toFixed(Math.min(dec, 20));
}
// a CI bound of H: "> high" / "< low" beyond the search box (service/serve/numbers.py format_bound)
function fmtBound(v, box) {
  if (v === null || v === undefined || Number.isNaN(Number(v))) return "–";
  const [lo, hi] = box || [0.1, 1e4];
  // a box edge as Python's "{:g}" writes it (the CLI's): 500, not 499.99999999999983
  const g = (x) => String(Number(Number(x).toPrecision(6)));
  if (v > hi) return "> " + g(hi);
  if (v < lo) return "< " + g(lo);
  return fmtSig(v);
}
function utc(iso) { return iso ? iso.replace("T", " ").replace(/\.\d+/, "").replace("Z", " UTC") : "–"; }
function ageText(s) {
  if (s === null || s === undefined) return "–";
  if (s < 120) return s.toFixed(1) + " s";
  if (s < 7200) return (s / 60).toFixed(1) + " min";
  return (s / 3600).toFixed(1) + " h";
}
function pretty(name) { return String(name).replace(/_/g, " "); }
function serverNow() { // the server's clock (a demo runs it faster than ours), else ours
  return state.chtc ? Date.parse(state.chtc.served_at) + (Date.now() - state.chtcAt) : Date.now();
}

// ---------- canvas and axes ----------
function setupCanvas(canvas) {
  const W = Math.max(canvas.clientWidth, 200), H = Number(canvas.dataset.h || 240);
  const dpr = window.devicePixelRatio || 1;
  canvas.style.height = H + "px";
  if (canvas.width !== Math.round(W * dpr) || canvas.height !== Math.round(H * dpr)) {
    canvas.width = Math.round(W * dpr); canvas.height = Math.round(H * dpr);
  }
  const ctx = canvas.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.clearRect(0, 0, W, H);
  ctx.font = "12px system-ui, sans-serif";
  ctx.lineWidth = 1;
  return { ctx, W, H };
}

function placeholder(canvas, text) {
  const { ctx, W, H } = setupCanvas(canvas);
  ctx.fillStyle = MUTED; ctx.textAlign = "center"; ctx.font = "14px system-ui, sans-serif";
  ctx.fillText(text, W / 2, H / 2);
}

function niceTicks(lo, hi, n = 5) {
  const span = hi - lo || 1;
  const step0 = Math.pow(10, Math.floor(Math.log10(span / n)));
  const step = [1, 2, 2.5, 5, 10].map((k) => k * step0).find((s) => span / s <= n) || step0 * 10;
  const out = [];
  for (let v = Math.ceil(lo / step - 1e-9) * step; v <= hi + 1e-9 * span; v += step) out.push(+v.toFixed(10));
  return out;
}

function stepDigits(ticks) { // decimals that tell the ticks apart (2.5 steps need one)
  const step = ticks.length > 1 ? Math.abs(ticks[1] - ticks[0]) : 1;
  for (let d = 0; d < 4; d++) if (Math.abs(step * 10 ** d - Math.round(step * 10 ** d)) < 1e-6) return d;
  return 4;
}

const TIME_STEPS_S = [1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200, 10800, 21600, 43200, 86400];
function timeTicks(t0, t1, n = 7) { // ms since epoch, UTC-aligned steps
  const span = (t1 - t0) / 1000;
  const step = (TIME_STEPS_S.find((s) => span / s <= n) || 86400) * 1000;
  const out = [];
  for (let t = Math.ceil(t0 / step) * step; t <= t1; t += step) out.push(t);
  return { ticks: out, withSeconds: step < 60000 };
}
function hhmm(t, withSeconds) { return new Date(t).toISOString().slice(11, withSeconds ? 19 : 16); }

// A y axis with grid lines, tick labels and a rotated title; the drawn ticks are mirrored in data-* attributes.
function yAxis(canvas, ctx, box, lo, hi, { title, ticks }) {
  const y = (v) => box.T + (box.H - box.T - box.B) * (1 - (v - lo) / ((hi - lo) || 1));
  const tv = ticks || niceTicks(lo, hi);
  const digits = stepDigits(tv);
  ctx.textAlign = "right"; ctx.textBaseline = "middle";
  for (const v of tv) {
    ctx.strokeStyle = GRID; ctx.beginPath(); ctx.moveTo(box.L, y(v)); ctx.lineTo(box.W - box.R, y(v)); ctx.stroke();
    ctx.strokeStyle = AXIS; ctx.beginPath(); ctx.moveTo(box.L - 4, y(v)); ctx.lineTo(box.L, y(v)); ctx.stroke();
    ctx.fillStyle = MUTED; ctx.fillText(v.toFixed(digits), box.L - 7, y(v));
  }
  ctx.strokeStyle = AXIS; ctx.beginPath(); ctx.moveTo(box.L, box.T); ctx.lineTo(box.L, box.H - box.B); ctx.stroke();
  ctx.save(); ctx.translate(13, (box.T + box.H - box.B) / 2); ctx.rotate(-Math.PI / 2);
  ctx.textAlign = "center"; ctx.fillStyle = TEXT; ctx.fillText(title, 0, 0); ctx.restore();
  ctx.textBaseline = "alphabetic";
  canvas.dataset.yTitle = title;
  canvas.dataset.yTicks = tv.map((v) => v.toFixed(digits)).join(" ");
  return y;
}

// A UTC time x axis: tick marks, HH:MM labels, faint vertical grid, title.
function xTimeAxis(canvas, ctx, box, t0, t1, title) {
  const x = (t) => box.L + (box.W - box.L - box.R) * (t - t0) / ((t1 - t0) || 1);
  const { ticks, withSeconds } = timeTicks(t0, t1, Math.max(3, Math.floor((box.W - box.L - box.R) / 90)));
  const yb = box.H - box.B;
  ctx.strokeStyle = AXIS; ctx.beginPath(); ctx.moveTo(box.L, yb); ctx.lineTo(box.W - box.R, yb); ctx.stroke();
  ctx.textAlign = "center"; ctx.fillStyle = MUTED;
  const labels = [];
  for (const t of ticks) {
    ctx.strokeStyle = GRID; ctx.beginPath(); ctx.moveTo(x(t), box.T); ctx.lineTo(x(t), yb); ctx.stroke();
    ctx.strokeStyle = AXIS; ctx.beginPath(); ctx.moveTo(x(t), yb); ctx.lineTo(x(t), yb + 4); ctx.stroke();
    labels.push(hhmm(t, withSeconds)); ctx.fillText(labels[labels.length - 1], x(t), yb + 16);
  }
  ctx.fillStyle = TEXT; ctx.fillText(title, (box.L + box.W - box.R) / 2, box.H - 5);
  canvas.dataset.xTitle = title;
  canvas.dataset.xTicks = labels.join(" ");
  return x;
}

// A log10 y axis (v > 0): grid lines and labels at 1-2-5 steps per decade (fewer when the range is wide).
function logTicks(lo, hi) {
  const out = (mults) => {
    const t = [];
    for (let e = Math.floor(Math.log10(lo)); e <= Math.ceil(Math.log10(hi)); e++) {
      for (const m of mults) { const v = m * 10 ** e; if (v >= lo * (1 - 1e-9) && v <= hi * (1 + 1e-9)) t.push(+v.toPrecision(6)); }
    }
    return t;
  };
  let t = out([1, 2, 5]);
  if (t.length > 9) t = out([1]);
  if (t.length < 3) t = out([1, 1.5, 2, 3, 5, 7]);
  return t;
}

function yLogAxis(canvas, ctx, box, lo, hi, { title }) {
  const a = Math.log10(lo), b = Math.log10(hi);
  const y = (v) => box.T + (box.H - box.T - box.B) * (1 - (Math.log10(Math.max(v, lo * 1e-3)) - a) / ((b - a) || 1));
  const tv = logTicks(lo, hi);
  const label = (v) => (v >= 1 ? String(Math.round(v * 10) / 10) : v.toPrecision(2));
  ctx.textAlign = "right"; ctx.textBaseline = "middle";
  for (const v of tv) {
    ctx.strokeStyle = GRID; ctx.beginPath(); ctx.moveTo(box.L, y(v)); ctx.lineTo(box.W - box.R, y(v)); ctx.stroke();
    ctx.strokeStyle = AXIS; ctx.beginPath(); ctx.moveTo(box.L - 4, y(v)); ctx.lineTo(box.L, y(v)); ctx.stroke();
    ctx.fillStyle = MUTED; ctx.fillText(label(v), box.L - 7, y(v));
  }
  ctx.strokeStyle = AXIS; ctx.beginPath(); ctx.moveTo(box.L, box.T); ctx.lineTo(box.L, box.H - box.B); ctx.stroke();
  ctx.save(); ctx.translate(13, (box.T + box.H - box.B) / 2); ctx.rotate(-Math.PI / 2);
  ctx.textAlign = "center"; ctx.fillStyle = TEXT; ctx.fillText(title, 0, 0); ctx.restore();
  ctx.textBaseline = "alphabetic";
  canvas.dataset.yTitle = title;
  canvas.dataset.yTicks = tv.map(label).join(" ");
  canvas.dataset.yScale = "log";
  return y;
}

// A linear x axis (ticks, labels, faint vertical grid, title), mirrored in data-x-* like the time axis.
function xAxis(canvas, ctx, box, lo, hi, title) {
  const x = (v) => box.L + (box.W - box.L - box.R) * (v - lo) / ((hi - lo) || 1);
  const ticks = niceTicks(lo, hi, Math.max(3, Math.min(8, Math.floor((box.W - box.L - box.R) / 80))));
  const digits = stepDigits(ticks), yb = box.H - box.B;
  ctx.strokeStyle = AXIS; ctx.beginPath(); ctx.moveTo(box.L, yb); ctx.lineTo(box.W - box.R, yb); ctx.stroke();
  ctx.textAlign = "center"; ctx.fillStyle = MUTED;
  for (const v of ticks) {
    ctx.strokeStyle = GRID; ctx.beginPath(); ctx.moveTo(x(v), box.T); ctx.lineTo(x(v), yb); ctx.stroke();
    ctx.strokeStyle = AXIS; ctx.beginPath(); ctx.moveTo(x(v), yb); ctx.lineTo(x(v), yb + 4); ctx.stroke();
    ctx.fillStyle = MUTED; ctx.fillText(v.toFixed(digits), x(v), yb + 16);
  }
  ctx.fillStyle = TEXT; ctx.fillText(title, (box.L + box.W - box.R) / 2, box.H - 5);
  canvas.dataset.xTitle = title;
  canvas.dataset.xTicks = ticks.map((v) => v.toFixed(digits)).join(" ");
  return x;
}

// ---------- banner: the cause, from /healthz, /readyz and /chtc ----------
const DEVICE_CAUSES = {
  modbus: { down: "DAQ unreachable", degraded: "DAQ degraded", what: "temperature DAQ (Modbus)" },
  can: { down: "CAN silent", degraded: "CAN faults", what: "speed/torque sensor (CAN)" },
  db: { down: "Database down", degraded: "Database slow", what: "database" },
  worker: { down: "Identification worker down", degraded: "Identification worker degraded", what: "worker" },
};

// devices judged on a recent window (the event loop's lag, the core's backlog): no "last ok" time to name
// (their "never ok" read as a fault that never cleared, though the log said "recovered")
const NO_LAST_OK = new Set(["event_loop", "core"]);

function deviceCauses(health) {
  const out = [];
  for (const d of health?.devices || []) {
    if (d.status !== "down" && d.status !== "degraded") continue;
    const names = DEVICE_CAUSES[d.name] || { down: `${d.name} down`, degraded: `${d.name} degraded` };
    const known = d.age_s !== null && d.age_s !== undefined;
    const since = known ? `last ok ${ageText(d.age_s)} ago` : NO_LAST_OK.has(d.name) ? "" : "never ok";
    const detail = [d.message, since].filter(Boolean).join("; ");
    // the database down loses nothing (records are buffered): a warning, not an alarm
    const sev = d.status === "down" && d.name !== "db" ? "alarm" : "warn";
    out.push({ sev, title: names[d.status], detail });
  }
  if (health && health.model_loaded === false) out.push({ sev: "alarm", title: "Model not loaded", detail: "the FE/reduced model is still loading or failed" });
  return out;
}

const UNREACHABLE = { title: "API unreachable", detail: "no answer from the service; values on this page are not being updated" };

function apiProblem(r) {
  const msg = r.body?.error?.message || "HTTP " + r.status;
  if (r.status === 401 || r.status === 403) {
    return { title: "Read token needed", detail: `${msg}; open the page as /#token=<read token> (kept in this tab only)` };
  }
  return { title: "API error", detail: `${msg}; values on this page are not being updated` };
}

function banner() {
  const causes = [];
  if (state.apiError) causes.push({ sev: "alarm", ...state.apiError });
  causes.push(...deviceCauses(state.health));
  if (state.ready && !state.ready.ready && (state.ready.reasons || []).length) {
    causes.push({ sev: "alarm", title: "Not ready", detail: state.ready.reasons.join("; ") });
  }
  causes.sort((a, b) => (a.sev === b.sev ? 0 : a.sev === "alarm" ? -1 : 1));
  const el = $("banner");
  if (!causes.length) { el.hidden = true; el.innerHTML = ""; el.className = "banner"; el.dataset.causes = ""; return; }
  el.hidden = false;
  el.className = causes[0].sev === "alarm" ? "banner banner-alarm" : "banner banner-warn";
  el.innerHTML = causes.map((c) => `<span class="cause cause-${c.sev}"><b>${esc(c.title)}</b>${esc(c.detail)}</span>`).join("");
  el.dataset.causes = causes.map((c) => c.title).join("|");
}

// The H card shows the status /chtc serves for H1-H7 (greyed when stale); the page's one status is the
// compensation's (showComp).
function setHStatus(status, text) {
  const stale = Boolean(state.chtc) && (status === "stale" || status === "no-data" || status === "error");
  $("card-h").classList.toggle("is-stale", stale);
  $("h-stale").hidden = !stale;
  $("h-status").textContent = text ? "H: " + text : "";
  banner();
}

// ---------- H1..H7 ----------
function identifiedText(z) {
  if (z.identified) return "yes";
  if (z.prior_dominated) return "no (prior)"; // not seen by the data: the prior's value and band
  return z.at_bound ? "no (at bound)" : "no (weak)";
}

function hTable(zones, desc, box) {
  $("h-table").querySelector("tbody").innerHTML = zones.map((z) =>
    `<tr data-zone="${z.name}"><td><b>${z.name}</b></td><td class="wrap desc">${esc((desc.get(z.name) || "").replace(/<->/g, "↔"))}</td>` +
    `<td class="num" id="h-${z.name}">${fmt(z.h_w_m2k, 2)}</td>` +
    `<td class="num">${fmtBound(z.ci95_lo_w_m2k, box)} – ${fmtBound(z.ci95_hi_w_m2k, box)}</td>` +
    `<td class="${z.identified ? "" : "no"}"${z.prior_dominated ? ' title="the data did not see this H: value and band are the prior\'s"' : ""}>` +
    `${identifiedText(z)}</td></tr>`).join("");
}

function drawH(c) {
  const canvas = $("h-chart");
  const { ctx, W, H } = setupCanvas(canvas);
  const box = { L: 60, R: 10, T: 16, B: 40, W, H };
  const zones = c.zones;
  const hmax = Math.max(...zones.map((z) => z.h_w_m2k ?? 0), 1);
  const cis = zones.map((z) => z.ci95_hi_w_m2k).filter((v) => v !== null && v <= 1.6 * hmax);
  const ticks = niceTicks(0, Math.max(hmax * 1.25, ...cis), 5);
  const top = ticks[ticks.length - 1] < Math.max(hmax * 1.15, ...cis) ? ticks[ticks.length - 1] + (ticks[1] - ticks[0]) : ticks[ticks.length - 1];
  if (top !== ticks[ticks.length - 1]) ticks.push(top);
  const y = yAxis(canvas, ctx, box, 0, top, { title: `H, ${c.unit}`, ticks });
  const slot = (W - box.L - box.R) / zones.length;
  const desc = new Map((state.layout?.zones || []).map((z) => [z.name, z.description]));
  zones.forEach((z, i) => {
    const x = box.L + slot * i + slot * 0.22, w = slot * 0.56, cx = x + w / 2;
    if (z.h_w_m2k !== null) {
      ctx.fillStyle = z.identified ? "#4c9be8" : "rgba(217,162,27,0.6)";
      ctx.fillRect(x, y(Math.min(z.h_w_m2k, top)), w, y(0) - y(Math.min(z.h_w_m2k, top)));
    }
    if (z.ci95_lo_w_m2k !== null && z.ci95_hi_w_m2k !== null) {
      const lo = y(Math.max(z.ci95_lo_w_m2k, 0)), hi = y(Math.min(z.ci95_hi_w_m2k, top));
      ctx.strokeStyle = TEXT; ctx.lineWidth = 1.5; ctx.beginPath();
      ctx.moveTo(cx, lo); ctx.lineTo(cx, hi);
      ctx.moveTo(cx - 6, lo); ctx.lineTo(cx + 6, lo);
      if (z.ci95_hi_w_m2k > top) { ctx.moveTo(cx - 5, hi + 7); ctx.lineTo(cx, hi); ctx.lineTo(cx + 5, hi + 7); } // off scale
      else { ctx.moveTo(cx - 6, hi); ctx.lineTo(cx + 6, hi); }
      ctx.stroke(); ctx.lineWidth = 1;
    }
    ctx.fillStyle = TEXT; ctx.textAlign = "center";
    ctx.font = "600 12px system-ui, sans-serif"; ctx.fillText(z.name, cx, H - box.B + 16);
    ctx.font = "12px system-ui, sans-serif";
    if (z.h_w_m2k !== null) {
      const yl = y(Math.min(z.ci95_hi_w_m2k ?? z.h_w_m2k, top)) - 5;
      ctx.fillStyle = "#fff"; ctx.fillText(fmt(z.h_w_m2k), cx + (z.ci95_hi_w_m2k > top ? 20 : 0), Math.max(yl, 12));
    }
  });
  ctx.fillStyle = MUTED; ctx.textAlign = "center";
  ctx.fillText("zone (see table for the surface)", (box.L + W - box.R) / 2, H - 5);
  canvas.dataset.xTitle = "zone"; canvas.dataset.xTicks = zones.map((z) => z.name).join(" ");
  hTable(zones, desc, c.h_box_w_m2k);
  $("h-unit").textContent = c.unit;
  $("h-meta").textContent = `identification #${c.identification_id} at ${utc(c.identified_at)} · ${c.method} · ` +
    `RMSE ${fmt(c.rmse_c, 2)} °C · fit ${fmt(c.fit, 3)} · condition #${c.condition.id} ` +
    `(${fmt(c.condition.speed_rpm, 0)} rpm) · model ${c.model_version}`;
  state.rendered.h = true;
}

async function pollChtc() {
  try {
    const r = await api("/chtc", { etag: state.etag });
    state.apiError = null;
    if (r.status === 304 && state.chtc) {
      const age = state.chtc.sample_age_s === null ? null : state.chtc.sample_age_s + (Date.now() - state.chtcAt) / 1000;
      setHStatus(state.chtc.status, `${state.chtc.status} · ${ageText(age)}`);
      return;
    }
    if (r.status === 503) {
      setHStatus("waiting", "no identification yet");
      placeholder($("h-chart"), "waiting for the first identification");
      if (!state.field) placeholder($("field"), "the field is shown after the first identification");
      return;
    }
    if (r.status !== 200) { state.apiError = apiProblem(r); setHStatus("error", state.apiError.title); return; }
    state.etag = r.headers.get("ETag");
    state.chtc = r.body;
    state.chtcAt = Date.now();
    setHStatus(r.body.status, `${r.body.status} · ${ageText(r.body.sample_age_s)}`);
    drawH(r.body);
    const key = r.body.identification_id + "|" + $("field-at").value;
    if (key !== state.fieldKey) pollField();
  } catch (e) { state.apiError = UNREACHABLE; setHStatus("error", "API unreachable"); }
  markRendered();
}

// ---------- H versus speed (/chtc/map, speed-map mode only) ----------
function drawHmap(m) {
  const canvas = $("hmap-chart");
  const { ctx, W, H } = setupCanvas(canvas);
  const box = { L: 60, R: 14, T: 18, B: 40, W, H };
  const sp = m.speeds_rpm, log = $("hmap-scale").value === "log";
  const hs = m.zones.flatMap((z) => z.h_w_m2k).filter((v) => v !== null && v > 0);
  if (!sp.length || !hs.length) { placeholder(canvas, "the map has no values"); return; }
  const hmin = Math.min(...hs), hmax = Math.max(...hs);
  let y;
  if (log) {
    y = yLogAxis(canvas, ctx, box, hmin / 1.6, hmax * 1.6, { title: `H, ${m.unit} (log)` });
  } else {
    const ticks = niceTicks(0, hmax * 1.25, 5);
    y = yAxis(canvas, ctx, box, 0, ticks[ticks.length - 1], { title: `H, ${m.unit}`, ticks });
    canvas.dataset.yScale = "linear";
  }
  const x = xAxis(canvas, ctx, box, 0, Math.max(sp[sp.length - 1], 1), "speed, rpm");
  ctx.save(); ctx.beginPath(); ctx.rect(box.L, box.T, W - box.L - box.R, H - box.T - box.B); ctx.clip();
  let bands = 0, curves = 0;
  const shown = (z) => !state.hmapHidden.has(z.name);
  m.zones.forEach((z, i) => { // bands first, under every curve
    if (!shown(z)) return;
    const col = COLORS[i % COLORS.length];
    const ok = sp.map((_, k) => z.ci95_lo_w_m2k[k] !== null && z.ci95_hi_w_m2k[k] !== null);
    if (!ok.every(Boolean)) return;
    ctx.fillStyle = col + "22"; ctx.beginPath();
    sp.forEach((v, k) => (k ? ctx.lineTo(x(v), y(z.ci95_hi_w_m2k[k])) : ctx.moveTo(x(v), y(z.ci95_hi_w_m2k[k]))));
    for (let k = sp.length - 1; k >= 0; k--) ctx.lineTo(x(sp[k]), y(z.ci95_lo_w_m2k[k]));
    ctx.closePath(); ctx.fill(); bands++;
  });
  m.zones.forEach((z, i) => { // solid where identified, dashed where the band is too wide
    if (!shown(z)) return;
    ctx.strokeStyle = COLORS[i % COLORS.length];
    for (let k = 0; k + 1 < sp.length; k++) {
      const a = z.h_w_m2k[k], b = z.h_w_m2k[k + 1];
      if (a === null || b === null) continue;
      const sure = z.identified[k] && z.identified[k + 1];
      ctx.lineWidth = sure ? 2 : 1.3; ctx.setLineDash(sure ? [] : [5, 4]);
      ctx.beginPath(); ctx.moveTo(x(sp[k]), y(a)); ctx.lineTo(x(sp[k + 1]), y(b)); ctx.stroke();
    }
    ctx.setLineDash([]); ctx.lineWidth = 1; curves++;
    const last = z.h_w_m2k[sp.length - 1];
    if (last !== null) { ctx.fillStyle = COLORS[i % COLORS.length]; ctx.textAlign = "right"; ctx.fillText(z.name, W - box.R - 3, y(last) - 4); }
  });
  // the visited speeds: a rug on the speed axis, tick height growing with the seconds of data there
  const yb = H - box.B, dmax = Math.max(...m.visited.map((v) => v.duration_s), 1);
  ctx.strokeStyle = "#e3e8ee"; ctx.lineWidth = 2;
  for (const v of m.visited) {
    const h = 5 + 25 * Math.sqrt(v.duration_s / dmax);
    ctx.beginPath(); ctx.moveTo(x(v.speed_rpm), yb); ctx.lineTo(x(v.speed_rpm), yb - h); ctx.stroke();
  }
  ctx.lineWidth = 1;
  if (m.current_speed_rpm !== null) { // the current speed
    const xc = x(Math.abs(m.current_speed_rpm));
    ctx.strokeStyle = "#ffffff"; ctx.setLineDash([3, 3]); ctx.beginPath(); ctx.moveTo(xc, box.T); ctx.lineTo(xc, yb); ctx.stroke();
    ctx.setLineDash([]); ctx.fillStyle = "#ffffff"; ctx.textAlign = xc > W - 120 ? "right" : "left";
    ctx.fillText(`now ${fmt(m.current_speed_rpm, 0)} rpm`, xc + (xc > W - 120 ? -4 : 4), box.T + 10);
  }
  ctx.restore();
  canvas.dataset.curves = String(curves);
  canvas.dataset.bands = String(bands);
  canvas.dataset.visited = m.visited.map((v) => fmt(v.speed_rpm, 0)).join(" ");
  canvas.dataset.current = m.current_speed_rpm === null ? "" : fmt(m.current_speed_rpm, 0);
  hmapLegend(m);
}

// The zone legend (click a zone to hide or show it); colours set through the CSSOM (the CSP forbids inline
// style attributes).
function hmapLegend(m) {
  const el = $("hmap-legend");
  el.innerHTML = m.zones.map((z) =>
    `<span class="hz${state.hmapHidden.has(z.name) ? " off" : ""}" data-zone="${esc(z.name)}" title="click to hide or show">` +
    `<i class="sw"></i>${esc(z.name)}</span>`).join(" ") +
    ` <i class="sw sw-rug"></i>data at the speed (tick height: seconds) · click a zone to hide or show it`;
  el.querySelectorAll(".hz .sw").forEach((sw, i) => { sw.style.backgroundColor = COLORS[i % COLORS.length]; });
}

function toggleHmapZone(ev) {
  const item = ev.target.closest(".hz");
  if (!item || !state.hmap) return;
  const name = item.dataset.zone;
  if (state.hmapHidden.has(name)) state.hmapHidden.delete(name); else state.hmapHidden.add(name);
  drawHmap(state.hmap);
}

function showHmap(m) {
  const pill = $("hmap-status");
  const age = m.sample_age_s === null ? null : m.sample_age_s + (Date.now() - state.hmapAt) / 1000;
  pill.className = "pill pill-" + m.status;
  pill.textContent = m.status;
  pill.title = m.reason || "the map is current at the current speed";
  $("hmap-meta").textContent = `map fitted at ${utc(m.fitted_at)} (window end)` +
    (m.identification_id === null ? "" : ` · identification #${m.identification_id}`) +
    ` · family ${m.family} · RMSE ${fmt(m.rmse_c, 3)} °C · evaluated at Ti ${fmt(m.ambient_c, 1)} °C` +
    ` · newest sample ${ageText(age)} old` + (m.restored ? " · restored, not re-fitted since the restart" : "") +
    (m.reason ? ` · ${m.reason}` : "");
  const total = m.visited.reduce((a, v) => a + v.duration_s, 0);
  $("hmap-visited").textContent = m.visited.length
    ? `speeds the data covered (± ${fmt(m.visited_margin_rpm, 0)} rpm counts as covered): ` +
      m.visited.map((v) => `${fmt(v.speed_rpm, 0)} rpm ${ageText(v.duration_s)}`).join(" · ") +
      ` · ${ageText(total)} in all (decayed with the map's forgetting)`
    : "no speed covered by fitted data yet";
}

async function pollHmap() {
  if (state.hmapOff) return;
  try {
    const r = await api("/chtc/map", { etag: state.hmapEtag });
    const card = $("card-hmap");
    if (r.status === 404) { // per-condition mode (fixed for the service's life): no map, no card
      state.hmapOff = true; state.hmap = null; card.hidden = true; card.dataset.mode = "per_condition";
      return;
    }
    card.dataset.mode = "speed_map";
    card.hidden = false;
    if (r.status === 304 && state.hmap) { showHmap(state.hmap); return; }
    if (r.status === 503) {
      state.hmap = null; state.hmapEtag = null;
      $("hmap-status").className = "pill pill-waiting"; $("hmap-status").textContent = "no map yet";
      placeholder($("hmap-chart"), "waiting for the first map fit");
      $("hmap-meta").textContent = r.body?.error?.message || "no speed map fitted yet";
      $("hmap-visited").textContent = "";
      return;
    }
    if (r.status !== 200) { $("hmap-meta").textContent = r.body?.error?.message || "HTTP " + r.status; return; }
    state.hmap = r.body; state.hmapEtag = r.headers.get("ETag"); state.hmapAt = Date.now();
    drawHmap(r.body);
    showHmap(r.body);
  } catch (e) { $("hmap-meta").textContent = "map unavailable"; }
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

// Labels of the named parts: inside the part (lower half) when the name fits, else in rows above the section
// with a leader line to the part (upper half). Returns the names drawn.
function labelParts(ctx, parts, m, topY) {
  const drawn = [], rows = [[], [], [], []], rowH = 14;
  const rect = (p, sign) => {
    const xa = m.x0 + (p.z0_m - m.zmin) * m.s, xb = m.x0 + (p.z1_m - m.zmin) * m.s;
    const ya = m.yAxis - sign * p.r0_m * m.s, yb = m.yAxis - sign * p.r1_m * m.s;
    return { x: Math.min(xa, xb), y: Math.min(ya, yb), w: Math.abs(xb - xa), h: Math.abs(yb - ya) };
  };
  ctx.font = "11px system-ui, sans-serif";
  const leader = [];
  for (const p of parts) {
    const text = pretty(p.name), tw = ctx.measureText(text).width;
    const lo = rect(p, -1);
    if (lo.w >= tw + 8 && lo.h >= 15) {
      ctx.fillStyle = "rgba(10,12,15,0.55)"; ctx.fillRect(lo.x + lo.w / 2 - tw / 2 - 3, lo.y + lo.h / 2 - 8, tw + 6, 15);
      ctx.fillStyle = "#fff"; ctx.textAlign = "center"; ctx.fillText(text, lo.x + lo.w / 2, lo.y + lo.h / 2 + 4);
      drawn.push(p.name);
    } else {
      const up = rect(p, 1);
      leader.push({ text, tw, tx: up.x + up.w / 2, ty: up.y, name: p.name });
    }
  }
  leader.sort((a, b) => a.tx - b.tx);
  for (const l of leader) { // the row where the label moves least
    let best = null;
    rows.forEach((row, k) => {
      const end = row.length ? row[row.length - 1] : -Infinity;
      const x = Math.max(l.tx - l.tw / 2, end + 8);
      const cost = Math.abs(x + l.tw / 2 - l.tx) + k * 6;
      if (best === null || cost < best.cost) best = { k, x, cost };
    });
    rows[best.k].push(best.x + l.tw);
    const ly = topY - 4 - (rows.length - 1 - best.k) * rowH;
    ctx.strokeStyle = "rgba(201,209,217,0.55)"; ctx.beginPath();
    ctx.moveTo(best.x + l.tw / 2, ly + 3); ctx.lineTo(l.tx, l.ty - 1); ctx.stroke();
    ctx.fillStyle = TEXT; ctx.textAlign = "left"; ctx.fillText(l.text, best.x, ly);
    drawn.push(l.name);
  }
  ctx.font = "12px system-ui, sans-serif";
  return drawn;
}

function drawMesh(ctx, f, m, lo, span, T) {
  const r = f.nodes_r_m, z = f.nodes_z_m;
  const px = (i) => m.x0 + (z[i] - m.zmin) * m.s;
  for (const sign of [-1, 1]) { // both halves of the axisymmetric section
    const py = (i) => m.yAxis - sign * r[i] * m.s;
    for (const [a, b, c] of f.triangles) {
      ctx.fillStyle = ctx.strokeStyle = colour(((T[a] + T[b] + T[c]) / 3 - lo) / span);
      ctx.beginPath(); ctx.moveTo(px(a), py(a)); ctx.lineTo(px(b), py(b)); ctx.lineTo(px(c), py(c));
      ctx.closePath(); ctx.fill(); ctx.stroke();
    }
  }
}

function drawOutlines(ctx, parts, m, zLen) {
  ctx.strokeStyle = "rgba(10,12,15,0.45)";
  for (const p of parts) for (const sign of [-1, 1]) {
    const ya = m.yAxis - sign * p.r0_m * m.s, yb = m.yAxis - sign * p.r1_m * m.s;
    ctx.strokeRect(m.x0 + (p.z0_m - m.zmin) * m.s, Math.min(ya, yb), (p.z1_m - p.z0_m) * m.s, Math.abs(yb - ya));
  }
  ctx.setLineDash([8, 3, 2, 3]); ctx.strokeStyle = MUTED; ctx.beginPath(); // axis of rotation
  ctx.moveTo(m.x0 - 6, m.yAxis); ctx.lineTo(m.x0 + zLen * m.s + 6, m.yAxis); ctx.stroke(); ctx.setLineDash([]);
  for (const sr of state.sensorsNow || []) { // sensor positions, upper half
    ctx.fillStyle = sr.quality === "ok" ? "#fff" : "#e5484d"; ctx.strokeStyle = "#000"; ctx.beginPath();
    ctx.arc(m.x0 + (sr.z_m - m.zmin) * m.s, m.yAxis - sr.r_m * m.s, 2.5, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
  }
}

// z along the bottom and r (mirrored) on the left, both in mm; mirrored in data-* like the other charts.
function drawSectionAxes(canvas, ctx, m, zmax, rmax, H) {
  const zLen = zmax - m.zmin, yb = m.yAxis + rmax * m.s + 4, x0 = m.x0;
  ctx.strokeStyle = AXIS; ctx.beginPath(); ctx.moveTo(x0, yb); ctx.lineTo(x0 + zLen * m.s, yb); ctx.stroke();
  ctx.fillStyle = MUTED; ctx.textAlign = "center";
  const zt = niceTicks(m.zmin * 1e3, zmax * 1e3, 8);
  for (const v of zt) {
    const px = x0 + (v / 1e3 - m.zmin) * m.s;
    ctx.beginPath(); ctx.moveTo(px, yb); ctx.lineTo(px, yb + 4); ctx.stroke(); ctx.fillText(v.toFixed(0), px, yb + 16);
  }
  const zTitle = "z, mm (0 = rear, pulley end → front, tool end)";
  ctx.fillStyle = TEXT; ctx.fillText(zTitle, x0 + zLen * m.s / 2, H - 5);
  const rt = niceTicks(0, rmax * 1e3, 2);
  ctx.textAlign = "right"; ctx.textBaseline = "middle"; ctx.fillStyle = MUTED;
  ctx.beginPath(); ctx.moveTo(x0 - 6, m.yAxis - rmax * m.s); ctx.lineTo(x0 - 6, m.yAxis + rmax * m.s); ctx.stroke();
  for (const v of rt) for (const sign of v === 0 ? [1] : [-1, 1]) {
    const py = m.yAxis - sign * v / 1e3 * m.s;
    ctx.beginPath(); ctx.moveTo(x0 - 10, py); ctx.lineTo(x0 - 6, py); ctx.stroke(); ctx.fillText(v.toFixed(0), x0 - 12, py);
  }
  ctx.textBaseline = "alphabetic";
  ctx.save(); ctx.translate(12, m.yAxis); ctx.rotate(-Math.PI / 2); ctx.textAlign = "center"; ctx.fillStyle = TEXT;
  ctx.fillText("r, mm", 0, 0); ctx.restore();
  canvas.dataset.xTitle = zTitle; canvas.dataset.xTicks = zt.map((v) => v.toFixed(0)).join(" ");
  canvas.dataset.yTitle = "r, mm"; canvas.dataset.yTicks = rt.map((v) => v.toFixed(0)).join(" ");
}

function drawColourScale(canvas, ctx, x, y, h, lo, hi, title = "T, °C") {
  const span = (hi - lo) || 1;
  for (let i = 0; i < h; i++) { ctx.fillStyle = colour(1 - i / h); ctx.fillRect(x, y + i, 14, 1); }
  ctx.strokeStyle = AXIS; ctx.strokeRect(x, y, 14, h);
  ctx.textAlign = "left"; ctx.textBaseline = "middle";
  const ticks = niceTicks(lo, hi, 6);
  for (const tv of ticks) {
    const py = y + h * (1 - (tv - lo) / span);
    ctx.fillStyle = AXIS; ctx.fillRect(x + 14, py, 4, 1); ctx.fillStyle = MUTED; ctx.fillText(tv.toFixed(stepDigits(ticks)), x + 20, py);
  }
  ctx.textBaseline = "alphabetic"; ctx.fillStyle = TEXT; ctx.fillText(title, x - 4, y - 8);
  canvas.dataset.cTitle = title; canvas.dataset.cTicks = ticks.map((v) => v.toFixed(stepDigits(ticks))).join(" ");
}

function drawField(f) {
  const canvas = $("field");
  const zmin = Math.min(...f.nodes_z_m), zmax = Math.max(...f.nodes_z_m), rmax = Math.max(...f.nodes_r_m);
  const L = 52, R = 86, top = 72, bottom = 42; // label rows above, z axis below, colour scale right
  const sw = (Math.max(canvas.clientWidth, 200) - L - R) / (zmax - zmin); // height follows the section's aspect
  canvas.dataset.h = String(Math.round(Math.min(Math.max(top + bottom + 2 * rmax * sw, 240), 480)));
  const { ctx, W, H } = setupCanvas(canvas);
  const s = Math.min((W - L - R) / (zmax - zmin), (H - top - bottom) / (2 * rmax));
  const m = { x0: L, yAxis: top + rmax * s, s, zmin };
  state.fieldMap = m;
  // colour: the temperature, or its 1σ (the filtered state's uncertainty; at=now only)
  const sigma = $("field-show").value === "std" && Array.isArray(f.std_c);
  const lo = sigma ? 0 : f.t_min_c, hi = sigma ? f.std_max_c : f.t_max_c;
  drawMesh(ctx, f, m, lo, (hi - lo) || 1, sigma ? f.std_c : f.temps_c);
  const parts = state.layout?.parts || [];
  drawOutlines(ctx, parts, m, zmax - zmin);
  canvas.dataset.parts = labelParts(ctx, parts, m, top - 6).join(" ");
  drawSectionAxes(canvas, ctx, m, zmax, rmax, H);
  drawColourScale(canvas, ctx, W - R + 22, top, H - top - bottom, lo, hi, sigma ? "1σ, °C" : "T, °C");
  ctx.fillStyle = MUTED; ctx.textAlign = "left";
  ctx.fillText("● sensor", W - R + 8, H - 26);
  const unc = f.std_max_c == null ? (f.at === "steady" ? " · no uncertainty for the steady state" : "")
    : ` · 1σ up to ${fmt(f.std_max_c, 2)} °C`;
  $("field-meta").textContent = `${f.at === "now" ? "current (filtered state estimate)" : "steady-state"} field of identification ` +
    `#${f.identification_id} at ${utc(f.t)} · ${fmt(f.t_min_c)}–${fmt(f.t_max_c)} °C${unc} · ${f.nodes_r_m.length} nodes · ` +
    `${sigma ? "coloured by its 1σ · " : ""}shown mirrored about the axis; sensors in the upper half (red = masked)`;
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

function hoverField(ev) { // the sensor under the pointer, as the canvas's tooltip
  const m = state.fieldMap, canvas = $("field");
  if (!m) return;
  const rect = canvas.getBoundingClientRect(), px = ev.clientX - rect.left, py = ev.clientY - rect.top;
  const near = (state.sensorsNow || []).find((s) =>
    Math.hypot(m.x0 + (s.z_m - m.zmin) * m.s - px, m.yAxis - s.r_m * m.s - py) <= 6);
  canvas.title = near ? `ch ${near.channel} ${near.name} (${near.role}): measured ${fmt(near.measured_c, 2)} °C, ` +
    `predicted ${fmt(near.predicted_c, 2)} ± ${fmt(near.predicted_sd_c, 2)} °C (1σ), ${near.quality}` : "";
}

function partAt(rm, zm) {
  const p = (state.layout?.parts || []).find((q) => rm >= q.r0_m && rm <= q.r1_m && zm >= q.z0_m && zm <= q.z1_m);
  return p ? pretty(p.name) : null;
}

async function probeField(ev) { // click on the section: T at that (r, z) from the API (format=points)
  const m = state.fieldMap;
  if (!m) return;
  const rect = $("field").getBoundingClientRect();
  const px = ev.clientX - rect.left, py = ev.clientY - rect.top;
  const r = Math.abs(m.yAxis - py) / m.s, z = m.zmin + (px - m.x0) / m.s;
  const at = $("field-at").value;
  const res = await api(`/temperature-field?format=points&at=${at}&points=${r.toFixed(5)},${z.toFixed(5)}`);
  const p = res.body?.points?.[0];
  const part = p ? partAt(p.r_m, p.z_m) : null;
  $("field-probe").textContent = !p ? (res.body?.error?.message || "probe failed")
    : `r = ${(p.r_m * 1e3).toFixed(1)} mm, z = ${(p.z_m * 1e3).toFixed(1)} mm` + (part ? ` (${part})` : "") + ": " +
      (p.inside ? `${fmt(p.temp_c, 2)} °C` + (p.std_c == null ? "" : ` ± ${fmt(p.std_c, 2)} °C (1σ; 95 %: ${fmt(p.ci95_c[0], 2)}–${fmt(p.ci95_c[1], 2)} °C)`)
        : "outside the section");
}

async function loadLayout() {
  try {
    const r = await api("/spindle");
    if (r.status !== 200) return;
    state.layout = r.body;
    $("spindle-id").textContent = r.body.spindle_id || "";
    $("spindle-name").textContent = `${r.body.name} · convective heat transfer coefficients H1–H7`;
    if (state.chtc) drawH(state.chtc);
    if (state.field) drawField(state.field);
  } catch (e) { /* retried on the next field poll */ }
}

// ---------- measured vs predicted (server-side history) ----------
function chosenChannels() {
  return [...new Set($("channels").value.split(",").map((s) => parseInt(s, 10)).filter((n) => n >= 1 && n <= 64))];
}

async function loadHistory() {
  const chans = chosenChannels();
  if (!chans.length) return;
  const key = chans.join(",");
  const fresh = !state.hist || state.hist.key !== key;
  const q = `channels=${key}&limit=${HISTORY_MAX}` + (fresh ? "" : `&since=${encodeURIComponent(state.hist.lastIso)}`);
  const r = await api(`/sensors/history?${q}`);
  if (r.status !== 200) {
    $("sensor-meta").textContent = "history: " + (r.body?.error?.message || "HTTP " + r.status);
    return;
  }
  const b = r.body;
  if (fresh) state.hist = { key, t: [], series: new Map(), lastIso: null, capacity: b.capacity };
  const h = state.hist;
  for (const c of b.channels) if (!h.series.has(c.channel)) h.series.set(c.channel, { name: c.name, role: c.role, m: [], p: [] });
  b.t.forEach((iso, i) => {
    h.t.push(Date.parse(iso));
    for (const c of b.channels) { const s = h.series.get(c.channel); s.m.push(c.measured_c[i]); s.p.push(c.predicted_c[i]); }
  });
  if (b.t.length) h.lastIso = b.t[b.t.length - 1];
  const extra = h.t.length - Math.max(h.capacity || 0, HISTORY_MAX);
  if (extra > 0) { h.t.splice(0, extra); for (const s of h.series.values()) { s.m.splice(0, extra); s.p.splice(0, extra); } }
}

function drawSensors() {
  const canvas = $("sensor-chart");
  const { ctx, W, H } = setupCanvas(canvas);
  const box = { L: 60, R: 14, T: 12, B: 40, W, H };
  const h = state.hist;
  canvas.dataset.points = h ? String(h.t.length) : "0";
  if (!h || !h.t.length) { ctx.fillStyle = MUTED; ctx.fillText("no samples yet", box.L + 10, H / 2); return; }
  const win = Number($("window").value) * 1000;
  const t1 = h.t[h.t.length - 1], t0 = Math.min(Math.max(h.t[0], t1 - win), t1 - 60e3);
  const first = h.t.findIndex((t) => t >= t0);
  const chans = [...h.series.keys()];
  const vals = chans.flatMap((c) => [...h.series.get(c).m.slice(first), ...h.series.get(c).p.slice(first)]).filter((v) => v !== null);
  let lo = Math.min(...vals), hi = Math.max(...vals);
  if (!vals.length) { lo = 0; hi = 1; }
  const pad = Math.max((hi - lo) * 0.06, 0.25); lo -= pad; hi += pad;
  const y = yAxis(canvas, ctx, box, lo, hi, { title: "temperature, °C" });
  const x = xTimeAxis(canvas, ctx, box, t0, t1, timeTitle());
  ctx.save(); ctx.beginPath(); ctx.rect(box.L, box.T, W - box.L - box.R, H - box.T - box.B); ctx.clip();
  chans.forEach((c, k) => {
    const s = h.series.get(c), col = COLORS[k % COLORS.length];
    for (const [key, dash, lw] of [["p", [6, 4], 1.4], ["m", [], 2]]) {
      ctx.strokeStyle = col; ctx.setLineDash(dash); ctx.lineWidth = lw; ctx.beginPath();
      let pen = false;
      for (let i = first; i < h.t.length; i++) {
        const v = s[key][i];
        if (v === null) { pen = false; continue; }
        if (pen) ctx.lineTo(x(h.t[i]), y(v)); else ctx.moveTo(x(h.t[i]), y(v));
        pen = true;
      }
      ctx.stroke();
    }
  });
  ctx.restore(); ctx.setLineDash([]); ctx.lineWidth = 1;
  drawLegend(chans);
  state.rendered.sensors = true;
}

function drawLegend(chans) {
  const now = new Map((state.sensorsNow || []).map((s) => [s.channel, s]));
  $("sensor-legend").querySelector("tbody").innerHTML = chans.map((c, k) => {
    const s = state.hist.series.get(c), n = now.get(c) || {};
    const q = n.quality || "–";
    return `<tr data-channel="${c}"><td><span class="line" data-k="${k}"></span></td>` +
      `<td>${c}</td><td class="sensor-name">${esc(s.name)}</td><td>${esc(s.role)}</td>` +
      `<td class="num">${fmt(n.measured_c, 2)} °C</td><td class="num">${fmt(n.predicted_c, 2)} ± ${fmt(n.predicted_sd_c, 2)} °C</td>` +
      `<td class="num">${fmt(n.residual_c, 2)} °C</td>` +
      `<td class="num" title="${n.offset_c == null ? "no baseline: offset unknown" : "1σ " + fmt(n.offset_sd_c, 3) + " °C"}">${fmt(n.offset_c, 2)} °C</td>` +
      `<td class="${q === "ok" ? "" : "bad"}">${esc(q)}</td></tr>`;
  }).join("");
  // the page's CSP forbids inline style attributes; CSSOM is allowed
  for (const el of $("sensor-legend").querySelectorAll(".line")) el.style.borderColor = COLORS[Number(el.dataset.k) % COLORS.length];
}

async function pollSensors() {
  try {
    const [r] = await Promise.all([api("/sensors"), loadHistory()]);
    if (r.status !== 200) { $("sensor-meta").textContent = r.body?.error?.message || "HTTP " + r.status; drawSensors(); return; }
    state.sensorsNow = r.body.channels;
    const bad = r.body.channels.filter((s) => s.quality !== "ok").map((s) => `${s.channel} (${s.quality})`);
    const res = r.body.channels.map((s) => s.residual_c).filter((v) => v !== null);
    const rms = res.length ? Math.sqrt(res.reduce((a, v) => a + v * v, 0) / res.length) : null;
    const n = state.hist ? state.hist.t.length : 0;
    $("sensor-meta").textContent = `newest sample ${utc(r.body.t)} (${ageText(r.body.sample_age_s)} old) · ` +
      `RMS residual ${fmt(rms, 2)} °C over ${res.length} channels · ${n} samples from the server's history` +
      (bad.length ? ` · masked: ${bad.join(", ")}` : "");
    showBaseline(r.body.channels);
    drawSensors();
  } catch (e) { $("sensor-meta").textContent = "sensors unavailable"; }
  markRendered();
}

// ---------- sensor offset baseline ----------
function showBaseline(channels) {
  const cal = channels.find((s) => s.offset_source);
  const el = $("baseline-meta");
  if (!cal) {
    const sd = channels.map((s) => s.offset_sd_c).find((v) => v !== null && v !== undefined);
    el.textContent = "no offset baseline: sensor offsets unknown" +
      (sd === undefined ? "" : ` (carried in the CIs as 1σ ${fmt(sd, 2)} °C)`) +
      "; one is taken when the spindle rests at the ambient";
    el.className = "no";
    return;
  }
  const offs = channels.map((s) => s.offset_c).filter((v) => v !== null && v !== undefined);
  const range = offs.length ? `${fmt(Math.min(...offs), 2)}..${fmt(Math.max(...offs), 2)} °C` : "–";
  el.textContent = `offset baseline: ${cal.offset_source}, at rest until ${utc(cal.offset_calibrated_at)} · ` +
    `offsets ${range} over ${offs.length} channels (subtracted before the fit)`;
  el.className = "";
}

function openBaseline() {
  $("baseline-token").value = sessionStorage.getItem("chtc-write-token") || "";
  $("baseline-dialog").showModal();
  ($("baseline-token").value ? $("baseline-submit") : $("baseline-token")).focus();
}

async function submitBaseline(ev) {
  ev.preventDefault();
  const tok = $("baseline-token").value.trim();
  if (!tok) { $("baseline-token").focus(); return; }
  sessionStorage.setItem("chtc-write-token", tok);
  $("baseline-dialog").close();
  const out = $("baseline-result");
  $("baseline-now").disabled = true;
  try {
    const r = await api("/sensors/baseline", { method: "POST", bearer: tok });
    if (r.status === 200) {
      out.textContent = `baseline taken (${r.body.samples} samples until ${utc(r.body.t_to)})`;
      out.className = "action-result ok";
      pollSensors();
    } else {
      if (r.status === 401 || r.status === 403) sessionStorage.removeItem("chtc-write-token");
      out.textContent = `refused (${r.status}): ${r.body?.error?.message || "HTTP " + r.status}`;
      out.className = "action-result err";
    }
  } catch (e) {
    out.textContent = "failed: the service did not answer";
    out.className = "action-result err";
  }
  out.title = out.textContent;
  $("baseline-now").disabled = false;
}

// ---------- condition timeline ----------
function drawConditions(current, recent, servedAt) {
  const stateCls = current.state === "stable" ? "" : "no";
  $("condition-now").innerHTML = `<b>${fmt(current.speed_rpm, 0)} rpm</b> · ${fmt(current.torque_nm, 2)} N·m · ` +
    `T<sub>i</sub> ${fmt(current.ambient_c, 1)} °C · <span class="${stateCls}">${current.state}</span>`;
  $("header-condition").innerHTML = `<b>${fmt(current.speed_rpm, 0)}</b> rpm · ${fmt(current.torque_nm, 2)} N·m · ` +
    `T<sub>i</sub> ${fmt(current.ambient_c, 1)} °C · <span class="${stateCls}">${current.state}</span>`;
  const canvas = $("condition-chart");
  const { ctx, W, H } = setupCanvas(canvas);
  const box = { L: 60, R: 12, T: 10, B: 40, W, H };
  const segs = [...recent].reverse();
  const now = Date.parse(servedAt); // the server's clock, not ours
  const t0 = Math.min(...segs.map((c) => Date.parse(c.since)), now - 600e3);
  const maxS = Math.max(...segs.map((c) => c.speed_rpm), 1000) * 1.15;
  const y = yAxis(canvas, ctx, box, 0, maxS, { title: "speed, rpm", ticks: niceTicks(0, maxS, 4) });
  const x = xTimeAxis(canvas, ctx, box, t0, now, timeTitle());
  segs.forEach((c, i) => {
    const a = x(Date.parse(c.since)), b = i + 1 < segs.length ? x(Date.parse(segs[i + 1].since)) : x(now);
    ctx.fillStyle = "rgba(76,155,232,0.28)";
    ctx.fillRect(a, y(c.speed_rpm), Math.max(b - a, 1), y(0) - y(c.speed_rpm));
    ctx.strokeStyle = "#4c9be8"; ctx.lineWidth = 2; ctx.beginPath();
    ctx.moveTo(a, y(c.speed_rpm)); ctx.lineTo(b, y(c.speed_rpm)); ctx.stroke(); ctx.lineWidth = 1;
    ctx.fillStyle = TEXT; ctx.textAlign = "left";
    if (b - a > 46) ctx.fillText(`#${c.id}`, a + 4, Math.max(y(c.speed_rpm) - 4, 10));
  });
  const dur = (now - Date.parse(current.since)) / 1000;
  $("condition-since").textContent = `#${current.id} since ${utc(current.since)} (${ageText(dur)})`;
}

async function pollCondition() {
  try {
    const r = await api("/condition?limit=20");
    if (r.status === 200) drawConditions(r.body.current, r.body.recent, r.body.served_at);
    else $("condition-now").textContent = r.body?.error?.message || "no condition yet";
  } catch (e) { $("condition-now").textContent = "condition unavailable"; }
}

// ---------- thermal growth (/compensation): kept from the polls since the page was loaded ----------
const GROWTH_KEEP = 2160;

function drawGrowth() {
  const canvas = $("growth-chart");
  const { ctx, W, H } = setupCanvas(canvas);
  const box = { L: 60, R: 14, T: 12, B: 40, W, H };
  const pts = state.growth, g = state.growthNow;
  canvas.dataset.points = String(pts.length);
  if (!g || !pts.length) { ctx.fillStyle = MUTED; ctx.fillText("no growth yet", box.L + 10, H / 2); return; }
  const fc = g.forecast.horizons.map((h) => ({ t: Date.parse(h.at), v: h.axial }));
  const t0 = Math.min(pts[0].t, Date.parse(g.at) - 600e3), tf = Math.max(...fc.map((p) => p.t));
  const t1 = tf + 0.03 * (tf - t0); // room for the last forecast point
  const vals = [...pts.flatMap((p) => p.ci), ...fc.flatMap((p) => p.v.ci95_um), g.forecast.steady_axial.um];
  let lo = Math.min(...vals, 0), hi = Math.max(...vals, 1);
  const pad = (hi - lo) * 0.06; lo -= pad; hi += pad;
  const y = yAxis(canvas, ctx, box, lo, hi, { title: "axial growth, µm" });
  const x = xTimeAxis(canvas, ctx, box, t0, t1, timeTitle());
  ctx.save(); ctx.beginPath(); ctx.rect(box.L, box.T, W - box.L - box.R, H - box.T - box.B); ctx.clip();
  ctx.fillStyle = "rgba(76,155,232,0.22)"; ctx.beginPath();
  pts.forEach((p, i) => (i ? ctx.lineTo(x(p.t), y(p.ci[1])) : ctx.moveTo(x(p.t), y(p.ci[1]))));
  [...pts].reverse().forEach((p) => ctx.lineTo(x(p.t), y(p.ci[0])));
  ctx.closePath(); ctx.fill();
  ctx.strokeStyle = "#4c9be8"; ctx.lineWidth = 2; ctx.beginPath();
  pts.forEach((p, i) => (i ? ctx.lineTo(x(p.t), y(p.um)) : ctx.moveTo(x(p.t), y(p.um)))); ctx.stroke();
  ctx.lineWidth = 1; ctx.strokeStyle = MUTED; ctx.setLineDash([6, 4]); ctx.beginPath();
  ctx.moveTo(x(Date.parse(g.at)), y(g.forecast.steady_axial.um)); ctx.lineTo(W - box.R, y(g.forecast.steady_axial.um));
  ctx.stroke(); ctx.setLineDash([]);
  for (const p of fc) {
    ctx.strokeStyle = "#f0883e"; ctx.beginPath(); ctx.moveTo(x(p.t), y(p.v.ci95_um[0])); ctx.lineTo(x(p.t), y(p.v.ci95_um[1])); ctx.stroke();
    ctx.fillStyle = "#f0883e"; ctx.beginPath(); ctx.arc(x(p.t), y(p.v.um), 3.5, 0, 2 * Math.PI); ctx.fill();
  }
  ctx.restore();
}

// ---------- the compensation (/compensation): the page's one status ----------
// Colour of the served verdict: green only when the API says usable; red when the value is not being updated
// or not identified; amber for the transient states. What the verdict is, is the API's.
const SEVERE = new Set(["stale", "no-data", "at-bound", "error"]);
function verdictClass(c) {
  if (!c) return "bad";
  if (c.usable_for_compensation) return "ok";
  return SEVERE.has(c.status) ? "bad" : "warn";
}
// Only for an API that serves no `action` yet (before the served-value policy): a hint by the served status.
const ACTION_BY_STATUS = {
  stale: "Check the DAQ and CAN connections (Devices card): the value is not being updated.",
  "no-data": "Wait for samples; if none arrive, check the devices.",
  identifying: "Wait: a new identification is on its way.",
  converging: "Wait a few minutes: the live temperature state is settling after a (re)start.",
  "at-bound": "Wait for more data at this condition; if it persists, check the sensors.",
  predicted: "Restore the temperature DAQ: the value is predicted without measurements.",
  fresh: "Wait until the estimate is good enough to apply.",
};

function showComp(c, problem) {
  const cls = c ? verdictClass(c) : problem.sev || "bad", pill = $("status"), v = $("comp-verdict");
  v.className = `comp-verdict verdict-${cls}`;
  pill.className = `pill pill-${cls}`;
  const ds = { status: c ? c.status : "", usable: c ? String(Boolean(c.usable_for_compensation)) : "false", reasonCode: c?.reason_code || "" };
  Object.assign(pill.dataset, ds); Object.assign(v.dataset, ds);
  if (!c) {
    pill.textContent = problem.title;
    $("comp-um").textContent = "–"; $("comp-ci").textContent = "no value"; $("comp-correction").textContent = "";
    $("comp-command").textContent = "";
    $("comp-usable").textContent = "No compensation value";
    $("comp-reason").textContent = problem.detail;
    $("comp-action").textContent = problem.action ? "What to do: " + problem.action : "";
    $("comp-faults").textContent = "";
    for (const id of ["comp-status", "comp-age", "comp-at"]) $(id).textContent = "–";
    banner();
    return;
  }
  const a = c.axial, usable = Boolean(c.usable_for_compensation);
  pill.textContent = `${usable ? "usable" : "not usable"} · ${c.status}`;
  pill.title = `/api/v1/compensation: ${c.status}, ${usable ? "usable" : "not usable"}` + (c.reason ? ` (${c.reason})` : "");
  $("comp-um").textContent = signed(a.um, 1);
  $("comp-ci").textContent = `95 % CI [${signed(a.ci95_um[0], 1)}, ${signed(a.ci95_um[1], 1)}] µm (± ${fmt((a.ci95_um[1] - a.ci95_um[0]) / 2, 1)})`;
  $("comp-correction").textContent = `axis correction ${signed(c.plc.correction_um, 1)} µm · SD43900 ` +
    `${c.plc.sd43900_temp_comp_abs_value_mm.toFixed(4)} mm · ISG ${c.plc.isg_temp_comp_offset_0_0p1um} × 0.1 µm`;
  // the command value: what the controller applies now (held, faded, rate-limited by the service)
  const cmd = c.command;
  $("comp-command").textContent = cmd ? `controller command ${signed(cmd.value_um, 1)} µm (${cmd.status}, ` +
    `profile ${cmd.profile.name}) · SD43900 ${cmd.sd43900_temp_comp_abs_value_mm.toFixed(4)} mm` : "";
  $("comp-usable").textContent = usable ? "Usable: apply the correction" : "Not usable: do not apply";
  $("comp-reason").textContent = usable ? "" : (c.reason || "");
  const action = "action" in c ? c.action : (usable ? null : ACTION_BY_STATUS[c.status]);
  $("comp-action").textContent = !usable && action ? "What to do: " + action : "";
  $("comp-status").textContent = c.status + (c.reason_code ? ` · ${c.reason_code}` : "");
  // channels the live state left out as stuck or drifting (the DAQ did not flag them): channel, since, why
  $("comp-faults").textContent = (c.sensor_faults || []).map((f) =>
    `Sensor ${f.channel} left out (${f.kind}) since ${utc(f.since)}: ${f.detail}`).join("\n");
  const plant = state.clockInfo?.simulated ? " (plant time)" : "";
  $("comp-age").textContent = c.sample_age_s === null ? "none yet" : `${ageText(c.sample_age_s)} old${plant}`;
  const ref = c.reference;
  $("comp-ref").textContent = ref ? `${fmt(ref.temperature_c, 2)} °C, set ${utc(ref.at)} (${ref.source}, ${ref.set_by})`
    : c.t_ref_at ? `${fmt(c.t_ref_c, 2)} °C since ${utc(c.t_ref_at)}` : `${fmt(c.t_ref_c, 2)} °C (none set)`;
  $("comp-at").textContent = utc(c.at);
  $("comp-at-label").textContent = state.clockInfo?.simulated ? "live field at (plant time)" : "live field at";
  banner();
}

async function pollGrowth() {
  try {
    const r = await api("/compensation");
    if (r.status !== 200) {
      const msg = r.body?.error?.message || "HTTP " + r.status;
      $("growth-now").textContent = msg || "no growth yet";
      const wait = r.status === 503; // no live state or identification yet: normal after a start
      showComp(null, { title: wait ? "no value yet" : "no value", detail: msg, sev: wait ? "warn" : "bad",
        action: wait ? "Wait: the service serves a value once its live state has converged." : null });
      if (!state.growthNow) drawGrowth();
      return;
    }
    const g = r.body, a = g.axial;
    state.growthNow = g;
    showComp(g);
    const t = Date.parse(g.at);
    const last = state.growth[state.growth.length - 1];
    if (!last || t > last.t) state.growth.push({ t, um: a.um, ci: a.ci95_um });
    else if (t < last.t) state.growth = [{ t, um: a.um, ci: a.ci95_um }]; // the server restarted
    if (state.growth.length > GROWTH_KEEP) state.growth.shift();
    const f = g.forecast;
    $("growth-now").innerHTML = `axial <b id="growth-axial">${fmt(a.um, 1)}</b> µm · radial ${fmt(g.radial.um, 1)} µm · ` +
      `steady ${fmt(f.steady_axial.um, 1)} µm (τ ${fmt(f.tau_s / 60, 0)} min)`;
    $("growth-stale").hidden = g.status !== "stale";
    $("growth-meta").textContent = `at ${utc(g.at)} over T_ref ${fmt(g.t_ref_c, 2)} °C · ${g.identification_id === null ? "no identification yet (H guessed)" : "identification #" + g.identification_id}`;
    drawGrowth();
  } catch (e) {
    $("growth-now").textContent = "growth unavailable";
    showComp(null, { title: "API unreachable", detail: "no answer from the service", action: "Check that the service runs." });
  }
}

// ---------- set the compensation zero (POST /compensation/reference) ----------
function openZero() {
  $("zero-token").value = sessionStorage.getItem("chtc-write-token") || "";
  $("zero-dialog").showModal();
  ($("zero-token").value ? $("zero-submit") : $("zero-token")).focus();
}

async function submitZero(ev) {
  ev.preventDefault();
  const tok = $("zero-token").value.trim();
  if (!tok) { $("zero-token").focus(); return; }
  sessionStorage.setItem("chtc-write-token", tok);
  $("zero-dialog").close();
  const out = $("zero-result");
  $("zero-now").disabled = true;
  try {
    const r = await api("/compensation/reference", { method: "POST", body: { set_by: "dashboard" }, bearer: tok });
    if (r.status === 200) {
      out.textContent = `zero set: ${fmt(r.body.temperature_c, 2)} °C at ${utc(r.body.at)}`;
      out.className = "action-result ok";
      pollGrowth();
    } else {
      if (r.status === 401 || r.status === 403) sessionStorage.removeItem("chtc-write-token");
      const missing = r.status === 404 || r.status === 405;
      out.textContent = missing ? "this service cannot store a compensation zero (no /compensation/reference)"
        : `refused (${r.status}): ${r.body?.error?.message || "HTTP " + r.status}`;
      out.className = "action-result err";
    }
  } catch (e) {
    out.textContent = "failed: the service did not answer";
    out.className = "action-result err";
  }
  out.title = out.textContent;
  $("zero-now").disabled = false;
}

// ---------- the deformed section (/compensation/section): outline + displacement × an exaggeration ----------
function exaggeration(maxUm, rmaxM) { // the 1-2-5 step that draws the largest |u| at about 12 % of the radius
  if (!(maxUm > 0)) return 1;
  const want = 0.12 * rmaxM / (maxUm * 1e-6), p = 10 ** Math.floor(Math.log10(want));
  return [5, 2, 1].map((f) => f * p).find((k) => k <= want) || p;
}

function drawDeformed(sec) {
  const canvas = $("deformed");
  if (!sec) return;
  const r = sec.nodes_r_m, z = sec.nodes_z_m, ur = sec.u_r_um, uz = sec.u_z_um;
  const zmin = Math.min(...z), zmax = Math.max(...z), rmax = Math.max(...r);
  const k = exaggeration(sec.max_abs_um, rmax);
  const L = 52, R = 20, top = 16, bottom = 42;
  const sw = (Math.max(canvas.clientWidth, 200) - L - R) / (zmax - zmin);
  canvas.dataset.h = String(Math.round(Math.min(Math.max(top + bottom + 1.25 * rmax * sw, 200), 420)));
  const { ctx, W, H } = setupCanvas(canvas);
  const s = Math.min((W - L - R) / (zmax - zmin) / 1.04, (H - top - bottom) / (rmax * 1.2));
  const X = (zm) => L + (zm - zmin) * s, Y = (rm) => H - bottom - rm * s;
  const dz = uz.map((v) => v * 1e-6 * k), dr = ur.map((v) => v * 1e-6 * k);
  ctx.lineWidth = 1; ctx.strokeStyle = "rgba(143,155,168,0.55)"; ctx.beginPath();
  for (const [a, b] of sec.edges) { ctx.moveTo(X(z[a]), Y(r[a])); ctx.lineTo(X(z[b]), Y(r[b])); }
  ctx.stroke();
  let digest = 0;
  ctx.lineWidth = 1.5; ctx.strokeStyle = "#4c9be8"; ctx.beginPath();
  for (const [a, b] of sec.edges) {
    ctx.moveTo(X(z[a] + dz[a]), Y(r[a] + dr[a])); ctx.lineTo(X(z[b] + dz[b]), Y(r[b] + dr[b]));
  }
  ctx.stroke();
  for (let i = 0; i < z.length; i++) digest += Math.abs(uz[i]) + Math.abs(ur[i]);
  // axes: z below, r at the left (mm), the upper half of the section (r ≥ 0)
  ctx.strokeStyle = AXIS; ctx.fillStyle = MUTED; ctx.textAlign = "center";
  const yb = H - bottom + 4;
  ctx.beginPath(); ctx.moveTo(X(zmin), yb); ctx.lineTo(X(zmax), yb); ctx.stroke();
  for (const v of niceTicks(zmin * 1e3, zmax * 1e3, 8)) {
    ctx.beginPath(); ctx.moveTo(X(v / 1e3), yb); ctx.lineTo(X(v / 1e3), yb + 4); ctx.stroke();
    ctx.fillText(v.toFixed(0), X(v / 1e3), yb + 16);
  }
  ctx.fillStyle = TEXT;
  ctx.fillText(`z, mm (undeformed); displacement drawn ×${k}`, L + (zmax - zmin) * s / 2, H - 5);
  ctx.textAlign = "right"; ctx.textBaseline = "middle"; ctx.fillStyle = MUTED;
  for (const v of niceTicks(0, rmax * 1e3, 3)) ctx.fillText(v.toFixed(0), L - 8, Y(v / 1e3));
  ctx.textBaseline = "alphabetic";
  ctx.save(); ctx.translate(12, Y(rmax / 2)); ctx.rotate(-Math.PI / 2); ctx.textAlign = "center"; ctx.fillStyle = TEXT;
  ctx.fillText("r, mm", 0, 0); ctx.restore();
  ctx.textAlign = "left"; ctx.fillStyle = TEXT;
  ctx.fillText(`×${k}`, W - R - 60, top + 12);
  Object.assign(canvas.dataset, { exaggeration: String(k), edges: String(sec.edges.length), at: sec.at,
    maxUm: sec.max_abs_um.toFixed(3), digest: digest.toFixed(3) });
  $("deformed-unit").textContent = `displacement in µm, drawn ×${k}; grey = undeformed outline, blue = deformed`;
  $("deformed-stale").hidden = sec.status !== "stale";
  $("deformed-meta").textContent = `at ${utc(sec.at)} over T_ref ${fmt(sec.t_ref_c, 2)} °C · largest |u| ` +
    `${fmt(sec.max_abs_um, 1)} µm · exaggeration ×${k} · identification #${sec.identification_id} · ${sec.status}` +
    ` · axial u_z relative to the mounting face`;
}

async function pollDeformed() {
  try {
    const r = await api("/compensation/section");
    if (r.status !== 200) { $("deformed-meta").textContent = r.body?.error?.message || "no deformation yet"; return; }
    state.deformed = r.body;
    drawDeformed(r.body);
  } catch (e) { $("deformed-meta").textContent = "deformation unavailable"; }
}

// ---------- health and identifications ----------
const DEVICE_LABEL = { modbus: "temperature DAQ (Modbus)", can: "speed/torque (CAN)", db: "database", worker: "identification worker" };

async function pollHealth() {
  try {
    const [h, rd] = await Promise.all([api("/healthz"), api("/readyz")]);
    if (h.status === 200) {
      state.health = h.body;
      showClockKind(h.body.clock);
      $("health-table").querySelector("tbody").innerHTML = h.body.devices.map((d) =>
        `<tr data-device="${esc(d.name)}"><td>${esc(DEVICE_LABEL[d.name] || d.name)}</td><td><span class="badge st-${d.status}">${d.status}</span></td>` +
        `<td>${d.age_s === null ? "–" : ageText(d.age_s) + " ago"}</td>` +
        `<td class="wrap detail">${d.message ? `<div>${esc(d.message)}</div>` : ""}` +
        `<div class="muted">${Object.entries(d.counters).map(([k, v]) => `${esc(k)} ${v}`).join(" · ")}</div></td></tr>`).join("");
    }
    state.ready = rd.status === 200 ? { ready: true, reasons: [] } : { ready: false, reasons: rd.body?.error?.detail?.reasons || [rd.body?.error?.message || "HTTP " + rd.status] };
    $("ready-meta").textContent = state.ready.ready ? "service ready" : "NOT READY";
    $("ready-meta").className = state.ready.ready ? "unit" : "unit bad";
  } catch (e) { state.apiError = UNREACHABLE; }
  banner();
}

async function pollIdents() {
  try {
    const r = await api("/identifications?limit=6");
    if (r.status !== 200) return;
    $("ident-table").querySelector("tbody").innerHTML = r.body.items.map((i) =>
      `<tr><td>${i.id}</td><td>${utc(i.finished_at)}</td><td>#${i.condition.id} · ${fmt(i.condition.speed_rpm, 0)} rpm, ` +
      `${fmt(i.condition.ambient_c, 1)} °C</td><td class="num">${fmt(i.rmse_c, 3)} °C</td><td>${esc(i.method)}</td>` +
      `<td class="wrap ${i.outcome === "ok" ? "" : "no"}">${esc(i.outcome)} · ${esc(i.reason)}</td></tr>`).join("");
  } catch (e) { /* shown by the other panels */ }
}

// The service's clock: a simulated plant time (chtc demo, chtc replay) is marked as such wherever time shows.
function showClockKind(info) {
  state.clockInfo = info || null;
  const sim = Boolean(info?.simulated), el = $("plant-time");
  el.hidden = !sim;
  el.textContent = sim ? `SIMULATED PLANT TIME ×${fmt(info.speedup, 0)}` : "";
  $("clock").title = sim ? "the service's simulated plant time, UTC" : "server time, UTC";
  $("footer-time").textContent = sim ? `all times are simulated plant time (UTC), running ×${fmt(info.speedup, 0)} the wall clock`
    : "all times UTC";
  document.body.dataset.plantTime = sim ? "1" : "0";
}

// ---------- identify now ----------
function showResult(text, cls) {
  const el = $("identify-result");
  el.textContent = text; el.className = "action-result " + (cls || ""); el.title = text;
}

function openIdentify() {
  $("write-token").value = sessionStorage.getItem("chtc-write-token") || "";
  $("identify-dialog").showModal();
  ($("write-token").value ? $("identify-submit") : $("write-token")).focus();
}

async function submitIdentify(ev) {
  ev.preventDefault();
  const tok = $("write-token").value.trim();
  if (!tok) { $("write-token").focus(); return; }
  sessionStorage.setItem("chtc-write-token", tok);
  $("identify-dialog").close();
  $("identify-now").disabled = true;
  showResult("requesting an identification …");
  try {
    const r = await api("/identifications", { method: "POST", body: { reason: $("identify-reason").value || "operator request from the dashboard" }, bearer: tok });
    if (r.status === 202) {
      state.job = r.body.job_id;
      showResult(`${r.body.job_id} ${r.body.state}`, "ok");
      followJob(r.body.job_id);
      return;
    }
    if (r.status === 401 || r.status === 403) sessionStorage.removeItem("chtc-write-token");
    const msg = r.body?.error?.message || "HTTP " + r.status;
    showResult(`refused (${r.status} ${r.body?.error?.code || ""}): ${msg}`, "err");
  } catch (e) {
    showResult("failed: the service did not answer", "err");
  }
  $("identify-now").disabled = false;
}

async function followJob(jobId) {
  const deadline = Date.now() + 15 * 60e3;
  while (Date.now() < deadline) {
    await new Promise((res) => setTimeout(res, 1000));
    let r;
    try { r = await api(`/identifications/jobs/${encodeURIComponent(jobId)}`); } catch (e) { continue; }
    if (r.status !== 200) { showResult(`${jobId}: ${r.body?.error?.message || "HTTP " + r.status}`, "err"); break; }
    const j = r.body;
    if (j.state === "done") { showResult(`${jobId} done: identification #${j.identification_id}`, "ok"); pollIdents(); break; }
    if (j.state === "failed") { showResult(`${jobId} failed: ${j.message || "no message"}`, "err"); pollIdents(); break; }
    showResult(`${jobId} ${j.state} …`, "ok");
  }
  $("identify-now").disabled = false;
}

// ---------- start ----------
function markRendered() {
  if (state.rendered.h && state.rendered.field && state.rendered.sensors) document.body.dataset.rendered = "1";
}

function every(fn, ms) { fn(); setInterval(fn, ms); }

function start() {
  readFragment();
  setInterval(() => { $("clock").textContent = new Date(serverNow()).toISOString().slice(0, 19).replace("T", " ") + " UTC"; }, 1000);
  $("field-at").addEventListener("change", pollField);
  $("field-show").addEventListener("change", () => { if (state.field) drawField(state.field); });
  $("field").addEventListener("click", probeField);
  $("field").addEventListener("mousemove", hoverField);
  $("channels").addEventListener("change", () => { state.hist = null; pollSensors(); });
  $("window").addEventListener("change", drawSensors);
  $("hmap-scale").addEventListener("change", () => { if (state.hmap) drawHmap(state.hmap); });
  $("hmap-legend").addEventListener("click", toggleHmapZone);
  $("identify-now").addEventListener("click", openIdentify);
  $("identify-form").addEventListener("submit", submitIdentify);
  $("identify-cancel").addEventListener("click", () => $("identify-dialog").close());
  $("baseline-now").addEventListener("click", openBaseline);
  $("baseline-form").addEventListener("submit", submitBaseline);
  $("baseline-cancel").addEventListener("click", () => $("baseline-dialog").close());
  $("zero-now").addEventListener("click", openZero);
  $("zero-form").addEventListener("submit", submitZero);
  $("zero-cancel").addEventListener("click", () => $("zero-dialog").close());
  let resizeTimer = null;
  window.addEventListener("resize", () => {
    clearTimeout(resizeTimer);
    resizeTimer = setTimeout(() => {
      if (state.chtc) drawH(state.chtc);
      if (state.field) drawField(state.field);
      if (state.hmap && !$("card-hmap").hidden) drawHmap(state.hmap);
      drawSensors(); drawGrowth(); drawDeformed(state.deformed);
    }, 150);
  });
  loadLayout().then(() => {
    every(pollSensors, POLL_MS.sensors);
    every(pollChtc, POLL_MS.chtc);
    every(pollCondition, POLL_MS.condition);
    every(pollHealth, POLL_MS.health);
    every(pollIdents, POLL_MS.idents);
    every(pollGrowth, POLL_MS.growth);
    every(pollDeformed, POLL_MS.deformed);
    every(pollHmap, POLL_MS.hmap);
    setInterval(pollField, POLL_MS.field);
  });
}

start();
