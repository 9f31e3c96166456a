// seqat serve: the run folder as a web map. Polls /status.json every 2 s; when its version
// changes (a new image, a new mosaic, the published results) the tiles, cameras and tie
// points are fetched again, without reloading the page.
"use strict";

const POLL_MS = 2000;
const map = L.map("map", { zoomControl: true, maxZoom: 24, zoomSnap: 0.25 });
map.setView([0, 0], 2);
let version = null;
let fitted = false;
const tiles = L.tileLayer("/tiles/{z}/{x}/{y}.png?v=0", {
  tileSize: 256, maxZoom: 24, maxNativeZoom: 19, minZoom: 0,
  attribution: "mosaic.tif · seqat",
}).addTo(map);
// cameras above the tie points, whatever order they are (re)loaded in
map.createPane("cameras").style.zIndex = 450;
const points = L.layerGroup().addTo(map);
const cameras = L.layerGroup().addTo(map);
L.control.layers(null, { "mosaic": tiles, "tie points": points, "cameras": cameras },
  { position: "topleft" }).addTo(map);
L.control.scale({ imperial: false }).addTo(map);

// viridis, 6 stops: low σ dark blue, high σ yellow
const STOPS = ["#440154", "#414487", "#2a788e", "#22a884", "#7ad151", "#fde725"];

function colour(t) {
  if (!Number.isFinite(t)) return "#888888";
  const x = Math.min(Math.max(t, 0), 1) * (STOPS.length - 1);
  return STOPS[Math.round(x)];
}

function fmt(value, digits, unit) {
  return value === null || value === undefined ? "–" : value.toFixed(digits) + (unit || "");
}

function sigmaRange(features) {
  const s = features.map(f => f.properties.sigma_position_m).filter(Number.isFinite);
  if (!s.length) return null;
  return [Math.min(...s), Math.max(...s)];
}

function legend(range) {
  const el = document.getElementById("legend");
  if (!range) { el.innerHTML = ""; return; }
  const unit = v => v < 0.1 ? (v * 1000).toFixed(1) + " mm" : v.toFixed(3) + " m";
  el.innerHTML = "<div>cameras: posterior σ of the position</div>" +
    `<div class="bar" style="background: linear-gradient(to right, ${STOPS.join(",")})"></div>` +
    `<div class="ends"><span>${unit(range[0])}</span><span>${unit(range[1])}</span></div>`;
}

async function getJson(url) {
  const r = await fetch(url, { cache: "no-store" });
  if (!r.ok) throw new Error(url + ": HTTP " + r.status);
  return r.json();
}

async function loadCameras() {
  const fc = await getJson("/cameras.geojson");
  const range = sigmaRange(fc.features);
  cameras.clearLayers();
  for (const f of fc.features) {
    const p = f.properties;
    const [lon, lat] = f.geometry.coordinates;
    const t = range && range[1] > range[0] ?
      (p.sigma_position_m - range[0]) / (range[1] - range[0]) : 0.5;
    L.circleMarker([lat, lon], {
      radius: 7, color: "#000", weight: 1, fillColor: colour(t), fillOpacity: 0.95,
      className: "seqat-camera", pane: "cameras",
    }).bindTooltip(`${p.image}${p.position === "nav" ? " (nav position, run going on)" : ""}` +
      `<br>σ X Y Z ${fmt(p.sx_m, 3)} ${fmt(p.sy_m, 3)} ` +
      `${fmt(p.sz_m, 3)} m<br>σ ω φ κ ${fmt(p.somega_deg, 4)} ${fmt(p.sphi_deg, 4)} ` +
      `${fmt(p.skappa_deg, 4)}°`).addTo(cameras);
  }
  legend(range);
  return fc.features;
}

async function loadPoints() {
  const fc = await getJson("/points.geojson");
  points.clearLayers();
  for (const f of fc.features) {
    const [lon, lat] = f.geometry.coordinates;
    L.circleMarker([lat, lon], {
      radius: 1.5, stroke: false, fillColor: "#d62728", fillOpacity: 0.6,
      className: "seqat-point", interactive: false,
    }).addTo(points);
  }
}

function showStatus(s) {
  document.getElementById("run").textContent = s.run;
  const state = document.getElementById("state");
  state.textContent = s.done ? "finished" : "live";
  state.className = s.done ? "done" : "live";
  document.getElementById("images").textContent = s.images;
  document.getElementById("points").textContent = s.points;
  document.getElementById("sigma0").textContent = fmt(s.sigma0, 3);
  const kind = s.last_latency_kind === "latency_ms" ? "" : " (processing)";
  document.getElementById("latency").textContent = fmt(s.last_latency_ms, 0, " ms") +
    (s.last_latency_ms === null ? "" : kind);
  document.getElementById("mosaic_latency").textContent = fmt(s.last_mosaic_latency_ms, 0, " ms");
  document.getElementById("method").textContent = s.method || "–";
  document.getElementById("crs").textContent = s.crs_name || "–";
  const ul = document.getElementById("warnings");
  ul.innerHTML = "";
  for (const w of s.warnings) {
    const li = document.createElement("li");
    li.textContent = w;
    ul.appendChild(li);
  }
  document.getElementById("updated").textContent =
    "updated " + new Date().toLocaleTimeString();
}

function fit(s, features) {
  if (fitted) return;
  let bounds = null;
  if (s.mosaic) {
    const [w, so, e, n] = s.mosaic.bounds_wgs84;
    bounds = L.latLngBounds([so, w], [n, e]);
  }
  for (const f of features) {
    const [lon, lat] = f.geometry.coordinates;
    bounds = bounds ? bounds.extend([lat, lon]) : L.latLngBounds([lat, lon], [lat, lon]);
  }
  if (bounds) {
    map.fitBounds(bounds.pad(0.05));
    fitted = true;
  }
}

async function poll() {
  try {
    const s = await getJson("/status.json");
    showStatus(s);
    if (s.version !== version) {
      version = s.version;
      if (s.mosaic) tiles.options.maxNativeZoom = s.mosaic.maxzoom;
      tiles.setUrl("/tiles/{z}/{x}/{y}.png?v=" + encodeURIComponent(s.version));
      const features = await loadCameras();
      await loadPoints();
      fit(s, features);
    }
  } catch (err) {
    document.getElementById("updated").textContent = "server unreachable: " + err.message;
  }
  setTimeout(poll, POLL_MS);
}

poll();
