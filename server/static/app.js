// Localizer dashboard: plain JavaScript and an SVG map in site metres (no library, nothing fetched
// from elsewhere). The API key is asked once and kept in sessionStorage; the key's scope decides
// what is shown (admin: sites, maps, models, every session; device: its own sessions).
"use strict";

const KEY = "localizer.key";
const SVGNS = "http://www.w3.org/2000/svg";
const COLORS = ["#2563eb", "#dc2626", "#059669", "#d97706", "#7c3aed", "#db2777", "#0891b2", "#4b5563"];
const CHI2_95 = 5.991; // 95 % of a 2-D Gaussian lies inside this squared Mahalanobis radius

const S = {
  key: null, scope: null, sites: [], site: null, building: 0, floor: null, rps: [], txs: [], models: [], sessions: [],
  tracks: new Map(), // session id -> {pts: [{idx, x, y, floor, covariance}], color, status}
  streams: [], bounds: null, replayTimer: null, algorithms: [], coverage: "",
  measured: null, // {tx, floor, body}: GET /coverage for the chosen transmitter and floor
  errors: null, // {model, points}: GET /models/{id}/errors of the active model
};
// Held-out error layer: the colour scale's top (m); larger errors get its colour.
const ERR_TOP_M = 10;
// Coverage layer: measured where the floor has reference points (GET /api/v1/sites/{id}/coverage:
// the mean RSS of the transmitter at each reference point), else a transmitter's RSS from the
// log-distance model the server's radio code uses (R0 at 1 m, exponent γ; -45 dBm and 2.5 when
// the transmitter has none), walls ignored.
const DEFAULT_R0_DBM = -45.0, DEFAULT_GAMMA = 2.5, HEAT_TOP = -30, HEAT_BOTTOM = -100;

const $ = (id) => document.getElementById(id);

// --- HTTP ------------------------------------------------------------------------------------

class HttpError extends Error {
  constructor(status, detail) { super(`${status}: ${typeof detail === "string" ? detail : JSON.stringify(detail)}`); this.status = status; }
}

async function api(path, options = {}) {
  const headers = { Authorization: `Bearer ${S.key}`, ...(options.body ? { "Content-Type": "application/json" } : {}) };
  const r = await fetch(path, { ...options, headers });
  if (r.status === 204) return null;
  const body = await r.json().catch(() => null);
  if (!r.ok) throw new HttpError(r.status, body && body.detail);
  return body;
}

// A server-sent event stream read with fetch (EventSource cannot send an Authorization header).
async function stream(path, onEvent, controller, lastId) {
  const headers = { Authorization: `Bearer ${S.key}`, Accept: "text/event-stream" };
  if (lastId !== undefined && lastId !== null) headers["Last-Event-ID"] = String(lastId);
  const r = await fetch(path, { headers, signal: controller.signal });
  if (!r.ok || !r.body) throw new HttpError(r.status, "stream refused");
  const reader = r.body.pipeThrough(new TextDecoderStream()).getReader();
  let buf = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buf = (buf + value).replace(/\r\n/g, "\n");
    let cut;
    while ((cut = buf.indexOf("\n\n")) >= 0) {
      const block = buf.slice(0, cut);
      buf = buf.slice(cut + 2);
      const ev = { event: "message", data: "", id: null };
      for (const line of block.split("\n")) {
        if (!line || line.startsWith(":")) continue;
        const i = line.indexOf(":");
        const name = i < 0 ? line : line.slice(0, i);
        const val = i < 0 ? "" : line.slice(i + 1).replace(/^ /, "");
        if (name === "data") ev.data += (ev.data ? "\n" : "") + val;
        else if (name === "event") ev.event = val;
        else if (name === "id") ev.id = val;
      }
      if (ev.data) onEvent(ev.event, JSON.parse(ev.data), ev.id);
    }
  }
}

// Keep a stream open: reconnect after an error or end (resuming after the last id), until aborted.
function follow(path, onEvent, { resume = false, endOn = null } = {}) {
  const controller = new AbortController();
  S.streams.push(controller);
  let lastId = null;
  let ended = false;
  (async () => {
    while (!controller.signal.aborted && !ended) {
      try {
        await stream(path, (event, data, id) => {
          if (resume && id !== null) lastId = id;
          if (event === endOn) ended = true;
          onEvent(event, data);
        }, controller, lastId);
      } catch (err) {
        if (controller.signal.aborted) return;
        if (err instanceof HttpError && err.status === 404) return;
        setStatus(`stream interrupted (${err.message}); reconnecting`);
      }
      if (!ended) await new Promise((ok) => setTimeout(ok, 2000));
    }
  })();
  return controller;
}

