// seqat serve: the run folder as a web map. Listens to /events (server-sent events: status.json
// each time its version changes); where the stream is not open (no EventSource, server
// unreachable) it polls /status.json every second instead. When the version changes (a new
// image, a new live mosaic, the published results) the cameras, error ellipses, footprints,
// tie points and coverage are fetched again, and the mosaic's tiles that changed, without
// reloading the page. Each
// georeferenced image is shown at once as its quick-look on its footprint, until the mosaic
// has it.
"use strict";

const POLL_MS = 1000;
// whole zooms: a TileLayer redrawn (setUrl) at a fractional map zoom requests fractional tile zooms
const map = L.map("map", { zoomControl: true, maxZoom: 24, zoomSnap: 1 });
map.setView([0, 0], 2);
let version = null;
let userMoved = false;  // the map follows the data until the user pans or zooms it
let stopCm = null;       // the page's stop criterion (the field), null: the run's
let stopShown = null;    // the criterion the shown layers were coloured with
// The tiles carry the mosaic's version (?v=), not the page's: a new camera or estimate that
// leaves the mosaic as it was reloads no tile, and a new revision of the live mosaic reloads
// only the tiles over the boxes it changed (refreshTiles).
let tileVersion = "0";
let mosaicShown = null;  // the status's mosaic whose tiles are shown
const tiles = L.tileLayer("/tiles/{z}/{x}/{y}.png?v={v}", {
  tileSize: 256, maxZoom: 24, maxNativeZoom: 19, minZoom: 0,
  attribution: "mosaic · seqat", v: () => encodeURIComponent(tileVersion),
}).addTo(map);
// cameras above everything, ellipses and tie points above footprints and coverage, the
// quick-looks just above the mosaic, under everything else (Leaflet's overlay pane is 400)
map.createPane("quicklooks").style.zIndex = 350;
map.createPane("coverage").style.zIndex = 410;
map.createPane("footprints").style.zIndex = 420;
map.createPane("ellipses").style.zIndex = 440;
map.createPane("cameras").style.zIndex = 450;
const coverage = L.layerGroup().addTo(map);
const footprints = L.layerGroup().addTo(map);
const points = L.layerGroup().addTo(map);
const ellipses = L.layerGroup().addTo(map);
const cameras = L.layerGroup().addTo(map);
const quicklooks = L.layerGroup().addTo(map);
L.control.layers(null, {
  "mosaic": tiles, "images (quick-look, until the mosaic has them)": quicklooks,
  "coverage (stop criterion)": coverage, "footprints": footprints,
  "tie points": points, "error ellipses": ellipses, "cameras": cameras,
}, { position: "topleft" }).addTo(map);
L.control.scale({ imperial: false }).addTo(map);

// viridis, 6 stops: low σ dark blue, high σ yellow
const STOPS = ["#440154", "#414487", "#2a788e", "#22a884", "#7ad151", "#fde725"];
const DONE = "#1a9850", NOT_DONE = "#f46d43";

function colour(t) {
  if (!Number.isFinite(t)) return "#888888";
  const x = Math.min(Math.max(t, 0), 1) * (STOPS.length - 1);
  return STOPS[Math.round(x)];
}

function fmt(value, digits, unit) {
  return value === null || value === undefined ? "–" : value.toFixed(digits) + (unit || "");
}

function range(values) {
  const s = values.filter(Number.isFinite);
  if (!s.length) return null;
  return [Math.min(...s), Math.max(...s)];
}

function scaled(v, r) {
  return r && r[1] > r[0] ? (v - r[0]) / (r[1] - r[0]) : 0.5;
}

function metres(v) {
  return v < 0.1 ? (v * 1000).toFixed(1) + " mm" : v.toFixed(3) + " m";
}

function legend(camRange, ptRange, scale, stop) {
  const el = document.getElementById("legend");
  const bar = `<div class="bar" style="background: linear-gradient(to right, ${STOPS.join(",")})"></div>`;
  let html = "";
  if (camRange) {
    html += "<div>cameras: posterior σ of the position" +
      (scale ? `; ellipses σE × σN, ×${scale}` : "") + "</div>" + bar +
      `<div class="ends"><span>${metres(camRange[0])}</span><span>${metres(camRange[1])}</span></div>`;
  }
  if (stop) {
    html += `<div><span class="swatch" style="background:${DONE}"></span>σ ≤ ${stop} cm (done) ` +
      `<span class="swatch" style="background:${NOT_DONE}"></span>not yet</div>`;
  } else if (ptRange) {
    html += "<div>tie points: largest σ of X, Y, Z</div>" + bar +
      `<div class="ends"><span>${metres(ptRange[0])}</span><span>${metres(ptRange[1])}</span></div>`;
  }
  el.innerHTML = html;
}

