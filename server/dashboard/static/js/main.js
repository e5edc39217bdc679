// The dashboard page: Leaflet in a metric frame (L.CRS.Simple, 1 unit = 1 m, [lat, lng] = [y, x]),
// fed by the server's WebSocket. Layers are created once per device and updated in place
// (setLatLng, setLatLngs, setStyle), keyed by "site/device". Test hooks are DOM state:
// body[data-floor], body[data-markers] (devices drawn on the shown floor), tr[data-device],
// body[data-coverage] (the floor whose heat layer is drawn), body[data-map-version].
import { ellipsePoints, deviceColour } from "./geometry.js";
import {
  newModel,
  applyFrame,
  staleness,
  ageOf,
  floorCounts,
  floorsOf,
  runsOnFloor,
  correctedRunsOnFloor,
  isCurrent,
  deviceKey,
} from "./state.js";
import { gridImage, gridBounds, legendImage } from "./coverage.js";

const L = window.L;
const body = document.body;
const $ = (id) => document.getElementById(id);
const nowS = () => Date.now() / 1000;
const params = new URLSearchParams(location.search);
// ?perf: the page records, per WebSocket frame, the time from its arrival to the animation frame
// after it was drawn (benchmarks/bench_dashboard.py); ?svg: SVG paths instead of one canvas
const perf = params.has("perf") ? (window.__hlPerf = { samples: [] }) : null;

const model = newModel();
const view = {
  site: null,
  floor: null,
  tx: null,
  follow: null, // device key
  sites: new Map(), // site id -> /api/sites entry
  planFloors: [],
};

// ------------------------------------------------------------------------------------------ map
const map = L.map("map", {
  crs: L.CRS.Simple,
  minZoom: -4,
  maxZoom: 6,
  zoomSnap: 0.25,
  preferCanvas: !params.has("svg"), // one canvas for hundreds of devices (SVG paths per device cost more)
  attributionControl: false,
});
map.setView([0, 0], 0);
L.control.scale({ imperial: false, metric: true, position: "bottomleft" }).addTo(map);
// panes, bottom to top: the floor plan, the coverage heat layer, then devices and tracks (overlayPane, 400)
map.createPane("plan").style.zIndex = "250";
map.createPane("coverage").style.zIndex = "300";
const planRenderer = L.canvas({ pane: "plan" });
const planLayer = L.layerGroup().addTo(map);
const coverageLayer = L.layerGroup().addTo(map);
const regionLayer = L.layerGroup().addTo(map);
const trackLayer = L.layerGroup().addTo(map);
const deviceLayer = L.layerGroup().addTo(map);
const layers = new Map(); // key -> {marker, ellipse, raw, corr, region, shown}
let planDoc = null;

const PLAN_STYLE = {
  floor: { color: "#9aa3ad", weight: 1, fillColor: "#eef1f4", fillOpacity: 1 },
  walkable: { color: "#c9d3dc", weight: 0.5, fillColor: "#ffffff", fillOpacity: 1 },
  room: { color: "#b8c0c8", weight: 0.8, fillColor: "#f6f7f8", fillOpacity: 1 },
  walls: { color: "#4a5560", weight: 1.2 },
  transition: { color: "#8a5cf6", weight: 3, dashArray: "2 3" },
};

function drawPlan() {
  planLayer.clearLayers();
  if (!planDoc) return;
  const feats = planDoc.features.filter((f) => f.properties.floor === view.floor || (f.properties.category === "transition" && (f.properties.floor_from === view.floor || f.properties.floor_to === view.floor)));
  const order = ["floor", "walkable", "room", "walls", "transition"];
  feats.sort((a, b) => order.indexOf(a.properties.category) - order.indexOf(b.properties.category));
  const g = L.geoJSON({ type: "FeatureCollection", features: feats }, {
    style: (f) => PLAN_STYLE[f.properties.category] || PLAN_STYLE.room,
    interactive: false,
    pane: "plan",
    renderer: planRenderer,
  });
  g.addTo(planLayer);
  const b = g.getBounds();
  if (b.isValid()) fitOnce(b);
}

let fitted = new Set();
function fitOnce(bounds) {
  const k = `${view.site}/${view.floor}`;
  if (fitted.has(k)) return;
  fitted.add(k);
  map.fitBounds(bounds, { padding: [12, 12] });
}

