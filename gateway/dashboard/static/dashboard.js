// sowgate dashboard: one page, live over a WebSocket from `sowgate dashboard`.
// The seed map is one canvas written pixel by pixel (ImageData): 100 000 seeds are a few
// milliseconds of work per frame, never a DOM node per seed.
"use strict";

const CLASS_COLOURS = [[189, 189, 189], [255, 167, 38], [102, 187, 106], [239, 83, 80]];
const CLASS_NAMES = ["no spacing yet", "multiple", "good", "miss"];
const ROW_PALETTE = [[66, 165, 245], [255, 202, 40], [171, 71, 188], [38, 198, 218],
  [255, 112, 67], [156, 204, 101], [236, 64, 122], [141, 110, 99], [120, 144, 156],
  [255, 238, 88], [92, 107, 192], [0, 150, 136]];

const app = {
  config: { commands: [], units: { rate: "kg/ha", speed: "km/h" }, machine_id: null, tile_url: null },
  machines: new Map(), // id -> {summary, xs, ys, rows, cls, n}
  selected: null,
  origin: null,
  view: { cx: 0, cy: 0, scale: 8, follow: true, fit: false },
  colourBy: "class",
  dirty: true,
  draws: [], // {seeds, t}: read by the browser tests and the benchmark
  chart: null,
  pending: new Map(), // request_id -> log <li>
  tiles: new Map(),
  // the fleet view (farm database): cells of the day's map, read by the tests and benchmark
  history: { ready: false, field: null, draws: [], colourBy: "class", quality: {}, alarms: null },
};
window.sowgate = app;

function $(id) { return document.getElementById(id); }
function fmt(v, digits, unit) {
  if (v === null || v === undefined) return "–";
  return (typeof v === "number" ? v.toFixed(digits) : String(v)) + (unit ? " " + unit : "");
}
function clock(seconds) {
  return new Date(seconds * 1000).toLocaleTimeString([], { hour: "2-digit", minute: "2-digit", second: "2-digit", hour12: false });
}
function time(iso) {
  if (!iso) return "";
  const d = new Date(iso);
  return isNaN(d) ? iso : clock(d.getTime() / 1000);
}

// ---- machines and seeds ---------------------------------------------------------------------

function machine(id) {
  let m = app.machines.get(id);
  if (!m) {
    const cap = 1 << 14;
    m = { summary: null, n: 0, xs: new Float32Array(cap), ys: new Float32Array(cap),
      rows: new Uint8Array(cap), cls: new Uint8Array(cap) };
    app.machines.set(id, m);
  }
  return m;
}

function addSeeds(m, flat) {
  const count = flat.length / 4;
  if (m.n + count > m.xs.length) {
    let cap = m.xs.length;
    while (cap < m.n + count) cap *= 2;
    for (const k of ["xs", "ys"]) { const a = new Float32Array(cap); a.set(m[k].subarray(0, m.n)); m[k] = a; }
    for (const k of ["rows", "cls"]) { const a = new Uint8Array(cap); a.set(m[k].subarray(0, m.n)); m[k] = a; }
  }
  for (let i = 0, j = m.n; i < flat.length; i += 4, j++) {
    m.xs[j] = flat[i]; m.ys[j] = flat[i + 1]; m.rows[j] = flat[i + 2]; m.cls[j] = flat[i + 3];
  }
  m.n += count;
}

function applyMachine(msg, replaceSeeds) {
  const m = machine(msg.machine_id);
  if (replaceSeeds) m.n = 0;
  if (msg.seeds && msg.seeds.length) addSeeds(m, msg.seeds);
  const { seeds, rate, rate_new, ...summary } = msg;
  m.summary = summary;
  if (rate) m.rate = rate;
  if (rate_new && rate_new.length) {
    m.rate = (m.rate || []).concat(rate_new);
    const since = m.rate[m.rate.length - 1][0] - 600;
    while (m.rate.length && m.rate[0][0] < since) m.rate.shift();
  }
  if (!app.selected) {
    // ?machine=ID picks one (a bookmark per seeder); else the config's own, else the first
    const wanted = new URLSearchParams(location.search).get("machine");
    if (wanted && wanted !== msg.machine_id && !app.machines.has(wanted)) return;
    select(wanted || (app.config.machine_id && app.machines.has(app.config.machine_id)
      ? app.config.machine_id : msg.machine_id));
  }
  app.dirty = true;
}

function select(id) {
  app.selected = id;
  renderMachineTabs();
  renderAll();
}

// ---- the WebSocket --------------------------------------------------------------------------