// The homography taking the four points src to dst ([[x, y] x 4]), row-major with h8 = 1:
// the 8 x 8 linear system solved by Gaussian elimination with partial pivoting.
function homography(src, dst) {
  const A = [];
  for (let i = 0; i < 4; i++) {
    const [x, y] = src[i], [u, v] = dst[i];
    A.push([x, y, 1, 0, 0, 0, -u * x, -u * y, u]);
    A.push([0, 0, 0, x, y, 1, -v * x, -v * y, v]);
  }
  for (let c = 0; c < 8; c++) {
    let p = c;
    for (let r = c + 1; r < 8; r++) if (Math.abs(A[r][c]) > Math.abs(A[p][c])) p = r;
    [A[c], A[p]] = [A[p], A[c]];
    if (Math.abs(A[c][c]) < 1e-12) return null;  // three corners on a line
    for (let r = 0; r < 8; r++) {
      if (r === c) continue;
      const f = A[r][c] / A[c][c];
      for (let k = c; k < 9; k++) A[r][k] -= f * A[c][k];
    }
  }
  return A.map((row, i) => row[8] / A[i][i]).concat([1]);
}

// An image on its footprint: the image's corners (top-left, top-right, bottom-right,
// bottom-left) mapped onto the footprint's by a CSS projective transform (matrix3d), redrawn
// when the zoom changes (a pan moves the pane, not the layer), hidden while zoom animates.
const QuickLook = L.Layer.extend({
  initialize(url, corners) {
    this.url = url;
    this._corners = corners.map(c => L.latLng(c[1], c[0]));
  },
  onAdd(map) {
    const img = this._img = L.DomUtil.create("img", "seqat-quicklook leaflet-zoom-hide",
      map.getPane("quicklooks"));
    img.style.position = "absolute";
    img.style.left = "0px";
    img.style.top = "0px";
    img.style.transformOrigin = "0 0";
    img.style.pointerEvents = "none";
    img.alt = "";
    img.onload = () => this._place();
    img.src = this.url;
    map.on("zoomend viewreset", this._place, this);
  },
  onRemove(map) {
    map.off("zoomend viewreset", this._place, this);
    L.DomUtil.remove(this._img);
  },
  setCorners(corners) {
    this._corners = corners.map(c => L.latLng(c[1], c[0]));
    this._place();
  },
  _place() {
    const img = this._img;
    if (!this._map || !img || !img.naturalWidth) return;
    const w = img.naturalWidth, h = img.naturalHeight;
    const dst = this._corners.map(c => {
      const p = this._map.latLngToLayerPoint(c);
      return [p.x, p.y];
    });
    const H = homography([[0, 0], [w, 0], [w, h], [0, h]], dst);
    if (!H) { img.style.display = "none"; return; }
    img.style.display = "";
    img.style.width = w + "px";
    img.style.height = h + "px";
    img.style.transform = "matrix3d(" + [H[0], H[3], 0, H[6], H[1], H[4], 0, H[7],
      0, 0, 1, 0, H[2], H[5], 0, H[8]].join(",") + ")";
    img.classList.add("seqat-quicklook-placed");
  },
});
const shownQuicklooks = {};  // image -> QuickLook

// The quick-looks of the images the mosaic does not show yet (footprints.geojson).
function showQuicklooks(fp) {
  const keep = new Set();
  for (const f of fp.features) {
    const p = f.properties;
    if (!p.quicklook || p.in_mosaic || !p.corners) continue;
    keep.add(p.image);
    const shown = shownQuicklooks[p.image];
    if (shown && shown.url === p.quicklook) shown.setCorners(p.corners);
    else {
      if (shown) quicklooks.removeLayer(shown);
      shownQuicklooks[p.image] = new QuickLook(p.quicklook, p.corners).addTo(quicklooks);
    }
  }
  for (const image of Object.keys(shownQuicklooks)) {
    if (!keep.has(image)) {
      quicklooks.removeLayer(shownQuicklooks[image]);
      delete shownQuicklooks[image];
    }
  }
}

// revalidated: a layer that did not change is a 304 (the server's ETag) and the copy kept
async function getJson(url) {
  const r = await fetch(url, { cache: "no-cache" });
  if (!r.ok) throw new Error(url + ": HTTP " + r.status);
  return r.json();
}

function stopQuery() {
  return stopCm ? "?stop_sigma_cm=" + encodeURIComponent(stopCm) : "";
}