// ------------------------------------------------------------------------------------------ devices
function layersOf(key, d) {
  let l = layers.get(key);
  if (l) return l;
  const colour = deviceColour(d.id);
  l = {
    colour,
    marker: L.circleMarker([0, 0], { radius: 6, color: "#ffffff", weight: 2, fillColor: colour, fillOpacity: 1 }).bindTooltip(d.id),
    ellipse: L.polygon([], { color: colour, weight: 1, fillColor: colour, fillOpacity: 0.12, interactive: false }),
    raw: L.polyline([], { color: colour, weight: 2, opacity: 0.7, interactive: false }),
    corr: L.polyline([], { color: colour, weight: 2.5, opacity: 0.9, dashArray: "6 4", interactive: false }),
    region: L.geoJSON(null, { style: { color: colour, weight: 1, dashArray: "3 3", fillOpacity: 0.05 }, interactive: false }),
    regionFloor: null,
    shown: false,
  };
  l.marker.on("click", () => setFollow(key));
  layers.set(key, l);
  return l;
}

function showLayers(l, on) {
  if (on === l.shown) return;
  const pairs = [
    [l.marker, deviceLayer],
    [l.ellipse, regionLayer],
    [l.raw, trackLayer],
    [l.corr, trackLayer],
    [l.region, regionLayer],
  ];
  for (const [layer, group] of pairs) {
    if (on) group.addLayer(layer);
    else group.removeLayer(layer);
  }
  l.shown = on;
}

const STATE_STYLE = {
  live: { marker: { fillOpacity: 1, opacity: 1, dashArray: null }, ellipse: { opacity: 1, fillOpacity: 0.12 } },
  stale: { marker: { fillOpacity: 0.35, opacity: 0.8, dashArray: "2 2" }, ellipse: { opacity: 0.4, fillOpacity: 0.04 } },
  lost: { marker: { fillOpacity: 0, opacity: 1, dashArray: "2 2" }, ellipse: { opacity: 0, fillOpacity: 0 } },
};

function drawDevice(key) {
  const d = model.devices.get(key);
  const l = layers.get(key);
  if (!d) {
    if (l) {
      showLayers(l, false);
      layers.delete(key);
    }
    return;
  }
  const on = d.site === view.site && d.x !== undefined && d.x !== null && (d.floor ?? "?") === view.floor;
  const ly = layersOf(key, d);
  showLayers(ly, on);
  if (!on) return;
  ly.marker.setLatLng([d.y, d.x]);
  const ring = ellipsePoints(d.x, d.y, d.cov).map(([x, y]) => [y, x]);
  ly.ellipse.setLatLngs(ring);
  ly.raw.setLatLngs($("show-raw").checked ? runsOnFloor(d.pts, view.floor).map((r) => r.map(([x, y]) => [y, x])) : []);
  ly.corr.setLatLngs($("show-corr").checked ? correctedRunsOnFloor(d.corr, view.floor).map((r) => r.map(([x, y]) => [y, x])) : []);
  const regionKey = d.region ? JSON.stringify(d.region.geometry).length + ":" + d.region.floor : null;
  if (ly.regionFloor !== regionKey) {
    ly.region.clearLayers();
    if (d.region && d.region.floor === view.floor && $("show-regions").checked) ly.region.addData(d.region.geometry);
    ly.regionFloor = regionKey;
  }
  restyle(key, d, ly);
}

function restyle(key, d, ly) {
  const st = staleness(ageOf(model, d, nowS()), model.staleS, model.lostS);
  if (ly.state === st) return;
  ly.state = st;
  const s = STATE_STYLE[st];
  ly.marker.setStyle({ ...s.marker, color: st === "lost" ? "#d0342c" : "#ffffff", fillColor: st === "stale" ? "#8a939c" : ly.colour });
  ly.ellipse.setStyle(s.ellipse);
}

function redrawAllDevices() {
  for (const k of new Set([...layers.keys(), ...model.devices.keys()])) {
    const l = layers.get(k);
    if (l) l.regionFloor = undefined;
    drawDevice(k);
  }
  updateCounts();
}

function updateCounts() {
  let n = 0;
  for (const l of layers.values()) if (l.shown) n++;
  body.dataset.markers = String(n);
  drawFloorStrip();
}