function connect() {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  const ws = new WebSocket(`${proto}//${location.host}/ws`);
  const link = $("link");
  ws.onopen = () => { link.dataset.state = "open"; link.textContent = "live"; };
  ws.onclose = () => {
    link.dataset.state = "closed";
    link.textContent = "dashboard server unreachable: retrying…";
    setTimeout(connect, 1000);
  };
  ws.onmessage = (ev) => handle(JSON.parse(ev.data));
}

function handle(msg) {
  switch (msg.type) {
    case "config":
      app.config = msg;
      setupControls();
      if (msg.history && !app.history.ready) setupHistory();
      else if (!msg.history) $("history").hidden = true;
      for (const el of document.querySelectorAll("[data-unit]")) el.textContent = msg.units[el.dataset.unit] || "";
      break;
    case "snapshot":
      app.origin = msg.origin;
      showBroker(msg.broker);
      for (const [id, m] of Object.entries(msg.machines)) applyMachine(m, true);
      renderAll();
      break;
    case "origin": app.origin = msg.origin; break;
    case "broker": showBroker(msg); break;
    case "machine": applyMachine(msg, false); renderAll(); break;
    case "ack": showAck(msg); break;
  }
}

function showBroker(b) {
  const el = $("broker");
  app.broker = b;
  if (b.connected) { el.hidden = true; el.textContent = ""; }
  else {
    el.hidden = false;
    el.textContent = "MQTT broker connection lost: the values below are not live. Reconnecting…"
      + (b.error ? ` (${b.error})` : "");
  }
  const detail = $("nodata-detail");
  detail.textContent = b.connected
    ? "Connected to the MQTT broker; no seeder has published yet."
    : "Not connected to the MQTT broker yet: reconnecting…";
}

// ---- panels ---------------------------------------------------------------------------------

function renderMachineTabs() {
  const nav = $("machines");
  const ids = [...app.machines.keys()].sort();
  nav.replaceChildren(...ids.map((id) => {
    const b = document.createElement("button");
    b.textContent = id;
    b.setAttribute("aria-pressed", String(id === app.selected));
    b.onclick = () => select(id);
    return b;
  }));
}

function renderAll() {
  const m = app.selected && app.machines.get(app.selected);
  $("nodata").hidden = !!m;
  $("main").hidden = !m;
  if (!m || !m.summary) return;
  if (app.machines.size > 1 && $("machines").children.length !== app.machines.size) renderMachineTabs();
  const s = m.summary, st = s.state || {}, u = app.config.units;
  $("machine-id").textContent = s.machine_id;
  const status = $("status");
  status.textContent = s.status || "status unknown";
  status.className = "badge " + (s.status || "");
  $("work-state").textContent = s.state ? st.work_state : "no state yet";
  $("speed").textContent = fmt(st.speed_kmh, 1, u.speed);
  $("speed-source").textContent = st.speed_source ? `(${st.speed_source})` : "";
  $("crop").textContent = st.crop || "–";
  $("target-rate").textContent = fmt(st.target_rate_kg_ha, 1, u.rate);
  $("commanded-rate").textContent = fmt(st.commanded_rate_kg_ha, 1, u.rate);
  $("motor").textContent = fmt(st.motor_duty_pct, 1, "%");
  $("fan").textContent = fmt(st.fan_duty_pct, 1, "%");
  $("tilt").textContent = fmt(st.tilt_deg, 1, "°") + (st.raised === true ? " (raised)" : st.raised === false ? " (lowered)" : "");
  $("gnss-fix").textContent = st.gnss_fix || "–";
  // a demo or a first headland is hundredths of a hectare: 0.00 ha said nothing moved
  $("area").textContent = fmt(st.area_ha, st.area_ha < 10 ? 3 : 2, u.area || "ha");
  $("mass").textContent = fmt(st.seed_mass_kg, st.seed_mass_kg < 10 ? 3 : 1, u.mass || "kg");
  $("applied-rate").textContent = appliedText(m.rate || [], st, u.rate);
  const cropSelect = $("rate-crop");
  if (st.crop && !cropSelect.dataset.chosen && cropSelect.value !== st.crop) {
    cropSelect.value = st.crop;  // the machine's crop, until the user picks another
    if (cropSelect.onchange) cropSelect.onchange();
  }
  $("state-utc").textContent = st.utc ? time(st.utc) : "–";
  const dev = $("devices");
  const devices = Object.entries(st.devices || {});
  dev.replaceChildren(...devices.map(([name, ok], i) => {
    const span = document.createElement("span");
    span.textContent = (i ? ", " : "") + name + (ok ? "" : " (not answering)");
    if (!ok) span.className = "dev-off";
    return span;
  }));
  if (!devices.length) dev.textContent = "–";
  $("seed-count").textContent = String(m.n);
  renderAlarms(s);
  renderRows(s.quality || {}, (st.row_monitor && st.row_monitor.rows) || {});
  renderChart(m.rate || []);
}