function stopStreams() {
  for (const c of S.streams) c.abort();
  S.streams = [];
  if (S.replayTimer) { clearInterval(S.replayTimer); S.replayTimer = null; }
}

function setStatus(text) { $("status").textContent = text; }

// --- login -----------------------------------------------------------------------------------

async function start() {
  S.key = sessionStorage.getItem(KEY);
  if (!S.key) return showLogin("");
  let who;
  try {
    who = await api("/api/v1/whoami");
  } catch (err) {
    sessionStorage.removeItem(KEY);
    return showLogin(err.status === 401 ? "That key was refused (unknown or revoked)." : `Cannot reach the server: ${err.message}`);
  }
  S.scope = who.scope;
  $("login").hidden = true;
  $("app").hidden = false;
  $("forget").hidden = false;
  $("scope").hidden = false;
  $("scope").textContent = `${S.scope} key`;
  document.body.classList.add(`scope-${S.scope}`);
  for (const el of document.querySelectorAll(".admin-only")) el.hidden = S.scope !== "admin";
  if (S.scope === "admin") {
    $("models-panel").hidden = false;
    await loadAlgorithms();
    await loadSites();
  } else {
    $("sites-panel").hidden = true;
    $("floor-label").hidden = true;
    $("coverage-label").hidden = true;
    $("site-name").textContent = "my sessions";
    drawMap();
    await loadSessions();
    followOwnSessions();
  }
}

function showLogin(message) {
  $("app").hidden = true;
  $("login").hidden = false;
  $("forget").hidden = true;
  $("scope").hidden = true;
  $("login-error").textContent = message;
  $("key").focus();
}

$("login-form").addEventListener("submit", (e) => {
  e.preventDefault();
  sessionStorage.setItem(KEY, $("key").value.trim());
  $("key").value = "";
  start();
});

$("forget").addEventListener("click", () => {
  stopStreams();
  sessionStorage.removeItem(KEY);
  location.reload();
});

// --- sites, floors, layers --------------------------------------------------------------------

async function loadSites() {
  S.sites = await api("/api/v1/sites");
  const ul = $("sites");
  ul.replaceChildren();
  if (!S.sites.length) {
    ul.append(li("no sites yet: create one with POST /api/v1/sites", ""));
    return;
  }
  for (const site of S.sites) {
    const item = li(site.name, `${site.reference_points} RPs · ${site.fingerprints.survey}+${site.fingerprints.crowd} fp`);
    item.dataset.site = site.id;
    item.addEventListener("click", () => selectSite(site.id));
    ul.append(item);
  }
  const wanted = Number(new URLSearchParams(location.hash.slice(1)).get("site"));
  await selectSite(S.sites.some((s) => s.id === wanted) ? wanted : S.sites[0].id);
}

async function selectSite(id) {
  stopStreams();
  S.site = S.sites.find((s) => s.id === id);
  S.tracks.clear();
  S.errors = null;
  history.replaceState(null, "", `#site=${id}`);
  for (const item of $("sites").children) item.classList.toggle("selected", Number(item.dataset.site) === id);
  $("site-name").textContent = S.site.name;
  const [txs, rps] = await Promise.all([api(`/api/v1/sites/${id}/transmitters`), api(`/api/v1/sites/${id}/reference-points`)]);
  S.txs = txs;
  S.rps = rps;
  // floors are (building, level) pairs: a level of building 1 is not building 0's
  const keys = new Map();
  for (const o of [...S.site.floors.map((f) => ({ building: f.building, floor: f.level })), ...rps, ...txs.filter((t) => t.floor !== null)]) {
    const b = o.building ?? 0;
    keys.set(`${b}:${o.floor}`, [b, o.floor]);
  }
  const sorted = [...keys.values()].sort((p, q) => p[0] - q[0] || p[1] - q[1]);
  if (!sorted.length) sorted.push([0, 0]);
  const several = new Set(sorted.map((k) => k[0])).size > 1;
  $("floor").replaceChildren(...sorted.map(([b, level]) => {
    const f = S.site.floors.find((x) => x.level === level && (x.building ?? 0) === b);
    const o = document.createElement("option");
    o.value = `${b}:${level}`;
    const name = f && f.name ? `${level} · ${f.name}` : String(level);
    o.textContent = several ? `building ${b} · ${name}` : name;
    return o;
  }));
  showFloor(...sorted[0]);
  S.coverage = "";
  fillCoverage();
  S.bounds = null;
  drawMap();
  await Promise.all([loadModels(), loadSessions()]);
  followSite();
}