// ------------------------------------------------------------------------------------------ device list
const rows = new Map(); // key -> tr
function drawRow(key) {
  const d = model.devices.get(key);
  let tr = rows.get(key);
  if (!d || !view.site || d.site !== view.site) {
    if (tr) {
      tr.remove();
      rows.delete(key);
    }
    return;
  }
  if (!tr) {
    tr = document.createElement("tr");
    tr.dataset.device = d.id;
    for (const cls of ["id", "floor", "state", "age", "online", "rej", "follow"]) {
      const td = document.createElement("td");
      td.className = cls;
      tr.appendChild(td);
    }
    const dot = document.createElement("span");
    dot.className = "dot";
    dot.style.backgroundColor = deviceColour(d.id); // CSSOM, allowed by the style-src policy
    tr.querySelector(".id").append(dot, document.createTextNode(d.id));
    tr.querySelector(".id").title = d.id;
    const btn = document.createElement("button");
    btn.type = "button";
    btn.textContent = "follow";
    btn.addEventListener("click", () => setFollow(view.follow === key ? null : key));
    tr.querySelector(".follow").appendChild(btn);
    insertSorted($("device-rows"), tr, d.id);
    rows.set(key, tr);
  }
  tr.querySelector(".floor").textContent = d.floor ?? "?";
  const rej = Object.entries(d.rej || {});
  const nrej = rej.reduce((a, [, n]) => a + n, 0);
  const cell = tr.querySelector(".rej");
  cell.textContent = String(nrej);
  cell.title = rej.map(([r, n]) => `${r}: ${n}`).join("\n") || "no rejections";
  tr.dataset.rejections = String(nrej);
  tr.querySelector(".online").textContent = d.online ? "yes" : "no";
  tr.dataset.ellipse = d.cov ? "1" : "0";
  tr.querySelector(".follow button").classList.toggle("on", view.follow === key);
  rowAge(tr, d);
}

function insertSorted(tbody, tr, id) {
  for (const other of tbody.children) {
    if (other.dataset.device > id) {
      tbody.insertBefore(tr, other);
      return;
    }
  }
  tbody.appendChild(tr);
}

function rowAge(tr, d) {
  const age = ageOf(model, d, nowS());
  const st = staleness(age, model.staleS, model.lostS);
  tr.dataset.state = st;
  tr.querySelector(".state").textContent = st;
  tr.querySelector(".age").textContent = d.seen ? formatAge(age) : "-";
}

function formatAge(s) {
  if (!Number.isFinite(s)) return "-";
  if (s < 1) return "now";
  if (s < 90) return `${Math.round(s)} s`;
  if (s < 5400) return `${Math.round(s / 60)} min`;
  return `${(s / 3600).toFixed(1)} h`;
}

function tickAges() {
  for (const [key, tr] of rows) {
    const d = model.devices.get(key);
    if (d) rowAge(tr, d);
  }
  for (const [key, l] of layers) {
    const d = model.devices.get(key);
    if (d && l.shown) restyle(key, d, l);
  }
  drawFloorStrip();
}

// ------------------------------------------------------------------------------------------ follow
function setFollow(key) {
  view.follow = key;
  if (key) body.dataset.follow = model.devices.get(key)?.id ?? "";
  else delete body.dataset.follow;
  for (const [k, tr] of rows) tr.querySelector(".follow button").classList.toggle("on", k === key);
  followNow();
}

function followNow() {
  if (!view.follow) return;
  const d = model.devices.get(view.follow);
  if (!d || d.x === undefined || d.x === null) return;
  if (d.site !== view.site) {
    selectSite(d.site);
    return;
  }
  const f = d.floor ?? "?";
  if (f !== view.floor) setFloor(f);
  map.panTo([d.y, d.x], { animate: false });
}

// ------------------------------------------------------------------------------------------ floors
function drawFloorStrip() {
  const strip = $("floors");
  const floors = floorsOf(view.planFloors, model, view.site);
  const counts = floorCounts(model, view.site, nowS());
  const have = new Map([...strip.children].map((b) => [b.dataset.floorButton, b]));
  floors.forEach((f, i) => {
    let b = have.get(f);
    if (!b) {
      b = document.createElement("button");
      b.type = "button";
      b.dataset.floorButton = f;
      const name = document.createElement("span");
      name.className = "name";
      name.textContent = f;
      const count = document.createElement("span");
      count.className = "count";
      b.append(name, count);
      b.addEventListener("click", () => {
        if (view.follow) setFollow(null); // a floor picked by hand ends following
        setFloor(f);
      });
    }
    if (strip.children[i] !== b) strip.insertBefore(b, strip.children[i] || null);
    b.querySelector(".count").textContent = String(counts.get(f) || 0);
    b.classList.toggle("current", f === view.floor);
    have.delete(f);
  });
  for (const b of have.values()) b.remove();
}

