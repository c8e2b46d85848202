// azimuthd dashboard: draws what /events streams (service/web/hub.py has the message types).
// No library: the instruments are SVG built here. Angles arrive in degrees (the Zenoh edge).
"use strict";

const SVGNS = "http://www.w3.org/2000/svg";
const PITCH_PX_PER_DEG = 2.2;          // attitude indicator: horizon shift per degree of pitch
const MAX_EVENTS = 40;                 // per vehicle, newest first
const SHOWN_RATES = ["RAW_IMU", "HIGHRES_IMU", "SCALED_IMU", "SCALED_PRESSURE", "ATTITUDE"];
const BAD_COUNTER = /(lost|error|rejected|drops|bad|replay|overflow|stall)/;
const M_PER_DEG_LAT = 110540, M_PER_DEG_LON_EQ = 111320;   // local plane for the track (small areas)

const vehicles = new Map();            // name -> {el, events: [], track: [], fence: null, last: {}}

function svg(tag, attrs, parent) {
  const e = document.createElementNS(SVGNS, tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  if (parent) parent.appendChild(e);
  return e;
}
const isNum = (v) => typeof v === "number" && isFinite(v);
const fmt = (v, digits = 1, unit = "") => (isNum(v) ? v.toFixed(digits) + unit : "-");
function field(v, name) { return v.el.querySelector(`[data-field="${name}"]`); }
function setText(v, name, text) { const e = field(v, name); if (e && e.textContent !== text) e.textContent = text; }
function clock(unix_s) {
  if (!isNum(unix_s)) return "";
  return new Date(unix_s * 1000).toLocaleTimeString([], {hour12: false});
}

// --- building a vehicle's card --------------------------------------------------------------

function vehicle(name) {
  if (vehicles.has(name)) return vehicles.get(name);
  const tpl = document.getElementById("vehicle-template");
  const el = tpl.content.firstElementChild.cloneNode(true);
  el.dataset.vehicle = name;
  const clipId = "adi-clip-" + name;
  el.querySelector("clipPath").id = clipId;
  el.querySelector("[clip-path]").setAttribute("clip-path", `url(#${clipId})`);
  const v = {name, el, events: [], track: [], fence: null, last: {}};
  setText(v, "vehicle", name);
  buildAdi(el.querySelector(".adi"));
  buildDial(el.querySelector(".compass .dial"));
  const main = document.getElementById("vehicles");
  const after = [...main.children].find((c) => c.dataset.vehicle > name);
  main.insertBefore(el, after || null);
  vehicles.set(name, v);
  drawTrack(v);                        // says what is missing until the geofence topic comes
  return v;
}

function buildAdi(adi) {
  const ladder = adi.querySelector(".pitch-ladder");
  for (let p = -40; p <= 40; p += 10) {
    if (p === 0) continue;
    const y = -p * PITCH_PX_PER_DEG, w = p % 20 === 0 ? 26 : 14;
    svg("line", {x1: -w, y1: y, x2: w, y2: y}, ladder);
    if (p % 20 === 0) {
      svg("text", {x: w + 4, y: y + 3}, ladder).textContent = Math.abs(p);
      svg("text", {x: -w - 14, y: y + 3}, ladder).textContent = Math.abs(p);
    }
  }
  const scale = adi.querySelector(".roll-scale");
  for (const a of [-60, -45, -30, -20, -10, 0, 10, 20, 30, 45, 60]) {
    const len = a % 30 === 0 ? 10 : 6;
    svg("line", {x1: 0, y1: -92, x2: 0, y2: -92 + len, transform: `rotate(${a})`}, scale);
  }
}

function buildDial(dial) {
  for (let a = 0; a < 360; a += 5) {
    const major = a % 30 === 0;
    svg("line", {x1: 0, y1: -92, x2: 0, y2: major ? -80 : (a % 10 === 0 ? -85 : -88),
                 transform: `rotate(${a})`, class: major ? "major" : ""}, dial);
  }
  const labels = {0: "N", 90: "E", 180: "S", 270: "W"};
  for (let a = 0; a < 360; a += 30) {
    const r = 68, x = r * Math.sin(a * Math.PI / 180), y = -r * Math.cos(a * Math.PI / 180);
    const t = svg("text", {x: x.toFixed(1), y: y.toFixed(1)}, dial);
    t.textContent = labels[a] || String(a / 10);
    if (labels[a]) t.setAttribute("class", a === 0 ? "cardinal north" : "cardinal");
  }
}

// --- topics ---------------------------------------------------------------------------------

function onAttitude(v, p) {
  setText(v, "phase", p.phase || "-");
  const adi = v.el.querySelector(".adi");
  const ok = isNum(p.roll_deg) && isNum(p.pitch_deg);
  adi.classList.toggle("na", !ok);
  setText(v, "roll_deg", fmt(p.roll_deg, 1, "°"));
  setText(v, "pitch_deg", fmt(p.pitch_deg, 1, "°"));
  setText(v, "roll_sigma_deg", isNum(p.roll_sigma_deg) ? `±${p.roll_sigma_deg.toFixed(1)}` : "");
  setText(v, "pitch_sigma_deg", isNum(p.pitch_sigma_deg) ? `±${p.pitch_sigma_deg.toFixed(1)}` : "");
  if (!ok) return;
  const pitch = Math.max(-60, Math.min(60, p.pitch_deg));
  adi.querySelector(".adi-horizon").setAttribute(
    "transform", `rotate(${(-p.roll_deg).toFixed(2)}) translate(0 ${(pitch * PITCH_PX_PER_DEG).toFixed(2)})`);
  adi.querySelector(".roll-pointer").setAttribute("transform", `rotate(${(-p.roll_deg).toFixed(2)})`);
}

function wedgePath(centerDeg, halfDeg, r) {
  const h = Math.min(Math.max(halfDeg, 0.3), 179);   // at least a visible sliver
  const a0 = (centerDeg - h) * Math.PI / 180, a1 = (centerDeg + h) * Math.PI / 180;
  const p = (a) => `${(r * Math.sin(a)).toFixed(2)},${(-r * Math.cos(a)).toFixed(2)}`;
  return `M0,0 L${p(a0)} A${r},${r} 0 ${2 * h > 180 ? 1 : 0} 1 ${p(a1)} Z`;
}

function onHeading(v, p) {
  setText(v, "phase", p.phase || field(v, "phase").textContent);
  const compass = v.el.querySelector(".compass");
  const ok = p.heading_valid && isNum(p.heading_true_deg);
  compass.classList.toggle("na", !ok);
  const h = field(v, "heading_true_deg");
  h.textContent = ok ? p.heading_true_deg.toFixed(1) + "°" : "no heading";
  h.dataset.time_fc_s = isNum(p.time_fc_s) ? String(p.time_fc_s) : "";
  setText(v, "heading_sigma_deg", ok && isNum(p.heading_sigma_deg) ? `± ${p.heading_sigma_deg.toFixed(1)}° (1σ)` : "");
  setText(v, "heading_source", p.heading_source || "-");
  if (ok) {
    compass.querySelector(".needle").setAttribute("transform", `rotate(${p.heading_true_deg.toFixed(2)})`);
    compass.querySelector(".sigma-wedge").setAttribute(
      "d", wedgePath(p.heading_true_deg, isNum(p.heading_sigma_deg) ? p.heading_sigma_deg : 0, 86));
  }
  renderSources(v, p);
  renderFlags(v, p.flags || {});
}

function renderSources(v, p) {
  const key = JSON.stringify([p.heading_source, p.sources || null]);
  if (key === v.last.sourcesKey) return;       // unchanged: keep the rows (5 Hz otherwise)
  v.last.sourcesKey = key;
  const body = field(v, "sources");
  body.textContent = "";
  const used = new Set((p.heading_source || "").split("+"));
  const sources = p.sources || Object.fromEntries(
    [...used].filter((s) => s && s !== "none" && s !== "coast").map((s) => [s, {fused: true, detail: ""}]));
  const names = Object.keys(sources).sort();
  if (!names.length) {
    const tr = body.insertRow(); const td = tr.insertCell(); td.colSpan = 3;
    td.className = "empty"; td.textContent = "no heading source reported yet";
  }
  for (const name of names) {
    const s = sources[name];
    const tr = body.insertRow();
    tr.dataset.source = name;
    tr.insertCell().textContent = name;
    const u = tr.insertCell();
    u.textContent = s.fused ? "yes" : "no";
    u.className = s.fused ? "used-yes" : "used-no";
    tr.insertCell().textContent = s.fused ? (p.heading_source === "coast" ? "coasting" : "fused")
      : (s.detail || s.why_not || "-");
  }
}

function renderFlags(v, flags) {
  const dl = field(v, "flags");
  dl.textContent = "";
  const keys = Object.keys(flags).sort();
  if (!keys.length) { const dd = document.createElement("dd"); dd.className = "empty"; dd.textContent = "none"; dl.appendChild(dd); }
  for (const k of keys) {
    const dt = document.createElement("dt"); dt.textContent = k.replace(/_/g, " ");
    const dd = document.createElement("dd"); dd.textContent = String(flags[k]);
    dl.append(dt, dd);
  }
}

function onAzimuth(v, p) {
  setText(v, "azimuth_true_deg", fmt(p.azimuth_true_deg, 1, "°"));
  setText(v, "azimuth_sigma_deg", isNum(p.azimuth_sigma_deg) ? `±${p.azimuth_sigma_deg.toFixed(1)}` : "");
  const mark = v.el.querySelector(".azimuth-mark");
  if (isNum(p.azimuth_true_deg)) {
    mark.setAttribute("transform", `rotate(${p.azimuth_true_deg.toFixed(2)})`);
    mark.setAttribute("visibility", "visible");
  } else mark.setAttribute("visibility", "hidden");
}

function onHealth(v, p) {
  v.last.health = p;
  setText(v, "phase", p.phase || "-");
  setText(v, "autopilot", p.autopilot || "-");
  setText(v, "uptime", isNum(p.uptime_s) ? `${Math.floor(p.uptime_s)} s` : "-");
  renderLink(v);
  const rates = field(v, "rates");
  rates.textContent = "";
  for (const k of SHOWN_RATES) {
    if (!(k in (p.rates_hz || {}))) continue;
    const s = document.createElement("span");
    s.innerHTML = `${k.toLowerCase()} <b></b> Hz`;
    s.querySelector("b").textContent = p.rates_hz[k].toFixed(0);
    rates.appendChild(s);
  }
  const body = field(v, "counters");
  body.textContent = "";
  const c = p.counters_count || {};
  const keys = Object.keys(c).filter((k) => c[k] > 0 || k === "imu_samples" || k === "imu_rejected").sort();
  for (const k of keys) {
    const tr = body.insertRow();
    tr.insertCell().textContent = k.replace(/_/g, " ");
    const td = tr.insertCell(); td.textContent = c[k]; td.className = "num";
    if (c[k] > 0 && BAD_COUNTER.test(k)) td.classList.add("bad");
  }
}

function renderLink(v) {
  const p = v.last.health, gone = v.status === "GONE";
  const e = field(v, "link");
  // what a GONE daemon last said about its link is history, not its state now
  e.textContent = gone || !p ? "-" : (p.link_up ? "up" : "DOWN");
  e.style.color = gone || !p ? "" : (p.link_up ? "var(--ok)" : "var(--bad)");
}

function onAirData(v, p) {
  setText(v, "airspeed_tas_m_s", fmt(p.airspeed_tas_m_s, 1, " m/s"));
  setText(v, "pressure_altitude_m", fmt(p.pressure_altitude_m, 0, " m"));
  setText(v, "alt_rate_m_s", fmt(p.alt_rate_m_s, 1, " m/s"));
  setText(v, "air_usable", p.usable ? "usable" : (p.unusable_reason ? `not usable: ${p.unusable_reason}` : ""));
}

function onCalibration(v, p) {
  v.last.calibration = Object.assign(v.last.calibration || {}, {[p.kind]: p});
  const dl = field(v, "calibration");
  dl.textContent = "";
  for (const [kind, c] of Object.entries(v.last.calibration).sort()) {
    const dt = document.createElement("dt"); dt.textContent = kind.replace(/_/g, " ");
    const dd = document.createElement("dd"); dd.textContent = `${c.status}: ${c.detail || ""}`;
    dl.append(dt, dd);
  }
}

function onEvent(v, p) {
  v.events.unshift(p);
  v.events.length = Math.min(v.events.length, MAX_EVENTS);
  const ol = field(v, "events");
  ol.textContent = "";
  for (const e of v.events) {
    const li = document.createElement("li");
    li.className = "sev-" + (e.severity || "info");
    const t = document.createElement("span"); t.className = "t"; t.textContent = clock(e.time_unix_s);
    const k = document.createElement("span"); k.className = "k"; k.textContent = e.kind;
    li.append(t, k, document.createTextNode(e.detail || ""));
    li.title = e.detail || "";           // the whole line when it is clipped
    ol.appendChild(li);
  }
}

function onGeofence(v, p) {
  if (Array.isArray(p.inclusion_polygons_deg)) {
    v.fence = {home: [p.home_lat_deg, p.home_lon_deg], incl: p.inclusion_polygons_deg,
               excl: p.exclusion_polygons_deg || []};
  }
  if (isNum(p.lat_deg) && isNum(p.lon_deg)) {
    const last = v.track[v.track.length - 1];
    if (!last || last[0] !== p.lat_deg || last[1] !== p.lon_deg) v.track.push([p.lat_deg, p.lon_deg]);
  }
  v.last.geofence = p;
  const st = field(v, "fence_state");
  st.textContent = p.state;
  st.className = "badge small " + ({ok: "ok", warning: "warn", breach: "bad"}[p.state] || "");
  setText(v, "distance_to_fence_m", fmt(p.distance_to_fence_m, 0, " m"));
  setText(v, "position_source", p.position_source || "-");
  setText(v, "pos_sigma_major_m", fmt(p.pos_sigma_major_m, 0, " m"));
  setText(v, "action_status", p.action ? `${p.action}: ${p.action_status}` : (p.action_status || "-"));
  drawTrack(v);
}

function drawTrack(v) {
  const box = v.el.querySelector(".track");
  box.textContent = "";
  const W = 300, H = 220, PAD = 14;
  const f = v.fence, p = v.last.geofence || {};
  const origin = f ? f.home : (v.track[0] || null);
  if (!origin || !isNum(origin[0])) {
    svg("text", {x: W / 2, y: H / 2, "text-anchor": "middle"}, box).textContent =
      "no fence configured and no position yet";
    return;
  }
  const cosLat = Math.cos(origin[0] * Math.PI / 180);
  const xy = ([lat, lon]) => [(lon - origin[1]) * M_PER_DEG_LON_EQ * cosLat, (lat - origin[0]) * M_PER_DEG_LAT];
  const polys = f ? f.incl.map((poly) => poly.map(xy)) : [];
  const excl = f ? f.excl.map((poly) => poly.map(xy)) : [];
  const path = v.track.map(xy);
  const pts = [[0, 0], ...polys.flat(), ...excl.flat(), ...path];
  let [x0, x1, y0, y1] = [Infinity, -Infinity, Infinity, -Infinity];
  for (const [x, y] of pts) { x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y); }
  const span = Math.max(x1 - x0, y1 - y0, 200);
  const s = Math.min((W - 2 * PAD) / Math.max(x1 - x0, 1e-6), (H - 2 * PAD) / Math.max(y1 - y0, 1e-6), (W - 2 * PAD) / span);
  const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
  const px = ([x, y]) => `${(W / 2 + (x - cx) * s).toFixed(1)},${(H / 2 - (y - cy) * s).toFixed(1)}`;
  for (const poly of polys) svg("polygon", {points: poly.map(px).join(" "), class: "fence"}, box);
  for (const poly of excl) svg("polygon", {points: poly.map(px).join(" "), class: "exclusion"}, box);
  const [hx, hy] = px([0, 0]).split(",");
  svg("circle", {cx: hx, cy: hy, r: 3.5, class: "home"}, box);
  if (path.length > 1) svg("polyline", {points: path.map(px).join(" "), class: "path"}, box);
  if (path.length) {
    const [nx, ny] = px(path[path.length - 1]).split(",");
    if (isNum(p.pos_sigma_major_m)) svg("circle", {cx: nx, cy: ny, r: Math.max(p.pos_sigma_major_m * s, 2), class: "sigma"}, box);
    svg("circle", {cx: nx, cy: ny, r: 3, class: "now"}, box);
  }
  // scale bar: a round length near a quarter of the width
  const target = (W / 4) / s, pow = Math.pow(10, Math.floor(Math.log10(target)));
  const len = [1, 2, 5, 10].map((k) => k * pow).filter((l) => l <= target).pop() || pow;
  svg("line", {x1: 8, y1: H - 8, x2: 8 + len * s, y2: H - 8, stroke: "#8796a5", "stroke-width": 2}, box);
  svg("text", {x: 8, y: H - 12}, box).textContent = len >= 1000 ? `${len / 1000} km` : `${len} m`;
  svg("text", {x: W - 10, y: 12, "text-anchor": "end"}, box).textContent = "N ↑";
}