// The newest applied rate (seed mass over area since the last one, drawn in the chart);
// until the first, say why the line is not there yet rather than show nothing.
function appliedText(rate, st, unit) {
  for (let i = rate.length - 1; i >= 0; i--) {
    if (rate[i][3] !== null && rate[i][3] !== undefined) return fmt(rate[i][3], 1, unit);
  }
  return st.work_state === "seeding" ? "measuring…" : "–";
}

function renderAlarms(s) {
  const body = $("alarms").querySelector("tbody");
  // active and unacknowledged first, newest first within each
  const list = [...(s.alarms || [])].reverse().sort((a, b) =>
    (Number(b.active || !b.acknowledged) - Number(a.active || !a.acknowledged)));
  $("alarms-none").hidden = list.length > 0;
  $("alarms").hidden = list.length === 0;
  const canAck = app.config.commands.includes("ack_alarm");
  body.replaceChildren(...list.map((a) => {
    const tr = document.createElement("tr");
    const unacked = a.severity === "critical" && !a.acknowledged;
    tr.className = `${a.active ? "active" : "cleared"} ${a.severity}${unacked ? " unacked" : ""}`;
    tr.dataset.code = a.code;
    const cells = [
      `<span class="sev ${a.severity}">${a.severity}</span>`,
      `<code></code><br><span class="msg"></span>`,
      time(a.raised),
      a.active ? "active" : time(a.cleared) + (a.ended === "offline" ? " (sowgate offline)" : ""),
      "",
    ];
    tr.innerHTML = cells.map((c) => `<td>${c}</td>`).join("");
    tr.querySelector("code").textContent = a.code;
    tr.querySelector(".msg").textContent = a.message;
    if (unacked && canAck) {
      const b = document.createElement("button");
      b.textContent = "Acknowledge";
      b.className = "ack-alarm";
      b.onclick = () => sendCommand("ack_alarm", { code: a.code });
      tr.lastChild.appendChild(b);
    } else if (unacked) {
      tr.lastChild.textContent = "to acknowledge";
    }
    return tr;
  }));
}

function bar(cls, v) {
  const w = v === null || v === undefined ? 0 : Math.max(0, Math.min(100, v));
  return `<div class="bar ${cls}"><span style="width:${w}%"></span><b>${fmt(v, 1, "%")}</b></div>`;
}

// Each row's spacing quality (from the seeds received) beside the row monitor's verdict (from
// the state message): a blocked, skipping or chattering row is marked, even one with no seeds.
function renderRows(quality, monitor) {
  const body = $("rows").querySelector("tbody");
  const rows = [...new Set([...Object.keys(quality), ...Object.keys(monitor)].map(Number))]
    .sort((a, b) => a - b);
  const empty = { quality_of_feed_index: null, multiples_index: null, miss_index: null, precision: null, n: 0 };
  body.innerHTML = rows.length ? rows.map((r) => {
    const q = quality[r] || empty;
    const st = (monitor[r] && monitor[r].state) || "";
    const marked = ["blocked", "skipping", "chattering"].includes(st);
    const label = marked ? st : (st === "ok" ? "ok" : "–");
    return `<tr data-row="${r}"${marked ? ` class="row-${st}"` : ""} data-state="${st}">` +
      `<td>${r}</td><td class="row-state">${label}</td><td>${bar("q", q.quality_of_feed_index)}</td>` +
      `<td>${bar("m", q.multiples_index)}</td><td>${bar("s", q.miss_index)}</td>` +
      `<td>${fmt(q.precision, 1, "%")}</td><td>${q.n}</td></tr>`;
  }).join("") : `<tr><td colspan="7" class="muted">no seed spacings yet</td></tr>`;
}

function renderChart(rate) {
  const el = $("rate-chart");
  const data = [rate.map((r) => r[0]), rate.map((r) => r[1]), rate.map((r) => r[2]), rate.map((r) => r[3])];
  if (typeof uPlot === "undefined") return;
  const width = Math.max(300, el.clientWidth || 600);
  if (!app.chart) {
    const unit = app.config.units.rate;
    app.chart = new uPlot({
      width, height: 200,
      scales: { x: { time: true } },
      // values only in the labels: "--" under every series until hovered read as "no data"
      legend: { live: false },
      series: [{}, { label: `target (${unit})`, stroke: "#2e7d32", width: 2 },
        // 0 on headlands and stops: said in the label and under the chart
        { label: `commanded (${unit}; 0 = not sowing)`, stroke: "#1565c0", dash: [4, 4] },
        // a point every ~50 g of seed, on top of the target when all is well: big enough to see
        { label: `applied (${unit})`, stroke: "#ef6c00", width: 2, spanGaps: true,
          points: { show: true, size: 9, fill: "#ef6c00" } }],
      // clock time on one line (uPlot's default adds the date under some ticks, overlapping)
      axes: [{ space: 70, values: (_u, ticks) => ticks.map(clock) }, { label: unit }],
    }, data, el);
  } else {
    app.chart.setData(data);
    if (Math.abs(app.chart.width - width) > 20) app.chart.setSize({ width, height: 200 });
  }
}