// The shown floor: S.building and S.floor (its level), and the selector's value "building:level".
function showFloor(building, level) {
  S.building = building ?? 0;
  S.floor = level;
  $("floor").value = `${S.building}:${S.floor}`;
}
// Whether a reference point, transmitter or estimate is on the shown floor.
const onShown = (o) => o.floor === S.floor && (o.building ?? 0) === S.building;

$("floor").addEventListener("change", (e) => {
  const [b, level] = e.target.value.split(":").map(Number);
  showFloor(b, level);
  S.coverage = "";
  fillCoverage();
  drawMap();
});
$("coverage").addEventListener("change", (e) => { S.coverage = e.target.value; loadCoverage(); });

// Measured coverage when the shown floor has reference points; the modelled layer otherwise.
const floorSurveyed = () => S.rps.some(onShown);

async function loadCoverage() {
  const tx = S.coverage, floor = S.floor, building = S.building, site = S.site;
  S.measured = null;
  if (tx && floorSurveyed()) {
    try {
      const body = await api(`/api/v1/sites/${site.id}/coverage?transmitter=${encodeURIComponent(tx)}&floor=${floor}&building=${building}`);
      if (S.coverage !== tx || S.floor !== floor || S.building !== building || S.site !== site) return; // chosen again meanwhile
      S.measured = { tx, floor, building, body };
    } catch (err) {
      setStatus(`coverage: ${err.message}`);
    }
  }
  drawMap();
}

// The coverage selector: the shown floor's transmitters (on a floor without reference points,
// only positioned ones: the modelled layer needs a position).
function fillCoverage() {
  S.measured = null;
  const off = document.createElement("option");
  off.value = "";
  off.textContent = "off";
  const measured = floorSurveyed();
  const txs = S.txs.filter((t) => (measured || t.x !== null) && (t.floor === null || onShown(t)));
  $("coverage").replaceChildren(off, ...txs.map((t) => {
    const o = document.createElement("option");
    o.value = o.textContent = t.id;
    return o;
  }));
  $("coverage").value = S.coverage;
}

// A dBm value on the heat scale: blue (−100) … green … yellow (−30).
const heatColor = (rss) => {
  const f = Math.min(1, Math.max(0, (rss - HEAT_BOTTOM) / (HEAT_TOP - HEAT_BOTTOM)));
  return `hsl(${240 - 185 * f}, 85%, ${50 + 5 * f}%)`;
};

function drawCoverage(svg, b) {
  const m = S.measured && S.measured.tx === S.coverage && S.measured.floor === S.floor && S.measured.building === S.building
    ? S.measured.body : null;
  const t = S.txs.find((x) => x.id === S.coverage && x.x !== null);
  $("coverage-measured-legend").hidden = !m;
  svg.classList.toggle("coverage-measured", !!m);
  $("coverage-legend").hidden = !!m || !t || floorSurveyed();
  if (m) return drawMeasured(svg, b, m);
  if (!t || floorSurveyed()) return;
  const g = el("g", { id: "coverage-layer", class: "modelled" }, svg);
  const r0 = t.tx_power_dbm ?? DEFAULT_R0_DBM, gamma = t.path_loss_exponent ?? DEFAULT_GAMMA;
  const cell = Math.max(0.25, b.size / 80);
  for (let x = b.x0; x < b.x1; x += cell) {
    for (let y = b.y0; y < b.y1; y += cell) {
      const d = Math.max(1, Math.hypot(x + cell / 2 - t.x, y + cell / 2 - t.y));
      const rss = r0 - 10 * gamma * Math.log10(d);
      el("rect", { x: X(x), y: Y(y + cell), width: cell * 1.02, height: cell * 1.02, class: "heat", fill: heatColor(rss) }, g);
    }
  }
}