function setFloor(f) {
  if (f === view.floor) return;
  view.floor = f;
  body.dataset.floor = f;
  drawPlan();
  redrawAllDevices();
  updateDownloads();
  refreshCoverage();
}

// ------------------------------------------------------------------------------------------ coverage
let coverageSeq = 0;
let coverageOverlay = null;

function clearCoverage() {
  coverageLayer.clearLayers();
  coverageOverlay = null;
  delete body.dataset.coverage;
  delete body.dataset.coverageEmpty;
  $("legend").hidden = true;
}

async function refreshTransmitters() {
  const sel = $("coverage-tx");
  const want = { site: view.site, floor: view.floor };
  sel.replaceChildren(new Option("all transmitters (map support)", ""));
  if (!$("show-coverage").checked || !want.site || !want.floor) return;
  const r = await fetch(`/api/transmitters?site=${encodeURIComponent(want.site)}&floor=${encodeURIComponent(want.floor)}`);
  if (!r.ok || want.site !== view.site || want.floor !== view.floor) return;
  const data = await r.json();
  for (const t of data.transmitters) sel.add(new Option(`${t.id} (${t.area_m2} m²)`, t.id));
  sel.value = view.tx || "";
}

async function refreshCoverage() {
  const seq = ++coverageSeq;
  clearCoverage();
  $("coverage-note").textContent = "";
  if (!$("show-coverage").checked || !view.site || !view.floor) return;
  const req = { seq, site: view.site, floor: view.floor, tx: view.tx };
  let url = `/api/coverage?site=${encodeURIComponent(req.site)}&floor=${encodeURIComponent(req.floor)}`;
  if (req.tx) url += `&tx=${encodeURIComponent(req.tx)}`;
  const r = await fetch(url);
  // the floor (or site, or transmitter) may have changed while the request was out: only the
  // answer to what is shown now is drawn (a stale answer drawn late is a known bug class)
  if (!isCurrent(req, view, coverageSeq)) return;
  if (!r.ok) {
    $("coverage-note").textContent = (await r.text()).replace(/^\d+ /, "").trim();
    return;
  }
  const cov = await r.json();
  if (!isCurrent(req, view, coverageSeq)) return;
  if (!cov.nx || !cov.ny) {
    $("coverage-note").textContent = cov.note || "no radio map cells on this floor";
    body.dataset.coverageEmpty = req.floor;
    return;
  }
  coverageOverlay = L.imageOverlay(gridImage(cov), gridBounds(cov), { opacity: 0.75, className: "cov", interactive: false, pane: "coverage" });
  coverageLayer.addLayer(coverageOverlay);
  body.dataset.coverage = req.floor;
  const lg = $("legend");
  lg.hidden = false;
  $("legend-bar").src = legendImage();
  $("legend-label").textContent = cov.label;
  $("legend-min").textContent = `${fmt(cov.vmin)} ${cov.unit}`;
  $("legend-max").textContent = `${fmt(cov.vmax)} ${cov.unit}`;
}

const fmt = (v) => (v === null || v === undefined ? "-" : Math.abs(v) >= 100 ? v.toFixed(0) : v.toFixed(1));

// ------------------------------------------------------------------------------------------ site panel
function drawSitePanel() {
  const s = model.sites.get(view.site) || {};
  const info = view.sites.get(view.site) || {};
  const v = s.map_version ?? info.map_version ?? null;
  if (v === null) delete body.dataset.mapVersion;
  else body.dataset.mapVersion = String(v);
  $("map-version").textContent = v === null ? "radio map: none" : `radio map v${v}${s.map_source ? ` (${s.map_source})` : ""}`;
  const p = s.progress;
  const bar = $("progress");
  if (p && nowS() + model.offset - p.t < 600) {
    bar.hidden = false;
    const done = p.total ? p.done / p.total : 1;
    $("progress-bar").value = done;
    $("progress-text").textContent = `${p.stage}${p.floor ? " " + p.floor : ""} ${p.done}/${p.total}`;
    bar.dataset.stage = p.stage;
  } else {
    bar.hidden = true;
  }
  const sl = s.slam;
  $("slam").textContent = sl
    ? `SLAM: ${sl.walks_corrected ?? 0} walks corrected, ${sl.walks_pending ?? 0} pending, ${sl.loops_accepted ?? 0} loops` +
      (sl.coverage !== null && sl.coverage !== undefined ? `, coverage ${Math.round(100 * sl.coverage)} %` : "") +
      (sl.busy ? ` — ${sl.busy}` : "")
    : "";
}