// ---- commands -------------------------------------------------------------------------------

function setupControls() {
  const cmds = app.config.commands;
  $("controls").hidden = !["start", "stop", "rate"].some((c) => cmds.includes(c));
  $("cmd-start").hidden = !cmds.includes("start");
  $("cmd-stop").hidden = !cmds.includes("stop");
  $("rate-form").hidden = !cmds.includes("rate");
  $("cmd-start").onclick = () => sendCommand("start", {});
  $("cmd-stop").onclick = () => sendCommand("stop", {});
  // the crops the config knows, each with its rate range: no free text to misspell
  const crops = app.config.crops || {};
  const select = $("rate-crop");
  select.replaceChildren(...Object.keys(crops).map((name) => {
    const option = document.createElement("option");
    option.value = name;
    option.textContent = name;
    return option;
  }));
  select.onchange = () => {
    const range = crops[select.value];
    // the range as a hint; the machine judges the value (and says why it refuses one)
    $("rate-value").placeholder = range ? `${range[0]}–${range[1]}` : "";
  };
  select.addEventListener("input", () => { select.dataset.chosen = "1"; });
  select.onchange();
  $("rate-form").onsubmit = (ev) => {
    ev.preventDefault();
    sendCommand("rate", { crop: select.value, rate_kg_ha: Number($("rate-value").value) });
  };
}

async function sendCommand(name, payload) {
  const li = document.createElement("li");
  li.className = "pending";
  li.dataset.command = name;
  li.textContent = `${name}: sending…`;
  $("cmd-log").prepend(li);
  try {
    const resp = await fetch("/api/command", {
      method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ machine_id: app.selected, command: name, payload }),
    });
    const body = await resp.json();
    if (!body.ok) { li.className = "error"; li.textContent = `${name}: not sent: ${body.error}`; return; }
    li.textContent = `${name}: sent, waiting for the machine's answer…`;
    app.pending.set(body.request_id, li);
    setTimeout(() => {
      if (app.pending.get(body.request_id) === li) {
        app.pending.delete(body.request_id);
        li.className = "error";
        li.textContent = `${name}: no answer from the machine in 10 s: treat it as not executed`;
      }
    }, 10000);
  } catch (err) {
    li.className = "error";
    li.textContent = `${name}: not sent: ${err}`;
  }
}

function showAck(msg) {
  const li = msg.request_id && app.pending.get(msg.request_id);
  if (!li) return; // another dashboard's command
  app.pending.delete(msg.request_id);
  li.className = msg.ok ? "ok" : "error";
  li.textContent = msg.ok
    ? `${msg.command}: done${msg.message ? ": " + msg.message : ""}`
    : `${msg.command}: refused: ${msg.error}`;
}

// ---- the seed map ---------------------------------------------------------------------------

function colourOf(m, i) {
  return app.colourBy === "row" ? ROW_PALETTE[(m.rows[i] - 1) % ROW_PALETTE.length] : CLASS_COLOURS[m.cls[i]];
}

function renderLegend(m) {
  const items = app.colourBy === "row"
    ? [...new Set(Array.from(m.rows.subarray(0, Math.min(m.n, 5000))))].sort((a, b) => a - b)
        .map((r) => [`row ${r}`, ROW_PALETTE[(r - 1) % ROW_PALETTE.length]])
    : CLASS_NAMES.map((n, i) => [n, CLASS_COLOURS[i]]);
  $("legend").innerHTML = items.map(([n, c]) => `<span><i style="background:rgb(${c})"></i>${n}</span>`).join("")
    + `<span class="muted">grid: 10 m · local metres from the first seed</span>`;
}

function fitView(m, w, h) {
  let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
  for (let i = 0; i < m.n; i++) {
    const x = m.xs[i], y = m.ys[i];
    if (x < x0) x0 = x; if (x > x1) x1 = x; if (y < y0) y0 = y; if (y > y1) y1 = y;
  }
  if (!isFinite(x0)) return;
  app.view.cx = (x0 + x1) / 2; app.view.cy = (y0 + y1) / 2;
  app.view.scale = Math.min(w / Math.max(x1 - x0 + 4, 4), h / Math.max(y1 - y0 + 4, 4));
}

