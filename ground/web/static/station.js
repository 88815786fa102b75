// debris-box ground station: the live view. Hand-written canvas plots, no library, nothing fetched
// from elsewhere. State from the server's WebSocket (/ws): a snapshot, then updates (4 Hz).
// window.station.plotted[sysid][plot] holds the last row drawn in each plot (the tests read it).
"use strict";

const AXES = ["#ff6b4a", "#3fcf8e", "#5b9cff"];
const station = window.station = { boxes: {}, info: {}, seq: 0, selected: null, plotted: {}, updates: 0 };

function ws_url() {
  return (location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws";
}

function connect() {
  const ws = new WebSocket(ws_url());
  const conn = document.getElementById("conn");
  ws.onopen = () => { conn.textContent = "live"; conn.className = "pill ok"; };
  ws.onclose = () => {
    conn.textContent = "disconnected: retrying"; conn.className = "pill bad";
    setTimeout(connect, 1000);
  };
  ws.onmessage = (ev) => {
    const m = JSON.parse(ev.data);
    if (m.type === "snapshot") snapshot(m); else if (m.seq > station.seq) update(m);
    station.last_message_s = Date.now() / 1000;
    render();
  };
}

function snapshot(m) {
  station.boxes = {};
  for (const [id, b] of Object.entries(m.boxes)) {
    const box = station.boxes[id] = { series: {}, state: b.state, events: b.events.slice() };
    for (const [name, s] of Object.entries(b.series)) box.series[name] = { cols: s.cols, rows: s.rows };
  }
  station.info = m.station; station.seq = m.seq; station.now_s = m.now_s;
}

function update(m) {
  const span = 14400;
  for (const [id, u] of Object.entries(m.boxes)) {
    let box = station.boxes[id];
    if (!box) box = station.boxes[id] = { series: {}, state: {}, events: [] };
    for (const name of u.reset) if (box.series[name]) box.series[name].rows = [];
    for (const [name, rows] of Object.entries(u.rows)) {
      const s = box.series[name] || (box.series[name] = { cols: [], rows: [] });
      for (const r of rows) s.rows.push(r);
      const newest = s.rows[s.rows.length - 1][0];
      let drop = 0;
      while (drop < s.rows.length && s.rows[drop][0] < newest - span) drop++;
      if (drop) s.rows.splice(0, drop);
    }
    box.state = u.state;
    for (const e of u.events) box.events.push(e);
    if (box.events.length > 200) box.events.splice(0, box.events.length - 200);
  }
  station.info = m.station; station.seq = m.seq; station.now_s = m.now_s; station.updates++;
}

// --- drawing -------------------------------------------------------------------------------------

function fmt(x, d = 2) { return x === null || x === undefined || Number.isNaN(x) ? "—" : Number(x).toFixed(d); }

function nice_ticks(lo, hi, n) {
  const step0 = (hi - lo) / Math.max(1, n);
  const mag = Math.pow(10, Math.floor(Math.log10(step0)));
  const step = [1, 2, 5, 10].map(k => k * mag).find(s => s >= step0) || step0;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9 * step; v += step) out.push(v);
  return out;
}