function updateDownloads() {
  const q = `site=${encodeURIComponent(view.site || "")}&floor=${encodeURIComponent(view.floor || "")}`;
  $("dl-csv").href = `/api/tracks.csv?${q}`;
  $("dl-geojson").href = `/api/tracks.geojson?${q}`;
}

async function selectSite(site) {
  if (!site || site === view.site) return;
  view.site = site;
  view.floor = null;
  view.tx = null;
  body.dataset.site = site;
  $("site").value = site;
  planDoc = null;
  const info = view.sites.get(site);
  view.planFloors = info ? info.floors.map((f) => f.name) : [];
  for (const key of [...rows.keys()]) drawRow(key);
  for (const key of model.devices.keys()) drawRow(key);
  if (info && info.has_plan) {
    const r = await fetch(`/api/plan?site=${encodeURIComponent(site)}`);
    if (r.ok && view.site === site) planDoc = await r.json();
  }
  if (view.site !== site) return;
  const floors = floorsOf(view.planFloors, model, site);
  setFloor(floors[0] ?? "?");
  drawSitePanel();
}

async function loadSites() {
  const r = await fetch("/api/sites");
  if (!r.ok) throw new Error(`sites: ${r.status}`);
  const data = await r.json();
  const sel = $("site");
  sel.replaceChildren();
  view.sites.clear();
  for (const s of data.sites) {
    view.sites.set(s.id, s);
    sel.add(new Option(s.id, s.id));
  }
  if (!view.site && data.sites.length) await selectSite(data.sites[0].id);
}

function addSiteOption(site) {
  if (view.sites.has(site)) return;
  view.sites.set(site, { id: site, floors: [], map_version: null, has_plan: false });
  $("site").add(new Option(site, site));
  if (!view.site) selectSite(site);
}

// ------------------------------------------------------------------------------------------ live feed
function onFrame(frame) {
  const t0 = performance.now();
  const changed = applyFrame(model, frame, nowS());
  for (const s of frame.sites || []) addSiteOption(s.id);
  for (const key of changed) {
    const d = model.devices.get(key);
    if (d) addSiteOption(d.site);
    drawDevice(key);
    drawRow(key);
  }
  updateCounts();
  drawSitePanel();
  followNow();
  if (perf) {
    const n = changed.size;
    requestAnimationFrame(() => perf.samples.push({ ms: performance.now() - t0, devices: n }));
  }
}

let retry = 0;
function connect() {
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  ws.onopen = () => {
    retry = 0;
    $("conn").textContent = "live";
    $("conn").className = "conn live";
    body.dataset.connected = "1";
  };
  ws.onmessage = (ev) => onFrame(JSON.parse(ev.data));
  ws.onclose = () => {
    $("conn").textContent = "reconnecting";
    $("conn").className = "conn down";
    delete body.dataset.connected;
    setTimeout(connect, Math.min(10000, 500 * 2 ** retry++));
  };
}

// ------------------------------------------------------------------------------------------ controls
$("site").addEventListener("change", (e) => selectSite(e.target.value));
for (const id of ["show-raw", "show-corr", "show-regions"]) $(id).addEventListener("change", redrawAllDevices);
$("show-coverage").addEventListener("change", () => {
  $("coverage-tx").disabled = !$("show-coverage").checked;
  refreshTransmitters();
  refreshCoverage();
});
$("coverage-tx").addEventListener("change", (e) => {
  view.tx = e.target.value || null;
  refreshCoverage();
});
setInterval(() => {
  tickAges();
  drawSitePanel();
}, 1000);

loadSites()
  .catch((err) => {
    $("conn").textContent = `error: ${err.message}`;
  })
  .finally(connect);