function draw() {
  requestAnimationFrame(draw);
  if (!app.dirty) return;
  app.dirty = false;
  const m = app.selected && app.machines.get(app.selected);
  const canvas = $("map");
  if (!m || $("main").hidden) return;
  const w = canvas.clientWidth, h = canvas.clientHeight;
  if (!w || !h) return;
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  const started = performance.now();
  const ctx = canvas.getContext("2d", { willReadFrequently: true });
  const v = app.view;
  if (v.fit) fitView(m, w, h);
  else if (v.follow && m.n) { v.cx = m.xs[m.n - 1]; v.cy = m.ys[m.n - 1]; }
  ctx.fillStyle = "#3b3326";
  ctx.fillRect(0, 0, w, h);
  drawTiles(ctx, w, h);
  const img = ctx.getImageData(0, 0, w, h);
  const px = new Uint32Array(img.data.buffer);
  const palette = (app.colourBy === "row" ? ROW_PALETTE : CLASS_COLOURS)
    .map(([r, g, b]) => (255 << 24) | (b << 16) | (g << 8) | r);
  const byRow = app.colourBy === "row";
  const s = v.scale, ox = w / 2 - v.cx * s, oy = h / 2 + v.cy * s;
  const dot = s >= 20 ? 3 : s >= 4 ? 2 : 1;
  const xs = m.xs, ys = m.ys, rows = m.rows, cls = m.cls, n = m.n;
  const np = palette.length;
  for (let i = 0; i < n; i++) {
    const x = (ox + xs[i] * s) | 0, y = (oy - ys[i] * s) | 0;
    if (x < 0 || y < 0 || x + dot > w || y + dot > h) continue;
    const c = byRow ? palette[(rows[i] + np - 1) % np] : palette[cls[i]];
    for (let dy = 0; dy < dot; dy++) {
      const base = (y + dy) * w + x;
      for (let dx = 0; dx < dot; dx++) px[base + dx] = c;
    }
  }
  ctx.putImageData(img, 0, 0);
  drawGrid(ctx, w, h, ox, oy, s);
  if (n) { // the machine: its latest seed
    const x = ox + xs[n - 1] * s, y = oy - ys[n - 1] * s;
    ctx.strokeStyle = "#fff"; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.arc(x, y, 7, 0, 2 * Math.PI); ctx.stroke();
  }
  renderLegend(m);
  const t = performance.now();
  app.draws.push({ seeds: n, t, ms: t - started });
  if (app.draws.length > 100) app.draws.shift();
}

function drawGrid(ctx, w, h, ox, oy, s) {
  const step = s * 10 >= 20 ? 10 : s * 100 >= 20 ? 100 : 1000;
  ctx.strokeStyle = "rgba(255,255,255,0.12)"; ctx.lineWidth = 1;
  ctx.beginPath();
  for (let gx = Math.ceil(-ox / s / step) * step; ox + gx * s < w; gx += step) { ctx.moveTo(ox + gx * s, 0); ctx.lineTo(ox + gx * s, h); }
  for (let gy = Math.floor(oy / s / step) * step; oy - gy * s < h; gy -= step) { ctx.moveTo(0, oy - gy * s); ctx.lineTo(w, oy - gy * s); }
  ctx.stroke();
}

// Background tiles only where [dashboard] tile_url is configured (an office with internet);
// the cab box draws on the plain background.
function drawTiles(ctx, w, h) {
  const url = app.config.tile_url, o = app.origin;
  if (!url || !o) return;
  const R = 6371008.8, k = Math.PI / 180 * R, cos = Math.cos(o[0] * Math.PI / 180), v = app.view;
  const toLatLon = (x, y) => [o[0] + y / k, o[1] + x / (k * cos)];
  const z = Math.max(1, Math.min(19, Math.round(Math.log2(v.scale * 156543.03 * cos))));
  const tileXY = ([lat, lon]) => {
    const n = 2 ** z, r = lat * Math.PI / 180;
    return [(lon + 180) / 360 * n, (1 - Math.log(Math.tan(r) + 1 / Math.cos(r)) / Math.PI) / 2 * n];
  };
  const toLocal = (tx, ty) => {
    const n = 2 ** z, lon = tx / n * 360 - 180;
    const lat = Math.atan(Math.sinh(Math.PI * (1 - 2 * ty / n))) * 180 / Math.PI;
    return [(lon - o[1]) * k * cos, (lat - o[0]) * k];
  };
  const [ax, ay] = tileXY(toLatLon(v.cx - w / 2 / v.scale, v.cy + h / 2 / v.scale));
  const [bx, by] = tileXY(toLatLon(v.cx + w / 2 / v.scale, v.cy - h / 2 / v.scale));
  for (let tx = Math.floor(ax); tx <= Math.floor(bx); tx++) {
    for (let ty = Math.floor(ay); ty <= Math.floor(by); ty++) {
      const key = `${z}/${tx}/${ty}`;
      let img = app.tiles.get(key);
      if (!img) {
        img = new Image(); img.crossOrigin = "anonymous";
        img.onload = () => { app.dirty = true; };
        img.src = url.replace("{z}", z).replace("{x}", tx).replace("{y}", ty);
        app.tiles.set(key, img);
      }
      if (!img.complete || !img.naturalWidth) continue;
      const [x0, y0] = toLocal(tx, ty), [x1, y1] = toLocal(tx + 1, ty + 1);
      const sx = w / 2 + (x0 - v.cx) * v.scale, sy = h / 2 - (y0 - v.cy) * v.scale;
      ctx.drawImage(img, sx, sy, (x1 - x0) * v.scale, (y0 - y1) * v.scale);
    }
  }
}