// Measured coverage: a disc per reference point coloured by the transmitter's mean RSS there
// (hollow and dashed where no fingerprint of the point heard it).
function drawMeasured(svg, b, m) {
  const g = el("g", { id: "coverage-layer", class: "measured" }, svg);
  const r = b.size / 55;
  for (const p of m.reference_points) {
    const heard = p.mean_rss_dbm !== null;
    const c = el("circle", {
      cx: X(p.x), cy: Y(p.y), r, class: heard ? "cov heard" : "cov not-heard", "data-label": p.label || "",
      ...(heard ? { fill: heatColor(p.mean_rss_dbm), "data-rss": p.mean_rss_dbm.toFixed(1) } : {}),
    }, g);
    el("title", {}, c).textContent = heard
      ? `${m.transmitter} at ${p.label || "(no label)"}: mean ${p.mean_rss_dbm.toFixed(1)} dBm, heard by ${p.heard} of ${p.fingerprints} fingerprints`
      : `${m.transmitter} at ${p.label || "(no label)"}: not heard by any of ${p.fingerprints} fingerprints`;
  }
  const c = m.crowd;
  $("coverage-crowd").textContent = c.fingerprints
    ? ` · crowd fingerprints on this floor: ${c.heard} of ${c.fingerprints} heard it${c.heard ? `, mean ${c.mean_rss_dbm.toFixed(1)} dBm` : ""}`
    : "";
}
$("show-rps").addEventListener("change", (e) => $("map").classList.toggle("hide-rps", !e.target.checked));
$("show-tx").addEventListener("change", (e) => $("map").classList.toggle("hide-tx", !e.target.checked));
$("show-smoothed").addEventListener("change", () => drawSessions());
$("show-errors").addEventListener("change", () => drawMap());

// The map's extent in metres: the floors' declared size, walls, reference points, transmitters, tracks.
function computeBounds() {
  const xs = [], ys = [];
  const add = (x, y) => { if (Number.isFinite(x) && Number.isFinite(y)) { xs.push(x); ys.push(y); } };
  if (S.site) {
    for (const f of S.site.floors) {
      if (f.width_m && f.height_m) { add(0, 0); add(f.width_m, f.height_m); }
      for (const w of f.walls) { add(w[0], w[1]); add(w[2], w[3]); }
    }
    for (const r of S.rps) add(r.x, r.y);
    for (const t of S.txs) add(t.x, t.y);
  }
  for (const tr of S.tracks.values()) for (const p of [...tr.pts, ...(tr.smooth || [])]) add(p.x, p.y);
  if (!xs.length) { add(0, 0); add(20, 20); }
  let [x0, x1, y0, y1] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
  const pad = Math.max(1, 0.05 * Math.max(x1 - x0, y1 - y0));
  x0 -= pad; x1 += pad; y0 -= pad; y1 += pad;
  return { x0, x1, y0, y1, size: Math.max(x1 - x0, y1 - y0, 1) };
}

