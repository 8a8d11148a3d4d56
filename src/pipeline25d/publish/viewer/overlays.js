// Overlays on the ground and the basemap of the 2.5D viewer (loaded after viewer.js, whose map, byId,
// current and mercatorToScene it uses).
// OVERLAYS (the config's viewer.overlays, GeoJSON in WGS 84 beside the page) and ?overlay=<url>[,<url>]
// are drawn on every perspective, turned or not. A map shows ground where it is, so a feature without
// height is drawn as it is. A point h metres above the ground (its "height" property, else its 3rd
// coordinate) shows h·cot φ further along the view direction d = (sin θ, cos θ) of the scene CRS
// (pipeline25d.geometry.camera.map_affine; the height tool reads the same displacement back), so each
// such vertex is moved there, per perspective: in the scene CRS by TO_SCENE, back to web mercator by
// Newton steps on it. A click on a feature shows its properties in a popup and goes on to the map (identify,
// height tool). BASEMAP (config viewer.basemap): an XYZ layer under the maps, only when given.
'use strict';

const overlayState = [];          // {name, color, data, on, drawn: {pid: L.GeoJSON}}
const PALETTE_JS = ['#ff00ff', '#00e5ff', '#ffea00', '#ff6d00', '#76ff03'];

// ∂(x, y)/∂(X, Y) of TO_SCENE at web-mercator point P.
function sceneJacobian(P) {
  const u = (P.x - TO_SCENE.origin[0]) / TO_SCENE.scale, v = (P.y - TO_SCENE.origin[1]) / TO_SCENE.scale;
  const du = [0, 1, 0, 2 * u, v, 0], dv = [0, 0, 1, 0, u, 2 * v];
  const dot = (c, t) => c.reduce((s, k, i) => s + k * t[i], 0) / TO_SCENE.scale;
  return [[dot(TO_SCENE.x, du), dot(TO_SCENE.x, dv)], [dot(TO_SCENE.y, du), dot(TO_SCENE.y, dv)]];
}

// [lng, lat] where perspective p shows a point h metres above the ground at [lng, lat].
function displaced(lng, lat, h, p) {
  if (!h || p.elevation === 90) return [lng, lat];
  const t = p.azimuth * Math.PI / 180, f = p.elevation * Math.PI / 180, k = h * Math.cos(f) / Math.sin(f);
  let P = L.CRS.EPSG3857.project(L.latLng(lat, lng));
  const s0 = mercatorToScene(P), goal = [s0[0] + k * Math.sin(t), s0[1] + k * Math.cos(t)];
  for (let i = 0; i < 4; i++) {
    const s = mercatorToScene(P), [[a, b], [c, e]] = sceneJacobian(P), r = [goal[0] - s[0], goal[1] - s[1]];
    const det = a * e - b * c;
    P = L.point(P.x + (e * r[0] - b * r[1]) / det, P.y + (a * r[1] - c * r[0]) / det);
  }
  const ll = L.CRS.EPSG3857.unproject(P);
  return [ll.lng, ll.lat];
}

function heightOf(props, coords) {
  const h = props && props.height !== undefined && props.height !== null ? Number(props.height) : coords[2];
  return Number.isFinite(h) ? h : 0;
}

// A geometry with every position moved to where perspective p shows it.
function moveGeometry(g, props, p) {
  if (!g) return g;
  if (g.type === 'GeometryCollection') return {...g, geometries: g.geometries.map(x => moveGeometry(x, props, p))};
  const move = c => typeof c[0] === 'number' ? displaced(c[0], c[1], heightOf(props, c), p) : c.map(move);
  return {...g, coordinates: move(g.coordinates)};
}

function popupText(props) {
  const div = document.createElement('div');
  div.textContent = Object.entries(props || {}).map(([k, v]) => `${k}: ${v}`).join('\n');
  div.style.whiteSpace = 'pre';
  return div;
}

function drawn(o, p) {
  if (!o.drawn[p.id]) {
    const features = (o.data.features || [o.data]).map(ft => ({...ft, geometry: moveGeometry(ft.geometry, ft.properties, p)}));
    o.drawn[p.id] = L.geoJSON({type: 'FeatureCollection', features}, {
      style: {color: o.color, weight: 3, opacity: 0.9},
      pointToLayer: (ft, ll) => L.circleMarker(ll, {radius: 5, color: '#000', weight: 1, fillColor: o.color, fillOpacity: 1}),
      onEachFeature: (ft, layer) => {
        // Not bindPopup: its click handler stops the event, so a click on a feature (a footprint over its
        // roof) would never reach the map: no identify, no height tool. This popup opens and the click goes on.
        if (ft.properties && Object.keys(ft.properties).length) {
          layer.on('click', e => L.popup({autoPan: false}).setLatLng(e.latlng).setContent(popupText(ft.properties)).openOn(map));
        }
      },
    });
  }
  return o.drawn[p.id];
}

// Show each overlay that is on, as perspective p shows it.
function redrawOverlays(p) {
  for (const o of overlayState) {
    for (const layer of Object.values(o.drawn)) map.removeLayer(layer);
    if (o.on && o.data && p) drawn(o, p).addTo(map);
  }
}

function addOverlay(name, url, color) {
  const o = {name, color, data: null, on: true, drawn: {}};
  overlayState.push(o);
  const row = document.createElement('label');
  row.innerHTML = '<input type="checkbox" checked> <span class="swatch"></span> ';
  row.querySelector('.swatch').style.background = color;
  row.append(name);
  row.dataset.overlay = name;
  row.querySelector('input').addEventListener('change', e => { o.on = e.target.checked; redrawOverlays(byId[current]); });
  document.getElementById('layers').appendChild(row);
  fetch(url).then(r => {
    if (!r.ok) throw new Error(`overlay ${url}: HTTP ${r.status}`);
    return r.json();
  }).then(data => {
    o.data = data;
    row.classList.add('loaded');
    redrawOverlays(byId[current]);
  }).catch(err => { document.getElementById('status').textContent = String(err); });
}

for (const o of OVERLAYS) addOverlay(o.name, o.url, o.color);
new URLSearchParams(location.search).getAll('overlay').flatMap(v => v.split(',')).filter(Boolean)
  .forEach((url, i) => addOverlay(decodeURIComponent(url.split('/').pop()) || url, url,
                                  PALETTE_JS[(OVERLAYS.length + i) % PALETTE_JS.length]));
map.on('perspective', e => redrawOverlays(e.p));

if (BASEMAP) {
  const base = L.tileLayer(BASEMAP.url, {attribution: BASEMAP.attribution, maxNativeZoom: BASEMAP.max_zoom,
                                          maxZoom: 24, zIndex: 1}).addTo(map);
  const row = document.createElement('label');
  row.innerHTML = '<input type="checkbox" checked> basemap';
  row.querySelector('input').addEventListener('change', e => e.target.checked ? base.addTo(map) : map.removeLayer(base));
  document.getElementById('layers').appendChild(row);
}