function setupMap() {
  const canvas = $("map");
  canvas.addEventListener("wheel", (ev) => {
    ev.preventDefault();
    app.view.fit = false;
    app.view.scale = Math.max(0.05, Math.min(200, app.view.scale * (ev.deltaY < 0 ? 1.25 : 0.8)));
    app.dirty = true;
  }, { passive: false });
  let drag = null;
  canvas.addEventListener("pointerdown", (ev) => { drag = [ev.clientX, ev.clientY]; });
  window.addEventListener("pointerup", () => { drag = null; });
  canvas.addEventListener("pointermove", (ev) => {
    if (!drag) return;
    app.view.cx -= (ev.clientX - drag[0]) / app.view.scale;
    app.view.cy += (ev.clientY - drag[1]) / app.view.scale;
    drag = [ev.clientX, ev.clientY];
    app.view.follow = false; app.view.fit = false; $("follow").checked = false;
    app.dirty = true;
  });
  $("follow").onchange = (ev) => { app.view.follow = ev.target.checked; if (app.view.follow) app.view.fit = false; app.dirty = true; };
  $("fit").onclick = () => { app.view.fit = true; app.view.follow = false; $("follow").checked = false; app.dirty = true; };
  $("colour").onchange = (ev) => { app.colourBy = ev.target.value; app.dirty = true; };
  window.addEventListener("resize", () => { app.dirty = true; });
}

// ---- the fleet view: a day of every machine from the farm database ----------------------------
// The server thins the day to one cell per grid square (GET /api/history/field); the page
// draws the cells, then fills the machines' gaps, per-row quality and the alarm timeline.

const MACHINE_PALETTE = ROW_PALETTE;

async function getJSON(url) {
  const resp = await fetch(url, { headers: { Accept: "application/json" } });
  const body = await resp.json().catch(() => ({ error: `HTTP ${resp.status}` }));
  if (!resp.ok) throw new Error(body.error || `HTTP ${resp.status}`);
  return body;
}

async function setupHistory(known) {
  const h = app.history;
  h.ready = true;
  $("history").hidden = false;
  $("h-colour").onchange = (ev) => { h.colourBy = ev.target.value; drawHistory(); };
  window.addEventListener("resize", () => drawHistory());
  const wanted = new URLSearchParams(location.search).get("day");
  let days = known || [];
  if (!known) {
    try { days = (await getJSON("/api/history/days")).days; }
    catch (err) { $("h-status").textContent = `farm database: ${err.message}`; return; }
  }
  if (wanted && !days.includes(wanted)) days.unshift(wanted);
  const select = $("h-day");
  select.replaceChildren(...days.map((d) => { const o = document.createElement("option"); o.value = d; o.textContent = d; return o; }));
  select.onchange = () => loadDay(select.value);
  if (days.length) loadDay(wanted || days[0]);
  else $("h-status").textContent = "the farm database holds no day yet";
}