async function loadCameras() {
  const [fc, el, fp] = await Promise.all([getJson("/cameras.geojson"),
    getJson("/ellipses.geojson"), getJson("/footprints.geojson")]);
  const r = range(fc.features.map(f => f.properties.sigma_position_m));
  const byImage = {};
  cameras.clearLayers();
  for (const f of fc.features) {
    const p = f.properties;
    const [lon, lat] = f.geometry.coordinates;
    byImage[p.image] = colour(scaled(p.sigma_position_m, r));
    const where = p.position === "nav" ? " (nav position: no estimate yet)" :
      p.estimate === "live" ? " (estimate of the live run" +
        (p.in_window === false ? ", left the window)" : ")") : "";
    L.circleMarker([lat, lon], {
      radius: 6, color: "#000", weight: 1, fillColor: byImage[p.image], fillOpacity: 0.95,
      className: "seqat-camera" + (p.estimate === "live" ? " seqat-camera-live" : ""),
      pane: "cameras",
    }).bindTooltip(`${p.image}${where}` +
      `<br>σ X Y Z ${fmt(p.sx_m, 3)} ${fmt(p.sy_m, 3)} ` +
      `${fmt(p.sz_m, 3)} m<br>σ ω φ κ ${fmt(p.somega_deg, 4)} ${fmt(p.sphi_deg, 4)} ` +
      `${fmt(p.skappa_deg, 4)}°`).addTo(cameras);
  }
  ellipses.clearLayers();
  L.geoJSON(el, {
    pane: "ellipses", interactive: false,
    style: f => ({ color: byImage[f.properties.image] || "#444", weight: 1.5, fillOpacity: 0.15,
      className: "seqat-ellipse" }),
  }).addTo(ellipses);
  footprints.clearLayers();
  L.geoJSON(fp, {
    pane: "footprints", interactive: false,
    style: f => ({ color: f.properties.in_window ? "#1f78b4" : "#777", weight: 1,
      fill: false, dashArray: f.properties.in_window ? null : "3 3",
      className: "seqat-footprint" }),
  }).addTo(footprints);
  showQuicklooks(fp);
  return [fc.features, r, el.scale];
}

async function loadPoints(stop) {
  const fc = await getJson("/points.geojson");
  const r = range(fc.features.map(f => f.properties.sigma_max_m));
  points.clearLayers();
  for (const f of fc.features) {
    const [lon, lat] = f.geometry.coordinates;
    const s = f.properties.sigma_max_m;
    const fill = stop ? (Number.isFinite(s) && s * 100 <= stop ? DONE : NOT_DONE) :
      colour(scaled(s, r));
    L.circleMarker([lat, lon], {
      radius: 2, stroke: false, fillColor: fill, fillOpacity: 0.8,
      className: "seqat-point", interactive: false,
    }).addTo(points);
  }
  return r;
}

