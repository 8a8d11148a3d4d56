// The 2.5D viewer: one tile layer per perspective (PERSPECTIVES, written into the page by
// pipeline25d.viewer), from its XYZ folder or its PMTiles archive (read by HTTP range requests),
// a switch that keeps place and zoom, the view in the URL hash (#<id>/<zoom>/<lat>/<lng>[/up]),
// [ and ] to rotate through the azimuths, r to turn the view direction up the screen (the map
// rotated by −θ with leaflet-rotate, so buildings lean up), and a height tool: on a map seen at
// elevation φ from azimuth θ, a vertical edge of height h runs h·cot φ along d = (sin θ, cos θ),
// so h = (top − base)·d / cot φ, measured in the scene CRS (TO_SCENE). Clicks are turned into
// map coordinates by the map itself, so measuring works the same on the rotated map.
// Overlays and the basemap: overlays.js (told of each perspective shown by a 'perspective' event).
'use strict';

const EMPTY = 'data:image/gif;base64,R0lGODlhAQABAIAAAAAAAP///yH5BAEAAAAALAAAAAABAAEAAAIBRAA7';
const map = L.map('map', {zoomSnap: 0.25, rotate: true, bearing: 0, rotateControl: false, touchRotate: false,
                          shiftKeyRotate: false, compassBearing: false});
const byId = Object.fromEntries(PERSPECTIVES.map(p => [p.id, p]));
const ring = PERSPECTIVES.filter(p => p.elevation !== 90)
  .sort((a, b) => a.azimuth - b.azimuth || a.elevation - b.elevation);
const layers = {};
let current = null;
let up = false;                 // the view direction turned up the screen

// A pyramid holds only the tiles with data: ask for those alone (no 404s over empty ground).
function hasTile(p, c) {
  return ((p.tiles[c.z] || {})[c.x] || []).some(([y0, y1]) => c.y >= y0 && c.y <= y1);
}
const Tiles = L.TileLayer.extend({
  getTileUrl(c) { return hasTile(this.options.p, c) ? L.TileLayer.prototype.getTileUrl.call(this, c) : EMPTY; },
});
// The same pyramid from one PMTiles archive: each tile a range request through the pmtiles decoder.
const Archive = L.GridLayer.extend({
  initialize(options) {
    L.GridLayer.prototype.initialize.call(this, options);
    this._archive = new pmtiles.PMTiles(options.p.pmtiles);
  },
  createTile(c, done) {
    const img = document.createElement('img');
    img.alt = '';
    img.onload = () => { if (img.src.startsWith('blob:')) URL.revokeObjectURL(img.src); done(null, img); };
    img.onerror = () => done(new Error(`tile ${c.z}/${c.x}/${c.y} of ${this.options.p.pmtiles} is no image`), img);
    if (!hasTile(this.options.p, c)) {
      img.src = EMPTY;
      return img;
    }
    this._archive.getZxy(c.z, c.x, c.y).then(tile => {
      if (!tile) throw new Error(`${this.options.p.pmtiles} has no tile ${c.z}/${c.x}/${c.y}`);
      img.src = URL.createObjectURL(new Blob([tile.data], {type: `image/${this.options.p.ext}`}));
    }).catch(err => {
      document.getElementById('status').textContent = String(err);
      done(err, img);
    });
    return img;
  },
});

function label(p) {
  const acc = p.rmsd_m === null ? 'no check points' : `RMSD ${p.rmsd_m.toFixed(2)} m (${p.rmsd_px.toFixed(2)} px)`;
  const name = p.elevation === 90 ? 'nadir' : `azimuth ${p.azimuth}°, elevation ${p.elevation}°`;
  return `${name} <span class="acc">${p.warp} · ${acc}</span>`;
}

function writeHash() {
  if (!current) return;
  const c = map.getCenter();
  history.replaceState(null, '', `#${current}/${+map.getZoom().toFixed(2)}/${c.lat.toFixed(7)}/${c.lng.toFixed(7)}` +
                                 (up ? '/up' : ''));
}