function el(tag, attrs = {}, parent = null) {
  const node = document.createElementNS(SVGNS, tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  if (parent) parent.append(node);
  return node;
}

// Site metres -> SVG user units: x as is, y flipped (north up).
const X = (x) => x;
const Y = (y) => -y;

function drawMap() {
  const b = S.bounds || (S.bounds = computeBounds());
  const svg = $("map");
  svg.replaceChildren();
  svg.setAttribute("viewBox", `${b.x0} ${-b.y1} ${b.x1 - b.x0} ${b.y1 - b.y0}`);
  svg.setAttribute("preserveAspectRatio", "xMidYMid meet");
  const grid = el("g", { id: "grid" }, svg);
  const minor = b.size > 150 ? 10 : 1;
  for (let x = Math.ceil(b.x0 / minor) * minor; x <= b.x1; x += minor) {
    el("line", { x1: X(x), x2: X(x), y1: Y(b.y0), y2: Y(b.y1), class: Math.round(x) % 10 === 0 ? "grid-major" : "grid-minor" }, grid);
  }
  for (let y = Math.ceil(b.y0 / minor) * minor; y <= b.y1; y += minor) {
    el("line", { x1: X(b.x0), x2: X(b.x1), y1: Y(y), y2: Y(y), class: Math.round(y) % 10 === 0 ? "grid-major" : "grid-minor" }, grid);
  }
  const fs = b.size / 45;
  for (let x = Math.ceil(b.x0 / 10) * 10; x <= b.x1; x += 10) {
    const t = el("text", { x: X(x) + fs * 0.2, y: Y(b.y0) - fs * 0.3, class: "axis-label", "font-size": fs }, grid);
    t.textContent = `${x} m`;
  }
  for (let y = Math.ceil(b.y0 / 10) * 10; y <= b.y1; y += 10) {
    if (y === 0) continue;
    const t = el("text", { x: X(b.x0) + fs * 0.2, y: Y(y) - fs * 0.3, class: "axis-label", "font-size": fs }, grid);
    t.textContent = `${y} m`;
  }
  if (S.site) {
    drawCoverage(svg, b);
    drawErrors(svg, b);
    const floor = S.site.floors.find((f) => f.level === S.floor && (f.building ?? 0) === S.building);
    const walls = el("g", { id: "walls" }, svg);
    for (const w of floor ? floor.walls : []) el("line", { x1: X(w[0]), y1: Y(w[1]), x2: X(w[2]), y2: Y(w[3]), class: "wall" }, walls);
    const rps = el("g", { id: "rps" }, svg);
    const base = b.size / 250;
    for (const r of S.rps.filter(onShown)) {
      const c = el("circle", { cx: X(r.x), cy: Y(r.y), r: base * Math.sqrt(1 + r.fingerprints), class: "rp", "data-label": r.label || "" }, rps);
      el("title", {}, c).textContent = `${r.label || "(no label)"} · (${r.x.toFixed(2)}, ${r.y.toFixed(2)}) m · ${r.fingerprints} fingerprints`;
    }
    const txs = el("g", { id: "txs" }, svg);
    const s = b.size / 90;
    for (const t of S.txs.filter((t) => t.x !== null && (t.floor === null || onShown(t)))) {
      const shape = t.kind === "ble"
        ? el("rect", { x: X(t.x) - s / 2, y: Y(t.y) - s / 2, width: s, height: s, class: "tx ble", "data-id": t.id }, txs)
        : el("polygon", { points: `${X(t.x)},${Y(t.y) - s * 0.7} ${X(t.x) + s * 0.7},${Y(t.y)} ${X(t.x)},${Y(t.y) + s * 0.7} ${X(t.x) - s * 0.7},${Y(t.y)}`, class: "tx wifi", "data-id": t.id }, txs);
      el("title", {}, shape).textContent = `${t.id} (${t.kind})${t.tx_power_dbm !== null ? ` · ${t.tx_power_dbm} dBm` : ""}`;
    }
  }
  el("g", { id: "sessions-layer" }, svg);
  drawSessions();
}

// The active model's held-out error per reference point (GET …/models/{id}/errors): a disc per
// point of the shown floor, green (0 m) … red (ERR_TOP_M or more).
const errColor = (m) => `hsl(${120 * (1 - Math.min(1, Math.max(0, m / ERR_TOP_M)))}, 80%, 45%)`;

async function loadErrors() {
  const site = S.site, active = S.models.find((m) => m.active && m.status === "ready");
  if (!active) { S.errors = null; return; }
  if (S.errors && S.errors.model === active.id) return;
  try {
    const points = await api(`/api/v1/sites/${site.id}/models/${active.id}/errors`);
    if (S.site === site) S.errors = { model: active.id, points };
  } catch (err) {
    S.errors = null;
    setStatus(`held-out error: ${err.message}`);
  }
}

function drawErrors(svg, b) {
  const on = $("show-errors").checked && !!S.errors;
  $("errors-legend").hidden = !on;
  if (!on) return;
  $("errors-model").textContent = ` (model ${S.errors.model})`;
  $("errors-top").textContent = String(ERR_TOP_M);
  const g = el("g", { id: "errors-layer" }, svg);
  const r = b.size / 70;
  for (const p of S.errors.points.filter(onShown)) {
    const c = el("circle", { cx: X(p.x), cy: Y(p.y), r, class: "err", fill: errColor(p.mean_error_m),
      "data-label": p.label, "data-error": p.mean_error_m.toFixed(2) }, g);
    el("title", {}, c).textContent = `${p.label}: held-out mean error ${p.mean_error_m.toFixed(2)} m over ${p.n} scan${p.n === 1 ? "" : "s"}`;
  }
}

// --- sessions: live, replayed ----------------------------------------------------------------

function colorOf(sid) {
  let h = 0;
  for (const ch of sid) h = (h * 31 + ch.charCodeAt(0)) >>> 0;
  return COLORS[h % COLORS.length];
}

function trackOf(sid, status = "open") {
  if (!S.tracks.has(sid)) S.tracks.set(sid, { pts: [], color: colorOf(sid), status });
  return S.tracks.get(sid);
}

function ellipse(cov) {
  // the 95 % ellipse of a 2x2 covariance [[sxx, sxy], [sxy, syy]] in m²: semi-axes and angle
  const [[a, b], [, d]] = cov;
  const tr = (a + d) / 2, det = Math.sqrt(Math.max(0, ((a - d) / 2) ** 2 + b * b));
  const l1 = Math.max(tr + det, 0), l2 = Math.max(tr - det, 0);
  const angle = 0.5 * Math.atan2(2 * b, a - d); // from +x towards +y (site frame)
  return { rx: Math.sqrt(CHI2_95 * l1), ry: Math.sqrt(CHI2_95 * l2), deg: (angle * 180) / Math.PI };
}

let drawPending = false;
function drawSessions() {
  const layer = document.getElementById("sessions-layer");
  if (!layer) return;
  layer.replaceChildren();
  const b = S.bounds || computeBounds();
  for (const [sid, tr] of S.tracks) {
    const pts = S.scope === "admin" ? tr.pts.filter(onShown) : tr.pts;
    if (!pts.length) continue;
    const g = el("g", { class: `session ${tr.status}`, "data-session": sid }, layer);
    if (tr.smooth && $("show-smoothed").checked) {
      // the smoothed track (GET …/track?smoothed=true), replayed at the same pace as the live one
      const sm = tr.smooth.slice(0, tr.pts.length).filter((p) => S.scope !== "admin" || onShown(p));
      if (sm.length) {
        const line = el("polyline", { points: sm.map((p) => `${X(p.x)},${Y(p.y)}`).join(" "), class: "track smoothed", stroke: tr.color, "data-session": sid }, g);
        el("title", {}, line).textContent = `session ${sid.slice(0, 8)} · smoothed (RTS) track`;
      }
    }
    el("polyline", { points: pts.map((p) => `${X(p.x)},${Y(p.y)}`).join(" "), class: "track live", stroke: tr.color }, g);
    const m = b.size / 120;
    for (const p of pts) {
      if (p.fix_refused) {
        // a scan whose fix the innovation gate refused: a cross at the estimate it left
        const mark = el("path", { d: `M${X(p.x) - m},${Y(p.y) - m}L${X(p.x) + m},${Y(p.y) + m}M${X(p.x) - m},${Y(p.y) + m}L${X(p.x) + m},${Y(p.y) - m}`, class: "refused", "data-session": sid, "data-idx": p.idx }, g);
        el("title", {}, mark).textContent = `session ${sid.slice(0, 8)} · #${p.idx} · fix refused by the innovation gate`;
      }
      if (p.snap_refused) {
        // a scan whose landmark snap the gate refused (a beacon implausibly far): a diamond around the estimate
        const r = 1.4 * m;
        const mark = el("path", { d: `M${X(p.x)},${Y(p.y) - r}L${X(p.x) + r},${Y(p.y)}L${X(p.x)},${Y(p.y) + r}L${X(p.x) - r},${Y(p.y)}Z`, class: "snap-refused", "data-session": sid, "data-idx": p.idx }, g);
        el("title", {}, mark).textContent = `session ${sid.slice(0, 8)} · #${p.idx} · landmark snap refused by the innovation gate`;
      }
    }
    const last = pts[pts.length - 1];
    if (last.covariance) {
      const e = ellipse(last.covariance);
      el("ellipse", {
        cx: X(last.x), cy: Y(last.y), rx: e.rx, ry: e.ry, class: "ellipse", fill: tr.color, stroke: tr.color,
        transform: `rotate(${-e.deg} ${X(last.x)} ${Y(last.y)})`,
      }, g);
    }
    const dot = el("circle", { cx: X(last.x), cy: Y(last.y), r: b.size / 150, class: "pos", fill: tr.color, stroke: "#fff", "data-session": sid, "data-idx": last.idx }, g);
    el("title", {}, dot).textContent = `session ${sid.slice(0, 8)} · #${last.idx} · (${last.x.toFixed(2)}, ${last.y.toFixed(2)}) m · floor ${last.floor}`;
  }
}

function scheduleDraw() {
  if (drawPending) return;
  drawPending = true;
  requestAnimationFrame(() => {
    drawPending = false;
    const b = S.bounds;
    const tracksOut = b && [...S.tracks.values()].some((t) => t.pts.some((p) => p.x < b.x0 || p.x > b.x1 || p.y < b.y0 || p.y > b.y1));
    if (tracksOut) { S.bounds = null; drawMap(); } else drawSessions();
  });
}

function onEstimate(sid, data) {
  const tr = trackOf(sid);
  if (tr.pts.length && tr.pts[tr.pts.length - 1].idx >= data.idx) return; // already drawn
  tr.pts.push(data);
  if (!S.sessions.some((s) => s.id === sid)) refreshSessionsSoon();
  else {
    const meta = document.querySelector(`#sessions li[data-session="${sid}"] .meta`);
    if (meta) meta.textContent = `open · ${data.idx + 1} est.`;
  }
  scheduleDraw();
}

let refreshTimer = null;
function refreshSessionsSoon() {
  if (refreshTimer) return;
  refreshTimer = setTimeout(() => { refreshTimer = null; loadSessions(); }, 500);
}

function followSite() {
  follow(`/api/v1/sites/${S.site.id}/events`, (event, data) => {
    if (event === "estimate") onEstimate(data.session_id, data);
    else if (event === "closed") { trackOf(data.session_id).status = "closed"; refreshSessionsSoon(); scheduleDraw(); }
  });
  setStatus("live");
}

// A device key has no site stream: it follows each of its open sessions (a few, newest first).
function followOwnSessions() {
  const followed = new Set();
  const go = () => {
    for (const s of S.sessions.filter((x) => x.status === "open").slice(0, 4)) {
      if (followed.has(s.id)) continue;
      followed.add(s.id);
      follow(`/api/v1/sessions/${s.id}/events`, (event, data) => {
        if (event === "estimate") onEstimate(s.id, data);
        else if (event === "closed") { trackOf(s.id).status = "closed"; refreshSessionsSoon(); scheduleDraw(); }
      }, { resume: true, endOn: "closed" });
    }
  };
  go();
  setInterval(async () => { await loadSessions(); go(); }, 5000);
  setStatus("live");
}

async function loadSessions() {
  const q = S.scope === "admin" && S.site ? `?site_id=${S.site.id}&limit=50` : "?limit=50";
  S.sessions = await api(`/api/v1/sessions${q}`);
  const ul = $("sessions");
  ul.replaceChildren();
  if (!S.sessions.length) ul.append(li("no sessions yet", ""));
  for (const s of S.sessions) {
    const item = li(`${s.id.slice(0, 8)} · ${s.filter}`, `${s.status} · ${s.track_length} est.`);
    const dot = document.createElement("span");
    dot.className = "dot";
    dot.style.background = colorOf(s.id);
    item.firstChild.prepend(dot);
    item.dataset.session = s.id;
    item.title = s.status === "open" ? "live: drawn as it moves" : "closed: click to replay";
    item.addEventListener("click", () => showSession(s));
    ul.append(item);
  }
}

async function showSession(s) {
  for (const item of $("sessions").children) item.classList.toggle("selected", item.dataset.session === s.id);
  if (s.status === "open") {
    const tr = S.tracks.get(s.id);
    if (tr && tr.pts.length && S.scope === "admin") {
      const last = tr.pts[tr.pts.length - 1];
      showFloor(last.building, last.floor);
      drawMap();
    }
    return; // its estimates come from the live stream, each with its gate marks (fix_refused, snap_refused)
  }
  // replay a closed session: its stored track and its smoothed track, drawn over a few seconds
  const [track, smooth] = await Promise.all([
    api(`/api/v1/sessions/${s.id}/track`), api(`/api/v1/sessions/${s.id}/track?smoothed=true`),
  ]);
  if (S.replayTimer) clearInterval(S.replayTimer);
  const tr = { pts: [], smooth, color: colorOf(s.id), status: "closed" };
  S.tracks.set(s.id, tr);
  if (track.length && S.scope === "admin") showFloor(track[0].building, track[0].floor);
  S.bounds = null;
  drawMap();
  let i = 0;
  const per = Math.max(1, Math.ceil(track.length / 150));
  setStatus(`replaying ${s.id.slice(0, 8)}`);
  S.replayTimer = setInterval(() => {
    for (let k = 0; k < per && i < track.length; k++, i++) tr.pts.push({ ...track[i], idx: i });
    scheduleDraw();
    if (i >= track.length) { clearInterval(S.replayTimer); S.replayTimer = null; setStatus(`replayed ${s.id.slice(0, 8)}: ${track.length} estimates`); }
  }, 40);
}

$("refresh-sessions").addEventListener("click", () => loadSessions());

// --- models ------------------------------------------------------------------------------------

async function loadAlgorithms() {
  try {
    const schema = await (await fetch("/openapi.json")).json();
    const prop = schema.components.schemas.ModelIn.properties.algorithm;
    const found = prop.enum || (prop.$ref && schema.components.schemas[prop.$ref.split("/").pop()].enum) || [];
    S.algorithms = found.length ? found : ["wknn"];
  } catch {
    S.algorithms = ["wknn"];
  }
  $("train-algorithm").replaceChildren(...S.algorithms.map((a) => {
    const o = document.createElement("option");
    o.value = o.textContent = a;
    return o;
  }));
}

const fmt = (v, digits = 2) => (v === null || v === undefined ? "–" : Number(v).toFixed(digits));

async function loadModels() {
  S.models = await api(`/api/v1/sites/${S.site.id}/models`);
  const body = $("models").tBodies[0];
  body.replaceChildren();
  for (const m of S.models) {
    const tr = document.createElement("tr");
    tr.className = m.active ? "active" : "";
    const mm = m.metrics || {};
    const cells = [m.id, m.algorithm, m.active ? `${m.status} ★` : m.status, `${fmt(mm.mean_error_m)} / ${fmt(mm.p90_error_m)}`,
      mm.floor_hit_rate === null || mm.floor_hit_rate === undefined ? "–" : `${Math.round(mm.floor_hit_rate * 100)} %`];
    for (const c of cells) { const td = document.createElement("td"); td.textContent = c; tr.append(td); }
    const td = document.createElement("td");
    if (m.status === "ready" && !m.active) {
      const b = document.createElement("button");
      b.textContent = "activate";
      b.addEventListener("click", async () => {
        try { await api(`/api/v1/sites/${S.site.id}/models/${m.id}/activate`, { method: "POST" }); } catch (err) { setStatus(err.message); }
        loadModels();
      });
      td.append(b);
    }
    if (m.error) tr.title = m.error;
    tr.append(td);
    body.append(tr);
  }
  if (!S.models.length) {
    const tr = document.createElement("tr");
    tr.innerHTML = '<td colspan="6" class="hint">no models yet</td>';
    body.append(tr);
  }
  if (S.models.some((m) => m.status === "queued" || m.status === "training")) setTimeout(() => S.site && loadModels(), 3000);
  const shown = S.errors && S.errors.model;
  await loadErrors();
  if ((S.errors && S.errors.model) !== shown) drawMap();
}

$("train-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  try {
    await api(`/api/v1/sites/${S.site.id}/models`, { method: "POST", body: JSON.stringify({ algorithm: $("train-algorithm").value }) });
    setStatus("training queued");
  } catch (err) {
    setStatus(`train: ${err.message}`);
  }
  loadModels();
});

// --- helpers ------------------------------------------------------------------------------------

function li(text, meta) {
  const item = document.createElement("li");
  const a = document.createElement("span");
  a.textContent = text;
  const b = document.createElement("span");
  b.className = "meta";
  b.textContent = meta;
  item.append(a, b);
  return item;
}

start().catch((err) => setStatus(`error: ${err.message}`));