// lines: [{rows, col, color, dash, lo, hi (band columns: value ± k × rows[i][sigma]), sigma, k, label}]
function plot(canvas, lines, t_end, span, empty = "no data yet") {
  const dpr = window.devicePixelRatio || 1;
  const w = canvas.clientWidth, h = canvas.clientHeight;
  if (canvas.width !== Math.round(w * dpr)) { canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr); }
  const g = canvas.getContext("2d");
  g.setTransform(dpr, 0, 0, dpr, 0, 0);
  g.clearRect(0, 0, w, h);
  const L = 54, R = 8, T = 16, B = 20;
  let first = Infinity;
  for (const ln of lines) if (ln.rows.length) first = Math.min(first, ln.rows[0][0]);
  const t0 = Math.max(t_end - span, Math.min(first, t_end - 1));
  span = t_end - t0;
  let ymin = Infinity, ymax = -Infinity;
  const last = [];
  for (const ln of lines) {
    for (const r of ln.rows) {
      if (r[0] < t0) continue;
      const v = r[ln.col];
      if (v === null) continue;
      const s = ln.sigma !== undefined && r[ln.sigma] !== null ? ln.k * r[ln.sigma] : 0;
      ymin = Math.min(ymin, v - s); ymax = Math.max(ymax, v + s);
    }
  }
  g.font = "11px system-ui, sans-serif";
  g.fillStyle = "#8796a8";
  if (!isFinite(ymin)) { g.fillText(empty, L + 10, T + 20); return null; }
  if (ymax - ymin < 1e-9) { ymin -= 1; ymax += 1; }
  const pad = 0.06 * (ymax - ymin); ymin -= pad; ymax += pad;
  const X = t => L + (t - t0) / span * (w - L - R);
  const Y = v => T + (ymax - v) / (ymax - ymin) * (h - T - B);
  g.strokeStyle = "#2a3542"; g.lineWidth = 1;
  for (const v of nice_ticks(ymin, ymax, 5)) {
    g.beginPath(); g.moveTo(L, Y(v)); g.lineTo(w - R, Y(v)); g.stroke();
    g.fillText(Math.abs(v) >= 1000 ? v.toExponential(1) : +v.toPrecision(4), 4, Y(v) + 4);
  }
  for (const t of nice_ticks(t0, t_end, 6)) {
    g.beginPath(); g.moveTo(X(t), T); g.lineTo(X(t), h - B); g.stroke();
    g.fillText(t.toFixed(span < 60 ? 1 : 0) + " s", X(t) - 12, h - 5);
  }
  g.save(); g.beginPath(); g.rect(L, T, w - L - R, h - T - B); g.clip();
  for (const ln of lines) {
    const rows = ln.rows.filter(r => r[0] >= t0 && r[ln.col] !== null);
    if (!rows.length) continue;
    if (ln.sigma !== undefined) {
      g.beginPath();
      rows.forEach((r, i) => { const y = Y(r[ln.col] + ln.k * r[ln.sigma]); i ? g.lineTo(X(r[0]), y) : g.moveTo(X(r[0]), y); });
      for (let i = rows.length - 1; i >= 0; i--) g.lineTo(X(rows[i][0]), Y(rows[i][ln.col] - ln.k * rows[i][ln.sigma]));
      g.closePath(); g.globalAlpha = 0.18; g.fillStyle = ln.color; g.fill(); g.globalAlpha = 1;
    }
    g.beginPath(); g.setLineDash(ln.dash ? [5, 4] : []); g.strokeStyle = ln.color; g.lineWidth = ln.dash ? 1.2 : 1.6;
    // an angle that wraps (±180°) is not joined across the wrap
    rows.forEach((r, i) => i && !(ln.wrap && Math.abs(r[ln.col] - rows[i - 1][ln.col]) > ln.wrap / 2)
      ? g.lineTo(X(r[0]), Y(r[ln.col])) : g.moveTo(X(r[0]), Y(r[ln.col])));
    if (rows.length === 1) g.arc(X(rows[0][0]), Y(rows[0][ln.col]), 2, 0, 7);
    g.stroke(); g.setLineDash([]);
  }
  g.restore();
  let x = L + 6;
  for (const ln of lines) {
    if (!ln.label) continue;
    g.fillStyle = ln.color; g.fillText(ln.label, x, 11); x += g.measureText(ln.label).width + 12;
  }
  g.fillStyle = "#8796a8"; g.fillText(canvas.dataset.unit, w - R - g.measureText(canvas.dataset.unit).width, 11);
  return lines.map(ln => ln.rows.length ? ln.rows[ln.rows.length - 1] : null);
}

function rows(box, name) { return (box.series[name] || { rows: [] }).rows; }

function newest(box) {
  let t = -Infinity;
  for (const s of Object.values(box.series)) if (s.rows.length) t = Math.max(t, s.rows[s.rows.length - 1][0]);
  return isFinite(t) ? t : 0;
}