// The compass angle on the web map of the view direction d = (sin θ, cos θ), which is given in the
// scene CRS: d taken to web mercator through the inverse of TO_SCENE's Jacobian at its origin (the
// scene's grid north is not true north: a UTM zone's meridian convergence reaches a few degrees).
function viewAngle(p) {
  const t = p.azimuth * Math.PI / 180, d = [Math.sin(t), Math.cos(t)];
  const [a, b, c, e] = [TO_SCENE.x[1], TO_SCENE.x[2], TO_SCENE.y[1], TO_SCENE.y[2]];   // ∂(x, y)/∂(u, v)
  const det = a * e - b * c, m = [(e * d[0] - b * d[1]) / det, (a * d[1] - c * d[0]) / det];
  return Math.atan2(m[0], m[1]) * 180 / Math.PI;
}

// View direction up: the map turned by minus the view's angle (leaflet-rotate's bearing turns it
// clockwise), so the camera looks up the screen; north up when off and on the nadir map.
function applyBearing() {
  const p = current && byId[current];
  map.setBearing(up && p && p.elevation !== 90 ? -viewAngle(p) : 0);
  document.getElementById('rotate-btn').classList.toggle('on', up);
}
function setUp(on) {
  up = on;
  applyBearing();
  writeHash();
}

function show(id) {
  if (current === id) return;
  if (current) map.removeLayer(layers[current]);
  current = id;
  layers[id].addTo(map);
  map.fire('perspective', {p: byId[id]});       // overlays.js redraws its layers for it
  document.querySelector(`input[value="${id}"]`).checked = true;
  document.getElementById('status').textContent = `showing ${id}` + (byId[id].pmtiles ? ' (PMTiles archive)' : '');
  clearMeasure();
  applyBearing();
  writeHash();
}

function step(k) {
  const i = ring.findIndex(p => p.id === current);
  if (!ring.length) return;
  show(ring[i < 0 ? (k > 0 ? 0 : ring.length - 1) : (i + k + ring.length) % ring.length].id);
}