async function loadDay(day) {
  const h = app.history;
  h.day = day;
  $("h-day").value = day;
  $("h-status").textContent = "loading…";
  let field;
  try {
    // a big day comes first as a page sample (drawn at once), then whole
    const pre = h.prefetch && h.prefetch.day === day ? h.prefetch.answer : null;
    h.prefetch = null;
    field = await (pre || getJSON(`/api/history/field?day=${encodeURIComponent(day)}&preview=1`));
    if (h.day !== day) return;
    if (!field.complete) {
      showField(field);
      $("h-status").textContent = `preview: a ${field.sample_pct.toFixed(0)} % sample of the day; the whole day is loading…`;
      field = await getJSON(`/api/history/field?day=${encodeURIComponent(day)}`);
    }
  } catch (err) { $("h-status").textContent = `farm database: ${err.message}`; return; }
  if (h.day !== day) return;
  showField(field);
  renderHistoryMachines();
  getJSON(`/api/history/alarms?day=${encodeURIComponent(day)}`)
    .then((a) => { if (h.day === day) { h.alarms = a; renderTimeline(); } })
    .catch((err) => { $("h-alarm-count").textContent = `(${err.message})`; });
  for (const m of field.machines) {
    try {
      const q = await getJSON(`/api/history/quality?day=${encodeURIComponent(day)}&machine=${encodeURIComponent(m.machine_id)}`);
      if (h.day !== day) return;
      h.quality[m.machine_id] = q;
      renderHistoryQuality();
    } catch (err) { h.quality[m.machine_id] = { error: err.message }; renderHistoryQuality(); }
  }
}

function showField(field) {
  const h = app.history;
  h.field = field;
  h.quality = {};
  $("h-seeds").textContent = field.seeds.toLocaleString("en");
  $("h-cells").textContent = (field.cells.length / 4).toLocaleString("en");
  $("h-cell-m").textContent = field.cell_m === null ? "–" : field.cell_m.toFixed(2);
  $("h-status").textContent = field.seeds ? "" : "no seed records on this day";
  drawHistory();
}

function drawHistory() {
  const h = app.history, f = h.field, canvas = $("h-map");
  if (!f || $("history").hidden) return;
  const started = performance.now();
  const w = canvas.clientWidth, ht = canvas.clientHeight;
  if (!w || !ht) return;
  if (canvas.width !== w || canvas.height !== ht) { canvas.width = w; canvas.height = ht; }
  const ctx = canvas.getContext("2d", { willReadFrequently: true });
  ctx.fillStyle = "#3b3326";
  ctx.fillRect(0, 0, w, ht);
  const cells = f.cells, n = cells.length / 4;
  if (n) {
    const [ex, ey] = f.extent_cells;
    const s = Math.min((w - 8) / (ex + 1), (ht - 8) / (ey + 1));
    const ox = (w - (ex + 1) * s) / 2, oy = (ht + (ey + 1) * s) / 2;
    const size = Math.max(1, Math.ceil(s));
    const img = ctx.getImageData(0, 0, w, ht);
    const px = new Uint32Array(img.data.buffer);
    const byMachine = h.colourBy === "machine";
    const palette = (byMachine ? MACHINE_PALETTE : CLASS_COLOURS)
      .map(([r, g, b]) => (255 << 24) | (b << 16) | (g << 8) | r);
    for (let i = 0; i < cells.length; i += 4) {
      const x = (ox + cells[i] * s) | 0, y = (oy - (cells[i + 1] + 1) * s) | 0;
      const c = byMachine ? palette[cells[i + 2] % palette.length] : palette[cells[i + 3]];
      for (let dy = 0; dy < size; dy++) {
        const yy = y + dy;
        if (yy < 0 || yy >= ht) continue;
        const base = yy * w;
        for (let dx = 0; dx < size; dx++) { const xx = x + dx; if (xx >= 0 && xx < w) px[base + xx] = c; }
      }
    }
    ctx.putImageData(img, 0, 0);
  }
  const items = h.colourBy === "machine"
    ? f.machines.map((m, i) => [m.machine_id, MACHINE_PALETTE[i % MACHINE_PALETTE.length]])
    : CLASS_NAMES.map((name, i) => [name, CLASS_COLOURS[i]]);
  $("h-legend").innerHTML = items.map(([name, c]) => `<span><i style="background:rgb(${c})"></i></span>`).join("")
    + `<span class="muted">each square: the class most of its seeds have</span>`;
  // names as text, never as HTML (machine ids come from the database)
  $("h-legend").querySelectorAll("span > i").forEach((el, i) => el.after(items[i][0]));
  const t = performance.now();
  h.draws.push({ day: f.day, cells: n, seeds: f.seeds, complete: f.complete, t, ms: t - started });
  if (h.draws.length > 100) h.draws.shift();
}

function cell(tr, text) { const td = document.createElement("td"); td.textContent = text; tr.appendChild(td); return td; }

function renderHistoryMachines() {
  const f = app.history.field;
  const body = $("h-machines").querySelector("tbody");
  body.replaceChildren(...f.machines.map((m) => {
    const tr = document.createElement("tr");
    tr.dataset.machine = m.machine_id;
    if (m.gap_runs) tr.className = "has-gaps";
    cell(tr, m.machine_id);
    cell(tr, m.seeds.toLocaleString("en"));
    cell(tr, time(m.first_utc));
    cell(tr, time(m.last_utc));
    cell(tr, m.x_ref_m === null ? "–" : `${(m.x_ref_m * 100).toFixed(1)} cm${m.target_configured ? " (target)" : " (median)"}`);
    cell(tr, m.gaps_text).className = "gaps";
    return tr;
  }));
}

