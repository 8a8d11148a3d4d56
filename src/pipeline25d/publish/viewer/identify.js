// Identify: which object a pixel of the shown map is (loaded after viewer.js, whose map, byId, current,
// hasTile and tool it uses). Each perspective with an id layer (p.ids) has, beside its map tiles, id tiles
// at the same XYZ positions (p.ids.url/{z}/{x}/{y}.bin, results/idtiles/<id>/ in a run: zlib of the tile's
// n distinct uint32 ids and each of its 256 × 256 pixels' index into them, little-endian,
// pipeline25d.stages.tiles.ids; 0 where the map is transparent), decoded here by DecompressionStream.
// The pointer's position is taken to the pixel of the finest id tile under it through the map's own
// projection, so it works the same on the map turned by leaflet-rotate. Hover highlights the object (its
// pixels of the id tiles, followed across tile edges, as an overlay); a click also shows its row of the
// objects table (OBJECTS: results/objects/shards as the page reaches it, index.json {slot: {district, bits}}, then
// <slot>/<local id >> (22 − bits)>.json {id: row}): id, name, type, model and measured height, attributes.
'use strict';

const identify = (() => {
  const LOCAL_BITS = 22, LOCAL = (1 << LOCAL_BITS) - 1, TILE = 256, MAX_TILES = 64;
  const tiles = new Map();                  // url -> Promise of Uint32Array | null
  const highlight = L.layerGroup().addTo(map);
  const state = {shown: null, pinned: null, hoverTimer: null, index: null, shards: new Map()};

  function fetchTile(p, z, x, y) {
    if (!hasTile({tiles: p.ids.tiles}, {z, x, y})) return Promise.resolve(null);
    const url = `${p.ids.url}/${z}/${x}/${y}.${p.ids.ext}`;
    if (!tiles.has(url)) {
      tiles.set(url, fetch(url).then(r => {
        if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
        return new Response(r.body.pipeThrough(new DecompressionStream('deflate'))).arrayBuffer();
      }).then(decode));
    }
    return tiles.get(url);
  }

  // A tile's ids (Uint32Array, 256 × 256) from its inflated bytes: n, n ids, n ≤ 256 ? uint8 : uint16 indices.
  function decode(buf) {
    const view = new DataView(buf), n = view.getUint32(0, true), ids = new Uint32Array(TILE * TILE);
    const palette = Array.from({length: n}, (_, k) => view.getUint32(4 + 4 * k, true));
    const at = 4 + 4 * n;
    if (n <= 256) {
      const index = new Uint8Array(buf, at, TILE * TILE);
      for (let k = 0; k < ids.length; k++) ids[k] = palette[index[k]];
    } else {
      for (let k = 0; k < ids.length; k++) ids[k] = palette[view.getUint16(at + 2 * k, true)];
    }
    return ids;
  }

  // {p, z, x, y, i, j}: the finest id tile and its pixel under latlng.
  function locate(latlng) {
    const p = byId[current];
    if (!p || !p.ids) return null;
    const z = p.ids.max_zoom, pt = map.project(latlng, z);
    const x = Math.floor(pt.x / TILE), y = Math.floor(pt.y / TILE);
    return {p, z, x, y, i: Math.floor(pt.x) - x * TILE, j: Math.floor(pt.y) - y * TILE};
  }

  async function idAt(latlng) {
    const at = locate(latlng);
    if (!at) return {at: null, id: 0};
    const tile = await fetchTile(at.p, at.z, at.x, at.y);
    return {at, id: tile ? tile[at.j * TILE + at.i] : 0};
  }

  // The object's pixels on the id tiles from the one under the pointer, followed into a neighbour tile
  // wherever they reach its edge (at most MAX_TILES tiles), each drawn as an image overlay.
  async function draw(at, id) {
    highlight.clearLayers();
    if (!id) return;
    const seen = new Set(), queue = [[at.x, at.y]];
    while (queue.length && seen.size < MAX_TILES) {
      const [x, y] = queue.shift(), key = `${x}/${y}`;
      if (seen.has(key)) continue;
      seen.add(key);
      const tile = await fetchTile(at.p, at.z, x, y);
      if (state.shown !== id) return;                  // the pointer moved on
      if (!tile) continue;
      const canvas = document.createElement('canvas');
      canvas.width = canvas.height = TILE;
      const ctx = canvas.getContext('2d'), img = ctx.createImageData(TILE, TILE);
      const edge = {l: false, r: false, t: false, b: false};
      let any = false;
      for (let k = 0; k < tile.length; k++) {
        if (tile[k] !== id) continue;
        any = true;
        img.data.set([255, 214, 0, 150], 4 * k);
        const i = k % TILE, j = (k - i) / TILE;
        edge.l ||= i === 0; edge.r ||= i === TILE - 1; edge.t ||= j === 0; edge.b ||= j === TILE - 1;
      }
      if (!any) continue;
      ctx.putImageData(img, 0, 0);
      const nw = map.unproject([x * TILE, y * TILE], at.z), se = map.unproject([(x + 1) * TILE, (y + 1) * TILE], at.z);
      L.imageOverlay(canvas.toDataURL(), L.latLngBounds(nw, se), {className: 'id-highlight', zIndex: 5})
        .addTo(highlight);
      if (edge.l) queue.push([x - 1, y]);
      if (edge.r) queue.push([x + 1, y]);
      if (edge.t) queue.push([x, y - 1]);
      if (edge.b) queue.push([x, y + 1]);
    }
  }

  async function row(id) {
    if (!OBJECTS) return null;
    state.index ||= fetch(`${OBJECTS}/index.json`).then(r => r.json());
    const slot = id >>> LOCAL_BITS, entry = (await state.index)[String(slot)];
    if (!entry) return null;
    const url = `${OBJECTS}/${slot}/${(id & LOCAL) >>> (LOCAL_BITS - entry.bits)}.json`;
    if (!state.shards.has(url)) state.shards.set(url, fetch(url).then(r => (r.ok ? r.json() : {})));
    return (await state.shards.get(url))[String(id)] || null;
  }

  function metres(v) { return v === null || v === undefined ? '–' : `${v.toFixed(2)} m`; }

  async function show(id) {
    const out = document.getElementById('object');
    out.dataset.id = String(id);
    if (!id) {
      out.textContent = 'nothing here (no object on this map)';
      return;
    }
    const r = await row(id);
    if (out.dataset.id !== String(id)) return;
    out.replaceChildren();
    const head = document.createElement('div');
    head.className = 'name';
    head.textContent = r ? `${r.name}${r.type ? ` (${r.type})` : ''}` : 'an object not in the table';
    const table = document.createElement('table');
    const lines = [['id', `${id} (district ${r ? r.district : id >>> LOCAL_BITS})`]];
    if (r) {
      lines.push(['model height', metres(r.model_height)], ['measured height', metres(r.measured_height)]);
      for (const [k, v] of Object.entries(r.attributes || {})) lines.push([k, typeof v === 'object' ? JSON.stringify(v) : String(v)]);
    }
    for (const [k, v] of lines) {
      const tr = table.insertRow();
      tr.insertCell().textContent = k;
      tr.insertCell().textContent = v;
    }
    out.append(head, table);
  }

  async function pick(latlng, pin) {
    const {at, id} = await idAt(latlng);
    if (!pin && state.pinned !== null) return;
    if (id !== state.shown) {
      state.shown = id;
      draw(at, id);
    }
    if (pin) {
      state.pinned = id || null;
      await show(id);
    }
  }

  map.on('click', e => { if (!tool.on) pick(e.latlng, true).catch(err => { document.getElementById('status').textContent = String(err); }); });
  map.on('mousemove', e => {
    clearTimeout(state.hoverTimer);
    if (!tool.on) state.hoverTimer = setTimeout(() => pick(e.latlng, false).catch(() => {}), 60);
  });
  map.on('perspective', () => {
    state.shown = state.pinned = null;
    highlight.clearLayers();
    const out = document.getElementById('object');
    out.textContent = byId[current].ids ? 'hover or click a building to identify it' : '';
    delete out.dataset.id;
  });
  document.addEventListener('keydown', e => {
    if (e.key === 'Escape') {
      state.shown = state.pinned = null;
      highlight.clearLayers();
    }
  });
  return {idAt, decode};
})();