async function loadCoverage() {
  const fc = await getJson("/coverage.geojson" + stopQuery());
  coverage.clearLayers();
  L.geoJSON(fc, {
    pane: "coverage", interactive: false,
    style: f => ({ stroke: false, fillColor: f.properties.done ? DONE : NOT_DONE,
      fillOpacity: 0.3, className: f.properties.done ? "seqat-cell-done" : "seqat-cell-todo" }),
  }).addTo(coverage);
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
  const lat = s.latency_ms || {};
  document.getElementById("lat_tracking").textContent = fmt(lat.tracking, 0, " ms");
  document.getElementById("lat_at").textContent = fmt(lat.at, 0, " ms");
  document.getElementById("mosaic_latency").textContent = fmt(s.last_mosaic_latency_ms, 0, " ms");
  document.getElementById("mosaic_images").textContent = s.mosaic_images ?? "–";
  document.getElementById("cameras_position").textContent =
    { final: "final estimates", live: "live estimates", nav: "nav (no estimate yet)" }[
      s.cameras_position] || "–";
  document.getElementById("method").textContent = s.method || "–";
  document.getElementById("crs").textContent = s.crs_name || "–";
  const stop = document.getElementById("stop");
  const input = document.getElementById("stop_cm");
  if (s.stop) {
    if (document.activeElement !== input && !stopCm) input.value = s.stop.sigma_cm;
    stop.textContent = `${s.stop.points_done} / ${s.stop.points_total} points, ` +
      `${s.stop.cells_done} / ${s.stop.cells_total} cells (${s.stop.cell_m} m) done` +
      (s.stop.reached ? ": reached" : "");
    stop.className = s.stop.reached ? "reached" : "";
  } else {
    stop.textContent = "no criterion set";
    stop.className = "";
  }
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

// The WGS 84 boxes [west, south, east, north] the live mosaic changed from the shown revision
// to cur's (status.mosaic.changes: [from, to, boxes], oldest first), or null when they do not
// reach back to it (the first mosaic, mosaic.tif replacing the live one, a page that fell
// more than the kept renderings behind): then every tile is reloaded.
function changedBoxes(shown, cur) {
  if (!shown || shown.version === cur.version) return shown ? [] : null;
  if (shown.revision == null || cur.revision == null || !cur.changes) return null;
  if (shown.maxzoom !== cur.maxzoom) return null;
  const later = cur.changes.filter(c => c[1] > shown.revision);
  if (!later.length || later[0][0] !== shown.revision) return null;
  return later.flatMap(c => c[2]);
}

// Show cur's mosaic: reload the tiles shown that it changed (all, without its changes).
function refreshTiles(cur) {
  const boxes = changedBoxes(mosaicShown, cur);
  tileVersion = cur.version;
  mosaicShown = cur;
  tiles.options.maxNativeZoom = cur.maxzoom;
  if (boxes === null) {
    tiles.redraw();
    return;
  }
  // Leaflet 1.9's (vendored) tiles on the map: a new src shows the old image until it loads
  for (const key in tiles._tiles) {
    const t = tiles._tiles[key];
    const b = tiles._tileCoordsToBounds(t.coords);
    if (boxes.some(([w, so, e, n]) => b.getWest() < e && b.getEast() > w &&
                   b.getSouth() < n && b.getNorth() > so)) {
      t.el.src = tiles.getTileUrl(t.coords);
    }
  }
}

function fit(s, features) {
  if (userMoved) return;
  let bounds = null;
  if (s.mosaic) {
    const [w, so, e, n] = s.mosaic.bounds_wgs84;
    bounds = L.latLngBounds([so, w], [n, e]);
  }
  for (const f of features) {
    const [lon, lat] = f.geometry.coordinates;
    bounds = bounds ? bounds.extend([lat, lon]) : L.latLngBounds([lat, lon], [lat, lon]);
  }
  footprints.eachLayer(g => g.eachLayer && g.eachLayer(
    p => { bounds = bounds ? bounds.extend(p.getBounds()) : p.getBounds(); }));
  if (bounds) map.fitBounds(bounds.pad(0.05), { maxZoom: 20 });
}

for (const kind of ["mousedown", "wheel", "touchstart", "keydown"]) {
  document.getElementById("map").addEventListener(kind, () => { userMoved = true; },
    { passive: true });
}

let busy = false;     // a refresh is running
let latest = null;    // the newest status not yet shown

// Show a status; on a new version (or criterion) fetch the layers again. Statuses arriving
// during a refresh are kept, the newest shown after it (one refresh at a time).
async function update(s) {
  latest = s;
  if (busy) return;
  busy = true;
  try {
    while (latest) {
      const cur = latest;
      latest = null;
      showStatus(cur);
      const stop = cur.stop ? cur.stop.sigma_cm : null;
      if (cur.version !== version || stop !== stopShown) {
        version = cur.version;
        stopShown = stop;
        if (cur.mosaic) refreshTiles(cur.mosaic);
        const [features, camRange, scale] = await loadCameras();
        const ptRange = await loadPoints(stop);
        await loadCoverage();
        legend(camRange, ptRange, scale, stop);
        fit(cur, features);
      }
    }
  } catch (err) {
    document.getElementById("updated").textContent = "server unreachable: " + err.message;
  } finally {
    busy = false;
  }
}

let source = null;       // the event stream, when open
let pollTimer = null;

async function poll() {
  pollTimer = null;
  try {
    await update(await getJson("/status.json" + stopQuery()));
  } catch (err) {
    document.getElementById("updated").textContent = "server unreachable: " + err.message;
  }
  if (!source || source.readyState !== EventSource.OPEN) pollTimer = setTimeout(poll, POLL_MS);
}

function listen() {
  if (source) source.close();
  source = null;
  if (!window.EventSource) {
    if (!pollTimer) poll();
    return;
  }
  source = new EventSource("/events" + stopQuery());
  source.addEventListener("status", e => update(JSON.parse(e.data)));
  // the browser reconnects by itself; meanwhile the page polls
  source.onerror = () => { if (!pollTimer) pollTimer = setTimeout(poll, POLL_MS); };
  source.onopen = () => { if (pollTimer) { clearTimeout(pollTimer); pollTimer = null; } };
}

// for tests and the curious: 1 while the event stream is open (EventSource.OPEN)
window.seqatEventState = () => (source ? source.readyState : -1);

function setStop(v) {
  const next = Number.isFinite(v) && v > 0 ? v : null;
  if (next === stopCm) return;
  stopCm = next;
  listen();  // the stream's statuses follow the page's criterion
}

document.getElementById("stopform").addEventListener("submit", e => {
  e.preventDefault();
  setStop(parseFloat(document.getElementById("stop_cm").value));
});
document.getElementById("stop_cm").addEventListener("change", e => {
  setStop(parseFloat(e.target.value));
});

listen();