function renderHistoryQuality() {
  const h = app.history, el = $("h-quality");
  el.replaceChildren(...h.field.machines.map((m) => {
    const q = h.quality[m.machine_id];
    const div = document.createElement("div");
    div.dataset.machine = m.machine_id;
    const title = document.createElement("h3");
    title.textContent = m.machine_id;
    div.appendChild(title);
    if (!q) { div.append("computing…"); return div; }
    if (q.error) { div.append(`not available: ${q.error}`); return div; }
    const table = document.createElement("table");
    table.className = "rows";
    table.innerHTML = "<thead><tr><th>row</th><th>quality of feed</th><th>multiples</th><th>misses</th><th>precision</th><th>spacings</th></tr></thead>";
    const tbody = document.createElement("tbody");
    tbody.innerHTML = Object.entries(q.rows).map(([r, v]) =>
      `<tr data-row="${Number(r)}"><td>${Number(r)}</td><td>${bar("q", v.quality_of_feed_index)}</td>` +
      `<td>${bar("m", v.multiples_index)}</td><td>${bar("s", v.miss_index)}</td>` +
      `<td>${fmt(v.precision, 1, "%")}</td><td>${Number(v.n)}</td></tr>`).join("");
    table.appendChild(tbody);
    div.appendChild(table);
    return div;
  }));
}

// Raised → cleared periods per machine and code, as bars on the day's time axis.
function renderTimeline() {
  const h = app.history, a = h.alarms, el = $("h-alarms");
  $("h-alarm-count").textContent = a.total > a.events.length
    ? `(${a.events.length} of ${a.total} events)` : `(${a.total} events)`;
  if (!a.events.length) { el.textContent = "no alarm on this day"; return; }
  const ms = (iso) => new Date(iso).getTime();
  const machines = h.field ? h.field.machines : [];
  let t0 = Math.min(...a.events.map((e) => ms(e.utc))), t1 = Math.max(...a.events.map((e) => ms(e.utc)));
  for (const m of machines) { t0 = Math.min(t0, ms(m.first_utc)); t1 = Math.max(t1, ms(m.last_utc)); }
  const span = Math.max(1, t1 - t0);
  const lanes = new Map();
  const open = new Map();
  for (const e of a.events) {
    if (!lanes.has(e.machine_id)) lanes.set(e.machine_id, []);
    const key = `${e.machine_id} ${e.code}`;
    if (e.active && !open.has(key)) open.set(key, e);
    else if (!e.active && open.has(key)) {
      const r = open.get(key); open.delete(key);
      lanes.get(e.machine_id).push([r, ms(r.utc), ms(e.utc)]);
    }
  }
  for (const r of open.values()) lanes.get(r.machine_id).push([r, ms(r.utc), t1]);
  const rows = [...lanes.entries()].sort().map(([mid, periods]) => {
    const lane = document.createElement("div");
    lane.className = "lane";
    lane.dataset.machine = mid;
    const name = document.createElement("span");
    name.textContent = mid;
    const track = document.createElement("div");
    track.className = "track";
    for (const [r, from, to] of periods) {
      const i = document.createElement("i");
      i.className = r.severity;
      i.style.left = `${(100 * (from - t0)) / span}%`;
      i.style.width = `${(100 * (to - from)) / span}%`;
      i.title = `${r.code}: ${time(r.utc)}–${time(new Date(to).toISOString())} ${r.message}`;
      i.dataset.code = r.code;
      track.appendChild(i);
    }
    lane.append(name, track);
    return lane;
  });
  const axis = document.createElement("div");
  axis.className = "axis";
  axis.innerHTML = `<span>${clock(t0 / 1000)}</span><span>${clock(t1 / 1000)}</span>`;
  el.replaceChildren(...rows, axis);
}

setupMap();
// ?day=: its map is asked for at once, beside the list of days (a 404 without a database)
{
  const day = new URLSearchParams(location.search).get("day");
  if (day) {
    const answer = getJSON(`/api/history/field?day=${encodeURIComponent(day)}&preview=1`);
    answer.catch(() => {});
    app.history.prefetch = { day, answer };
  }
}
// the fleet view starts without waiting for the WebSocket: /api/history/days answers 404
// when the dashboard has no farm database, and the section stays hidden
getJSON("/api/history/days").then((d) => { if (!app.history.ready) setupHistory(d.days); }).catch(() => {});
if (new URLSearchParams(location.search).get("view") === "field") $("fit").click();
connect();
requestAnimationFrame(draw);