const HANDLERS = {attitude: onAttitude, heading: onHeading, azimuth: onAzimuth, health: onHealth,
                  air_data: onAirData, calibration: onCalibration, events: onEvent, geofence: onGeofence};

// --- liveness -------------------------------------------------------------------------------

function setStatus(v, status, reason) {
  v.status = status;
  const b = field(v, "status");
  b.textContent = status;
  b.className = "badge " + ({alive: "ok", GONE: "bad", starting: "warn"}[status] || "");
  setText(v, "status_reason", reason || "");
  v.el.classList.toggle("gone", status === "GONE");
  renderLink(v);
}

function onStatus(msg) {
  const banner = document.getElementById("banner");
  banner.hidden = !msg.no_daemon;
  banner.textContent = msg.message || "";
  for (const [name, s] of Object.entries(msg.vehicles || {})) setStatus(vehicle(name), s.status, s.status_reason);
}

function onSnapshot(msg) {
  for (const v of vehicles.values()) v.events = [];   // a reconnect: the snapshot has them again
  for (const [name, snap] of Object.entries(msg.vehicles || {})) {
    const v = vehicle(name);
    v.track = (msg.tracks || {})[name] || [];
    for (const topic of ["geofence", "attitude", "heading", "azimuth", "health", "air_data"]) {
      if (snap.latest[topic]) HANDLERS[topic](v, snap.latest[topic]);
    }
    v.last.calibration = {};
    for (const c of (msg.calibrations || {})[name] || []) HANDLERS.calibration(v, c);
  }
  for (const e of msg.events || []) HANDLERS.events(vehicle(e.vehicle), e);
  onStatus(msg.status);
}

function onMessage(ev) {
  const msg = JSON.parse(ev.data);
  if (msg.type === "sample") {
    const h = HANDLERS[msg.topic];
    if (h) h(vehicle(msg.vehicle), msg.payload);
  } else if (msg.type === "alive") {
    if (!msg.alive) setStatus(vehicle(msg.vehicle), "GONE", "liveliness token withdrawn (daemon stopped or its process died)");
  } else if (msg.type === "status") onStatus(msg);
  else if (msg.type === "snapshot") onSnapshot(msg);
}

function connect() {
  const conn = document.getElementById("conn");
  const es = new EventSource("/events");
  es.onopen = () => { conn.textContent = "live"; conn.className = "badge ok"; };
  es.onerror = () => { conn.textContent = "dashboard server unreachable: retrying"; conn.className = "badge bad"; };
  es.onmessage = onMessage;
}

connect();