// The view a hash names, or null: #<id>[/<zoom>/<lat>/<lng>][/up].
function parseHash() {
  const m = location.hash.match(/^#(az\d{3}_el\d{2})(?:\/([\d.]+)\/(-?[\d.]+)\/(-?[\d.]+))?(\/up)?$/);
  if (!m || !byId[m[1]]) return null;
  return {id: m[1], view: m[2] === undefined ? null : {zoom: +m[2], center: [+m[3], +m[4]]}, up: !!m[5]};
}
function applyHash() {
  const h = parseHash();
  if (!h) return;
  if (h.view) map.setView(h.view.center, h.view.zoom);
  up = h.up;
  show(h.id);
  applyBearing();
}

// --- measuring heights -------------------------------------------------------------------
const tool = {on: false, base: null, drawn: L.layerGroup().addTo(map)};

function toScene(latlng) {
  return mercatorToScene(L.CRS.EPSG3857.project(latlng));
}
function mercatorToScene(P) {
  const u = (P.x - TO_SCENE.origin[0]) / TO_SCENE.scale, v = (P.y - TO_SCENE.origin[1]) / TO_SCENE.scale;
  const t = [1, u, v, u * u, u * v, v * v];
  const poly = c => c.reduce((s, k, i) => s + k * t[i], 0);
  return [poly(TO_SCENE.x), poly(TO_SCENE.y)];
}

function edgeHeight(p, base, top) {
  const t = p.azimuth * Math.PI / 180, f = p.elevation * Math.PI / 180;
  const d = [Math.sin(t), Math.cos(t)], cot = Math.cos(f) / Math.sin(f);
  const v = [top[0] - base[0], top[1] - base[1]];
  return {height: (v[0] * d[0] + v[1] * d[1]) / cot, off: Math.abs(v[0] * d[1] - v[1] * d[0]), perPx: p.gsd / cot};
}

function say(text, height) {
  const out = document.getElementById('measure');
  out.textContent = text;
  out.dataset.height = height === undefined ? '' : String(height);
}

function clearMeasure() {
  tool.base = null;
  tool.drawn.clearLayers();
  say(tool.on ? 'click the base of a vertical edge' : '');
}

function setTool(on) {
  tool.on = on;
  document.getElementById('measure-btn').classList.toggle('on', on);
  document.getElementById('map').classList.toggle('measuring', on);
  clearMeasure();
}

map.on('click', e => {
  if (!tool.on) return;
  const p = byId[current];
  if (p.elevation === 90) {
    say('heights cannot be measured on the nadir map (elevation 90°): choose an oblique perspective');
    return;
  }
  if (!tool.base) {
    clearMeasure();
    tool.base = e.latlng;
    L.circleMarker(e.latlng, {radius: 4, color: '#d00'}).addTo(tool.drawn);
    say('now click the top of the same edge');
    return;
  }
  const m = edgeHeight(p, toScene(tool.base), toScene(e.latlng));
  L.polyline([tool.base, e.latlng], {color: '#d00', weight: 2}).addTo(tool.drawn);
  L.circleMarker(e.latlng, {radius: 4, color: '#d00'}).addTo(tool.drawn)
    .bindTooltip(`${m.height.toFixed(2)} m`, {permanent: true, direction: 'right'});
  say(`height ${m.height.toFixed(2)} m (±${m.perPx.toFixed(2)} m per pixel of click error; ` +
      `${m.off.toFixed(2)} m off the view direction)`, m.height);
  tool.base = null;
});

// --- page set-up -------------------------------------------------------------------------
const choices = document.getElementById('choices');
for (const p of PERSPECTIVES) {
  const b = p.lonlat_bounds;
  const options = {p, minZoom: 0, maxZoom: p.max_zoom + 3, maxNativeZoom: p.max_zoom, minNativeZoom: p.min_zoom,
                   bounds: [[b[1], b[0]], [b[3], b[2]]], attribution: 'pipeline25d', zIndex: 2};
  layers[p.id] = p.pmtiles ? new Archive(options) : new Tiles(`../tms/${p.id}/{z}/{x}/{y}.${p.ext}`, options);
  const row = document.createElement('label');
  row.innerHTML = `<input type="radio" name="persp" value="${p.id}"> ${label(p)}`;
  row.querySelector('input').addEventListener('change', () => show(p.id));
  choices.appendChild(row);
}
document.getElementById('prev').addEventListener('click', () => step(-1));
document.getElementById('next').addEventListener('click', () => step(1));
document.getElementById('measure-btn').addEventListener('click', () => setTool(!tool.on));
document.getElementById('rotate-btn').addEventListener('click', () => setUp(!up));
document.addEventListener('keydown', e => {
  if (e.ctrlKey || e.metaKey || e.altKey || e.target.tagName === 'INPUT' && e.target.type === 'text') return;
  if (e.key === '[') step(-1);
  else if (e.key === ']') step(1);
  else if (e.key === 'm') setTool(!tool.on);
  else if (e.key === 'r') setUp(!up);
  else if (e.key === 'Escape') setTool(false);
});
L.control.scale({imperial: false}).addTo(map);
map.on('moveend', writeHash);
window.addEventListener('hashchange', applyHash);

const start = parseHash();
up = !!(start && start.up);
if (start && start.view) {
  map.setView(start.view.center, start.view.zoom);
} else {
  const all = PERSPECTIVES.map(p => p.lonlat_bounds);
  map.fitBounds([[Math.min(...all.map(b => b[1])), Math.min(...all.map(b => b[0]))],
                 [Math.max(...all.map(b => b[3])), Math.max(...all.map(b => b[2]))]]);
}
show(start ? start.id : (ring[0] || PERSPECTIVES[0]).id);