function draw_box(id) {
  const box = station.boxes[id], st = box.state;
  const span = Number(document.getElementById("span").value);
  const t_end = newest(box);
  const p = station.plotted[id] = {};
  const axes3 = (name, labels, extra = {}) => labels.map((lab, i) => ({ rows: rows(box, name), col: i + 1,
    color: AXES[i], label: lab, ...extra }));
  const keep = (plotname, names, drawn) => { if (drawn) names.forEach((n, i) => { if (drawn[i]) p[n] = drawn[i]; }); };
  let d = plot(document.getElementById("p-field"), axes3("field_uT", ["Bx", "By", "Bz"]), t_end, span,
    "no magnetometer samples yet");
  keep("field", ["field_uT"], d);
  const rate = axes3("rate_dps", ["ωx", "ωy", "ωz"]).map((l, i) => ({ ...l, sigma: i + 4, k: 1 }));
  const truth = axes3("truth_rate_dps", ["", "", ""], { dash: true });
  d = plot(document.getElementById("p-rate"), rate.concat(truth), t_end, span);
  keep("rate", ["rate_dps", null, null, "truth_rate_dps"], d);
  d = plot(document.getElementById("p-att"), axes3("attitude_deg", ["roll", "pitch", "yaw"], { wrap: 360 })
    .concat(axes3("truth_attitude_deg", ["", "", ""], { dash: true, wrap: 360 })), t_end, span,
    "no attitude: the box flies the fixed-field filter until it has a UTC and a TLE");
  keep("att", ["attitude_deg", null, null, "truth_attitude_deg"], d);
  const inertia = axes3("inertia_kgm2", ["Ixx", "Iyy", "Izz"]).map((l, i) => ({ ...l, sigma: i + 4, k: 1 }));
  d = plot(document.getElementById("p-inertia"), inertia, t_end, span, "no estimate: no identification experiment run");
  keep("inertia", ["inertia_kgm2"], d);
  d = plot(document.getElementById("p-sail"), axes3("sail_deg", ["yaw", "pitch"], { wrap: 360 }), t_end, span,
    st.kit ? `no attitude for the controller (source: ${st.sail ? st.sail.source : "—"})` : "no de-orbit kit reported");
  keep("sail", ["sail_deg"], d);
  d = plot(document.getElementById("p-energy"), axes3("kit_energy_J", ["pitch channel", "yaw channel"]), t_end, span,
    "no de-orbit kit reported");
  keep("energy", ["kit_energy_J"], d);
  d = plot(document.getElementById("p-backlog"), axes3("backlog_frames", ["buffered", "replayed", "dropped"]), t_end, span);
  keep("backlog", ["backlog_frames"], d);

  document.getElementById("title").textContent = `box ${id}` + (st.box_time_s !== undefined ? ` — box time ${fmt(st.box_time_s, 1)} s` : "")
    + (st.sample_rate_hz ? `, ${fmt(st.sample_rate_hz, 1)} Hz samples` : "");
  document.getElementById("method").textContent = st.method || "";
  const ver = document.getElementById("verified");
  ver.textContent = st.verified ? "signatures verified with this box's key" : "NOT VERIFIED: no key for this box";
  ver.className = st.verified ? "pill ok" : "pill warn";
  const sa = st.attitude_sigma_deg || [];
  document.getElementById("att-kv").innerHTML = `filter <b>${st.filter || "—"}</b>, 1σ (${sa.map(x => fmt(x, 2)).join(", ") || "—"}) deg`;
  const inr = st.inertia;
  document.getElementById("inertia-kv").innerHTML = inr ? `experiment <b>${inr.state}</b>, ${inr.samples} samples; `
    + ["Ixx", "Iyy", "Izz"].map((n, i) => `${n} <b>${fmt(inr.inertia_kgm2[i], 2)}</b> ± ${fmt(inr.ci95_kgm2[i], 2)}`).join(", ")
    : "no identification experiment reported";
  const k = st.kit, sail = st.sail;
  document.getElementById("kit").innerHTML = k ? `<tr><th></th><th>pitch channel</th><th>yaw channel</th></tr>`
    + [["capsule", k.capsules], ["magnet", k.magnets], ["polarity", k.polarity], ["pulses (steps)", k.pulses],
       ["energy J", k.energy_J.map(x => fmt(x, 1))], ["openings", k.capsule_openings], ["turns", k.magnet_turns],
       ["faults", k.faults]].map(([n, v]) => `<tr><td>${n}</td><td>${v[0]}</td><td>${v[1]}</td></tr>`).join("")
    + `<tr><td>controller</td><td colspan="2">${k.controller}${sail ? `, attitude ${sail.source}, yaw ${fmt(sail.yaw_deg, 1)}°, pitch ${fmt(sail.pitch_deg, 1)}°, held ${sail.held}` : ""}, interlock violations ${k.interlock_violations}</td></tr>`
    : "<tr><td>no de-orbit kit reported</td></tr>";
  const l = st.link || {}, bl = st.box_link;
  const rej = Object.entries(st.rejected || {}).map(([r, n]) => `${r} ${n}`).join(", ") || "none";
  document.getElementById("link-kv").innerHTML = `received <b>${l.received}</b>, lost <b>${l.lost}</b> (${fmt(100 * (l.loss_fraction || 0), 2)} %), `
    + `duplicates ${l.duplicates}; refused: <b>${rej}</b>`
    + (bl ? `<br>box: downlink ${bl.link_up ? "up" : "DOWN"}, backlog <b>${bl.buffered}</b>, replayed ${bl.replayed}, dropped ${bl.dropped}; `
      + `commands accepted ${bl.cmd_accepted}, uplink frames refused ${bl.uplink_rejected}` : "");
  const ev = document.getElementById("events");
  ev.innerHTML = "";
  for (const e of box.events.slice(-60).reverse()) {
    const li = document.createElement("li");
    li.className = e.severity;
    const t = document.createElement("span"); t.className = "t";
    t.textContent = new Date(e.rx_s * 1000).toISOString().slice(11, 23) + " " + e.severity;
    li.append(t, document.createTextNode(e.text));
    ev.append(li);
  }
}

function age_class(age) { return age < 3 ? "good" : age < 15 ? "stale" : "dead"; }

function render() {
  const ids = Object.keys(station.boxes).sort((a, b) => a - b);
  if (station.selected === null || !station.boxes[station.selected]) {
    const want = new URLSearchParams(location.search).get("box");
    station.selected = want && station.boxes[want] ? want : (ids[0] ?? null);
  }
  const body = document.querySelector("#fleet tbody");
  body.innerHTML = "";
  const now = station.now_s || Date.now() / 1000;
  for (const id of ids) {
    const st = station.boxes[id].state, l = st.link || {};
    const tr = document.createElement("tr");
    if (id === station.selected) tr.className = "sel";
    const age = st.last_rx_s ? now - st.last_rx_s : Infinity;
    const refused = Object.values(st.rejected || {}).reduce((a, b) => a + b, 0);
    const cells = [id, isFinite(age) ? fmt(age, 1) + " s ago" : "—", fmt(st.field_norm_uT, 2), fmt(st.rate_norm_dps, 2),
      fmt(st.truth_rate_norm_dps, 2), st.filter || "—", fmt(100 * (l.loss_fraction || 0), 2) + " %", refused,
      st.inertia ? st.inertia.state : "—", st.kit ? st.kit.controller : "—"];
    cells.forEach((c, i) => {
      const td = document.createElement("td"); td.textContent = c; td.className = "num";
      if (i === 1) td.className += " " + age_class(age);
      if (i === 7 && refused) td.className += " stale";
      tr.append(td);
    });
    tr.onclick = () => { station.selected = id; render(); };
    body.append(tr);
  }
  const s = station.info || {};
  const a = s.archive || {};
  document.getElementById("station").textContent = `${s.frames ?? 0} frames; archived ${a.frames ?? "—"}`
    + (a.error ? ` (ARCHIVE FAILED: ${a.error})` : "") + (s.verified ? "" : "; signatures NOT verified")
    + (s.other_frames ? `; ${s.other_frames} frames of ${s.other_systems} other system ids` : "")
    + (s.dropped ? `; ${s.dropped} frames dropped (station overloaded)` : "")
    + (s.view_failures ? `; ${s.view_failures} frames the view could not show (archived)` : "")
    + (s.bad_crc || s.garbage_bytes ? `; ${s.bad_crc} bad CRC, ${s.garbage_bytes} garbage bytes` : "");
  document.getElementById("nobox").hidden = ids.length > 0;
  document.getElementById("detail").hidden = station.selected === null;
  if (station.selected !== null) draw_box(station.selected);
}

document.getElementById("span").onchange = render;
window.addEventListener("resize", render);
connect();
