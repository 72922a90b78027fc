// The daemon's viewer page (/) in a headless Chromium, WebGL on SwiftShader, and its
// quantized-mesh tiles decoded straight from the daemon. Prints one JSON object on stdout
// for tests/daemon/web_browser.rs to judge; exits non-zero only when it could not run.
//
//   node tests/web/browser.mjs --base http://127.0.0.1:PORT --out DIR
//        [--modules DIR/node_modules] [--token T] [--timeout-s 180] [--points lon,lat,...]
//        [--viewer FILE]
//
// --modules is the node_modules folder holding tests/web/package.json's packages (default:
// $PATCHWORK_WEB_MODULES, else tests/web/node_modules). $CHROMIUM names the browser
// (default /usr/bin/chromium). --viewer serves FILE as the page at / in place of the one built
// into the daemon, to try a page against a daemon built without it.

import { createRequire } from 'node:module';
import fs from 'node:fs';
import http from 'node:http';
import https from 'node:https';
import path from 'node:path';
import zlib from 'node:zlib';
import { fileURLToPath } from 'node:url';

const here = path.dirname(fileURLToPath(import.meta.url));

function parseArgs(argv) {
  const a = { timeout: 180, modules: process.env.PATCHWORK_WEB_MODULES || path.join(here, 'node_modules') };
  for (let i = 0; i < argv.length; i++) {
    const k = argv[i], v = argv[i + 1];
    if (k === '--base') a.base = v.replace(/\/+$/, '');
    else if (k === '--out') a.out = v;
    else if (k === '--modules') a.modules = v;
    else if (k === '--token') a.token = v;
    else if (k === '--timeout-s') a.timeout = Number(v);
    else if (k === '--points') a.points = pairs(v.split(',').map(Number));
    else if (k === '--viewer') a.viewer = fs.readFileSync(v, 'utf8');
    else fail(`unknown argument ${k}`);
    i++;
  }
  if (!a.base || !a.out) fail('usage: browser.mjs --base http://HOST:PORT --out DIR [--modules DIR] [--token T]');
  return a;
}

function fail(msg, code = 2) {
  process.stderr.write(`browser.mjs: ${msg}\n`);
  process.exit(code);
}

const pairs = (v) => Array.from({ length: v.length >> 1 }, (_, k) => [v[2 * k], v[2 * k + 1]]);

const args = parseArgs(process.argv.slice(2));
const require = createRequire(path.join(args.modules, '..', 'resolve-from-here.js'));
const load = (name) => {
  try {
    return require(name);
  } catch (e) {
    fail(`cannot load ${name} from ${args.modules} (npm install tests/web/package.json there): ${e.message}`);
  }
};
const puppeteer = load('puppeteer-core');
const { PNG } = load('pngjs');
const qm = load('@here/quantized-mesh-decoder');
const decodeMesh = qm.default || qm;

const base = new URL(args.base);
const daemonUrl = (u) => u.startsWith(base.origin + '/');
const withToken = (u) => {
  if (!args.token) return u;
  const url = new URL(u, base);
  url.searchParams.set('token', args.token);
  return url.href;
};

/** GET from the daemon, the body raw (not decompressed) with the response's headers. */
function get(pathAndQuery, headers = {}) {
  const url = new URL(pathAndQuery, base);
  const h = { ...headers };
  if (args.token) h.Authorization = `Bearer ${args.token}`;
  const lib = url.protocol === 'https:' ? https : http;
  return new Promise((resolve, reject) => {
    const req = lib.get(url, { headers: h, timeout: 60000 }, (res) => {
      const chunks = [];
      res.on('data', (c) => chunks.push(c));
      res.on('end', () => resolve({ url: url.href, status: res.statusCode, headers: res.headers, body: Buffer.concat(chunks) }));
      res.on('error', reject);
    });
    req.on('timeout', () => req.destroy(new Error(`timed out: ${url.href}`)));
    req.on('error', reject);
  });
}

async function getJSON(p) {
  const r = await get(p, { Accept: 'application/json', 'Accept-Encoding': 'identity' });
  if (r.status !== 200) throw new Error(`GET ${r.url}: ${r.status} ${r.body.toString().slice(0, 200)}`);
  return JSON.parse(r.body.toString());
}

// ---------------------------------------------------------------------------------------
// Where to sample: points well inside the survey footprints.

function rings(geometry) {
  if (!geometry) return [];
  if (geometry.type === 'Polygon') return [geometry.coordinates];
  if (geometry.type === 'MultiPolygon') return geometry.coordinates;
  return [];
}

function inPolygon(p, poly) {
  let inside = false;
  for (const ring of poly) {
    for (let i = 0, j = ring.length - 1; i < ring.length; j = i++) {
      const [xi, yi] = ring[i], [xj, yj] = ring[j];
      if ((yi > p[1]) !== (yj > p[1]) && p[0] < ((xj - xi) * (p[1] - yi)) / (yj - yi) + xi) inside = !inside;
    }
  }
  return inside;
}

function choosePoints(fc) {
  const polys = fc.features.flatMap((f) => rings(f.geometry));
  const all = polys.flat(2);
  if (!all.length) return [];
  const w = Math.min(...all.map((c) => c[0])), e = Math.max(...all.map((c) => c[0]));
  const s = Math.min(...all.map((c) => c[1])), n = Math.max(...all.map((c) => c[1]));
  // Off any grid the daemon might sample on, and inside at least one footprint.
  const fractions = [[0.231, 0.313], [0.712, 0.274], [0.517, 0.488], [0.338, 0.741], [0.774, 0.693],
    [0.41, 0.59], [0.62, 0.37], [0.29, 0.52]];
  const round = (x) => Math.round(x * 1e7) / 1e7;
  return fractions
    .map(([fx, fy]) => [round(w + fx * (e - w)), round(s + fy * (n - s))])
    .filter((p) => polys.some((poly) => inPolygon(p, poly)))
    .slice(0, 5);
}

// ---------------------------------------------------------------------------------------
// Screenshots: is there relief, or one flat colour?

function relief(pngBytes) {
  const img = PNG.sync.read(Buffer.from(pngBytes));
  const { width, height, data } = img;
  // The map area, less the margins where the controls and credits sit.
  const x0 = Math.floor(width * 0.05), x1 = Math.ceil(width * 0.95);
  const y0 = Math.floor(height * 0.1), y1 = Math.ceil(height * 0.85);
  let n = 0, sum = 0, sum2 = 0, footprint = 0;
  const colours = new Set();
  for (let y = y0; y < y1; y++) {
    for (let x = x0; x < x1; x++) {
      const k = (y * width + x) * 4;
      const r = data[k], g = data[k + 1], b = data[k + 2];
      // The footprint outlines (red) are not relief.
      if (r > g + 60 && r > b + 60) { footprint++; continue; }
      const l = 0.2126 * r + 0.7152 * g + 0.0722 * b;
      n++; sum += l; sum2 += l * l;
      colours.add((r >> 2) << 12 | (g >> 2) << 6 | (b >> 2));
    }
  }
  const mean = n ? sum / n : 0;
  return {
    relief_stddev: n ? Math.sqrt(Math.max(0, sum2 / n - mean * mean)) : 0,
    mean_luminance: mean,
    distinct_colours: colours.size,
    footprint_pixels: footprint,
    size: [width, height],
  };
}

// ---------------------------------------------------------------------------------------
// One view of the page in its own tab.

async function runView(browser, view, points, log) {
  const page = await browser.newPage();
  await page.setViewport({ width: 960, height: 640 });
  const tag = (o) => ({ view, ...o });
  page.on('console', (m) => {
    const loc = m.location && m.location();
    const entry = tag({ type: m.type(), text: m.text(), url: loc && loc.url || null });
    if (m.type() === 'error') log.console_errors.push(entry);
    else if (m.type() === 'warn' || m.type() === 'warning') log.console_warnings.push(entry);
  });
  page.on('pageerror', (e) => log.console_errors.push(tag({ type: 'pageerror', text: String(e && e.stack || e) })));
  page.on('response', (r) => {
    const url = r.url();
    if (!daemonUrl(url)) return;
    log.responses++;
    const status = r.status();
    log.by_status[status] = (log.by_status[status] || 0) + 1;
    if (![200, 204, 304].includes(status)) log.bad_responses.push(tag({ url, status }));
    // What the quantized-mesh tiles say of their heights' frame, as Cesium received them.
    if (/\.terrain(\?|$)/.test(new URL(url).pathname + new URL(url).search)) {
      const warning = r.headers()['warning'] || null;
      log.terrain.responses++;
      if (warning) {
        log.terrain.warned++;
        log.terrain.warning = warning;
      }
    }
  });
  page.on('request', (r) => {
    const url = r.url();
    if (!daemonUrl(url) && !/^(data|blob|about|chrome|devtools):/.test(url)) log.external_requests.push(tag({ url }));
  });
  page.on('requestfailed', (r) => {
    const url = r.url(), error = r.failure() && r.failure().errorText;
    if (!daemonUrl(url)) return;
    // Requests the libraries cancel themselves (tiles no longer wanted) are not failures.
    if (error === 'net::ERR_ABORTED') { log.aborted_requests++; return; }
    log.bad_responses.push(tag({ url, status: null, error }));
  });

  if (args.viewer) {
    await page.setRequestInterception(true);
    page.on('request', (r) => {
      const u = new URL(r.url());
      if (u.origin === base.origin && u.pathname === '/') r.respond({ status: 200, contentType: 'text/html; charset=utf-8', body: args.viewer });
      else r.continue();
    });
  }

  const out = { ready: false, error: null };
  const t0 = Date.now();
  const url = withToken(`${base.origin}/?view=${view}`);
  try {
    await page.goto(url, { waitUntil: 'load', timeout: args.timeout * 1000 });
    await page.waitForFunction(() => !!(window.patchwork && window.patchwork.ready), { timeout: 30000 })
      .catch(() => { throw new Error(`${url} defined no window.patchwork.ready in 30 s: is it the viewer page?`); });
    const r = await page.evaluate((ms) => Promise.race([
      window.patchwork.ready.then(() => ({ ok: true }), (e) => ({ ok: false, error: String(e && e.message || e) })),
      new Promise((res) => setTimeout(() => res({ ok: false, error: `not ready after ${ms / 1000} s` }), ms)),
    ]), args.timeout * 1000);
    out.ready = r.ok;
    out.error = r.error || null;
  } catch (e) {
    out.error = String(e && e.message || e);
  }
  out.ready_ms = Date.now() - t0;

  const shot = path.join(args.out, `${view}.png`);
  try {
    const bytes = await page.screenshot({ path: shot, type: 'png' });
    Object.assign(out, relief(bytes), { screenshot: shot });
  } catch (e) {
    out.relief_stddev = null;
    out.error = out.error || `screenshot: ${e.message}`;
  }

  if (out.ready) {
    const t1 = Date.now();
    try {
      if (view === 'maplibre') {
        Object.assign(out, await page.evaluate(mapLibreHeights, points, 0));
        // Close up, a small window is enough, and SwiftShader draws it faster.
        await page.setViewport({ width: 320, height: 240 });
        out.close = await page.evaluate(mapLibreHeights, points, args.timeout * 1000);
      } else {
        Object.assign(out, await page.evaluate(cesiumHeights, points));
      }
    } catch (e) {
      out.error = `sampling heights: ${e.message}`;
    }
    out.sample_ms = Date.now() - t1;
  }
  await page.close();
  return out;
}

// In the page: MapLibre's terrain elevation at each point, and the DEM samples it came from:
// in the view as it is (closeUpMs 0), or close up over each point in turn, at the DEM's
// deepest zoom where the tiles promise the most, waiting up to closeUpMs for each.
async function mapLibreHeights(points, closeUpMs) {
  const map = window.patchwork.map, terrain = map.terrain;
  if (!terrain) throw new Error('no terrain set on the map');
  const ml = window.maplibregl;
  const sample = (p) => {
    // The zoom queryTerrainElevation samples at: the deepest terrain tile the view covers.
    const zoom = Math.min(Math.max(...terrain.tileManager.getRenderableTiles().filter(Boolean)
      .map((t) => t.tileID.canonical.z)), terrain.tileManager.maxzoom);
    const elevation = map.queryTerrainElevation(p);
    const ll = ml.LngLat.convert(p);
    const { tileID } = terrain._getOverscaledTileIDFromLngLatZoom(ll, zoom);
    const tile = terrain.tileManager.getSourceTile(tileID, true);
    if (!tile || !tile.dem) return { elevation, render_zoom: zoom, dem_zoom: null };
    const c = tile.tileID.canonical, dim = tile.dem.dim;
    const m = ml.MercatorCoordinate.fromLngLat(ll);
    // MapLibre reads DEM pixel i as lying at i (its corner), not i + 0.5 (its centre).
    const px = m.x * 2 ** c.z * dim - c.x * dim, py = m.y * 2 ** c.z * dim - c.y * dim;
    const cx = Math.floor(px), cy = Math.floor(py);
    const pixels = [[cx, cy], [cx + 1, cy], [cx, cy + 1], [cx + 1, cy + 1]];
    const centre = ([i, j]) => {
      const mc = new ml.MercatorCoordinate((c.x * dim + i + 0.5) / (2 ** c.z * dim), (c.y * dim + j + 0.5) / (2 ** c.z * dim));
      const g = mc.toLngLat();
      return [g.lng, g.lat];
    };
    return {
      elevation,
      render_zoom: zoom,
      dem_zoom: c.z,
      dem_tile: [c.x, c.y],
      dem_size: dim,
      exaggeration: terrain.exaggeration,
      pixels,
      frac: [px - cx, py - cy],
      dem: pixels.map(([i, j]) => tile.dem.get(i, j)),
      // Pixels outside [0, dim) are the border MapLibre copies from the neighbouring tile.
      inside: pixels.map(([i, j]) => i >= 0 && j >= 0 && i < dim && j < dim),
      centres: pixels.map(centre),
    };
  };
  if (!closeUpMs) {
    const samples = points.map(sample);
    return { elevations: samples.map((s) => s.elevation), exaggeration: terrain.exaggeration, samples };
  }
  const samples = [];
  map.resize();
  const deepest = terrain.tileManager.getSource().maxzoom;
  for (const p of points) {
    const t = performance.now();
    map.jumpTo({ center: p, zoom: deepest + 2, pitch: 0, bearing: 0 });
    const idle = await Promise.race([
      map.once('idle').then(() => true),
      new Promise((res) => setTimeout(() => res(false), closeUpMs)),
    ]);
    if (!idle) throw new Error(`the map did not settle over ${p} close up`);
    samples.push({ ...sample(p), ms: Math.round(performance.now() - t) });
  }
  return { elevations: samples.map((s) => s.elevation), samples };
}

// In the page: Cesium's most detailed terrain height at each point, and the level it used.
async function cesiumHeights(points) {
  const viewer = window.patchwork.viewer, tp = viewer.terrainProvider;
  const cartos = points.map(([lon, lat]) => Cesium.Cartographic.fromDegrees(lon, lat));
  const levels = cartos.map((c) => tp.availability ? tp.availability.computeMaximumLevelAtPosition(c) : null);
  const sampled = await Cesium.sampleTerrainMostDetailed(tp, cartos.map((c) => c.clone()));
  return {
    elevations: sampled.map((c) => (Number.isFinite(c.height) ? c.height : null)),
    levels,
    exaggeration: viewer.scene.verticalExaggeration,
  };
}

// ---------------------------------------------------------------------------------------
// Quantized-mesh tiles straight from the daemon.

const ACCEPT = 'application/vnd.quantized-mesh;extensions=octvertexnormals-watermask-metadata,application/octet-stream;q=0.9,*/*;q=0.01';

function tileOf(lon, lat, level) {
  const span = 180 / 2 ** level;
  return [Math.floor((lon + 180) / span), Math.floor((lat + 90) / span)];
}

function tileRect(level, x, y) {
  const span = 180 / 2 ** level;
  return [-180 + x * span, -90 + y * span, -180 + (x + 1) * span, -90 + (y + 1) * span];
}

function available(layer, level, x, y) {
  return (layer.available && layer.available[level] || [])
    .some((r) => x >= r.startX && x <= r.endX && y >= r.startY && y <= r.endY);
}

const meshCache = new Map();

async function fetchMesh(layer, level, x, y) {
  const key = `${level}/${x}/${y}`;
  if (meshCache.has(key)) return meshCache.get(key);
  const tpl = (layer.tiles && layer.tiles[0]) || '{z}/{x}/{y}.terrain';
  const rel = tpl.replace('{z}', level).replace('{x}', x).replace('{y}', y).replace('{version}', layer.version || '');
  const r = await get(new URL(rel, new URL('/terrain/', base)).href, { Accept: ACCEPT, 'Accept-Encoding': 'gzip' });
  const t = {
    url: r.url, level, x, y, status: r.status,
    content_type: r.headers['content-type'] || null,
    content_encoding: r.headers['content-encoding'] || null,
    etag: r.headers.etag || null,
    bytes: r.body.length,
    errors: [],
  };
  let mesh = null;
  if (r.status !== 200) {
    t.errors.push(`HTTP ${r.status}: ${r.body.toString().slice(0, 200)}`);
  } else {
    try {
      const raw = t.content_encoding === 'gzip' ? zlib.gunzipSync(r.body) : r.body;
      // A fresh ArrayBuffer: the decoder's typed arrays need the buffer's own alignment.
      mesh = decodeMesh(raw.buffer.slice(raw.byteOffset, raw.byteOffset + raw.length));
      t.decoded_bytes = raw.length;
    } catch (e) {
      t.errors.push(`decode: ${e.message}`);
    }
  }
  if (mesh) check(t, mesh);
  const entry = { t, mesh };
  meshCache.set(key, entry);
  return entry;
}

function check(t, mesh) {
  const { header: h, vertexData: vd, triangleIndices: tri } = mesh;
  const n = vd.length / 3;
  t.vertices = n;
  t.triangles = tri.length / 3;
  t.min_height = h.minHeight;
  t.max_height = h.maxHeight;
  t.quantization_step = (h.maxHeight - h.minHeight) / 32767;
  const ext = mesh.extensions || {};
  t.extensions = {
    octvertexnormals: ext.vertexNormals ? ext.vertexNormals.length === 2 * n : false,
    watermask: ext.waterMask ? [1, 256 * 256].includes(ext.waterMask.byteLength) : false,
    metadata: ext.metadata !== undefined,
  };
  const e = t.errors;
  if (!Number.isFinite(h.minHeight) || !Number.isFinite(h.maxHeight) || h.minHeight > h.maxHeight) e.push(`header heights ${h.minHeight}..${h.maxHeight}`);
  if (h.minHeight < -12000 || h.maxHeight > 9000) e.push(`header heights ${h.minHeight}..${h.maxHeight} out of this world`);
  if (n < 3 || t.triangles < 1) e.push(`${n} vertices, ${t.triangles} triangles`);
  for (const i of tri) if (i >= n) { e.push(`triangle index ${i} ≥ ${n} vertices`); break; }
  let umin = 32767, umax = 0, vmin = 32767, vmax = 0, hmin = 32767, hmax = 0;
  for (let i = 0; i < n; i++) {
    umin = Math.min(umin, vd[i]); umax = Math.max(umax, vd[i]);
    vmin = Math.min(vmin, vd[n + i]); vmax = Math.max(vmax, vd[n + i]);
    hmin = Math.min(hmin, vd[2 * n + i]); hmax = Math.max(hmax, vd[2 * n + i]);
  }
  if (umin !== 0 || umax !== 32767 || vmin !== 0 || vmax !== 32767) e.push(`vertices span u ${umin}..${umax}, v ${vmin}..${vmax}, not the whole tile`);
  if (umax > 32767 || vmax > 32767 || hmax > 32767) e.push('a quantized value above 32767');
  if (h.maxHeight > h.minHeight && (hmin !== 0 || hmax !== 32767)) e.push(`quantized heights span ${hmin}..${hmax}, not the header's min..max`);
  const edges = { west: [mesh.westIndices, 0, 0], east: [mesh.eastIndices, 0, 32767], south: [mesh.southIndices, 1, 0], north: [mesh.northIndices, 1, 32767] };
  for (const [name, [idx, axis, value]] of Object.entries(edges)) {
    if (!idx || idx.length < 2) { e.push(`${name} edge has ${idx ? idx.length : 0} vertices`); continue; }
    const bad = Array.from(idx).find((i) => i >= n || vd[axis * n + i] !== value);
    if (bad !== undefined) e.push(`${name} edge vertex ${bad} is not on the ${name} edge`);
  }
  for (const [name, ok] of Object.entries(t.extensions)) if (!ok) e.push(`extension ${name} missing or malformed`);
  if (t.content_type !== 'application/vnd.quantized-mesh') e.push(`Content-Type ${t.content_type}`);
  if (t.content_encoding !== 'gzip') e.push(`Content-Encoding ${t.content_encoding} though gzip was accepted`);
  t.ok = e.length === 0;
}

const heightOf = (mesh, i) => {
  const n = mesh.vertexData.length / 3, h = mesh.header;
  return h.minHeight + (mesh.vertexData[2 * n + i] / 32767) * (h.maxHeight - h.minHeight);
};

/** The vertices on one edge, by their position along it, with their heights. */
function edgeVertices(mesh, side) {
  const n = mesh.vertexData.length / 3;
  const idx = { west: mesh.westIndices, east: mesh.eastIndices, south: mesh.southIndices, north: mesh.northIndices }[side];
  const along = side === 'west' || side === 'east' ? 1 : 0;
  return Array.from(idx).map((i) => [mesh.vertexData[along * n + i], heightOf(mesh, i)]).sort((a, b) => a[0] - b[0]);
}

async function edgePair(layer, level, a, b, kind) {
  const [A, B] = await Promise.all([fetchMesh(layer, level, ...a), fetchMesh(layer, level, ...b)]);
  const r = { kind, level, tiles: [a, b], ok: false };
  if (!A.mesh || !B.mesh) { r.error = 'a tile did not decode'; return r; }
  const [sa, sb] = kind === 'west-east' ? ['east', 'west'] : ['north', 'south'];
  const ea = edgeVertices(A.mesh, sa), eb = edgeVertices(B.mesh, sb);
  const pa = ea.map((v) => v[0]), pb = eb.map((v) => v[0]);
  r.vertices = [ea.length, eb.length];
  r.positions_match = pa.length === pb.length && pa.every((v, i) => v === pb[i]);
  if (!r.positions_match) {
    r.only_in_first = pa.filter((v) => !pb.includes(v)).slice(0, 20);
    r.only_in_second = pb.filter((v) => !pa.includes(v)).slice(0, 20);
  }
  const hb = new Map(eb);
  let worst = 0;
  for (const [p, h] of ea) if (hb.has(p)) worst = Math.max(worst, Math.abs(h - hb.get(p)));
  r.max_height_difference = worst;
  r.quantization_steps = [A.t.quantization_step, B.t.quantization_step];
  r.tolerance = Math.max(...r.quantization_steps);
  r.ok = r.positions_match && worst <= r.tolerance + 1e-9;
  return r;
}

/** Two tile pairs that share an edge inside the data: west-east and south-north. */
async function quantizedMesh(bbox, points) {
  const out = { tiles: [], edges: [], samples: [], errors: [] };
  const layer = await getJSON('/terrain/layer.json');
  out.layer = { format: layer.format, scheme: layer.scheme, projection: layer.projection, minzoom: layer.minzoom,
    maxzoom: layer.maxzoom, bounds: layer.bounds, extensions: layer.extensions, tiles: layer.tiles, version: layer.version,
    levels: (layer.available || []).length };
  if (layer.format !== 'quantized-mesh-1.0') out.errors.push(`layer.json format ${layer.format}`);
  if (layer.scheme !== 'tms') out.errors.push(`layer.json scheme ${layer.scheme}`);
  const maxLevel = Math.min(layer.maxzoom ?? (layer.available || []).length - 1, (layer.available || []).length - 1);
  const [w, s, e, n] = bbox;
  const cx = (w + e) / 2, cy = (s + n) / 2;
  // The deepest level with a tile boundary near the data's middle, both sides available.
  for (const kind of ['west-east', 'south-north']) {
    let found = null;
    for (let level = maxLevel; level >= 1 && !found; level--) {
      const span = 180 / 2 ** level;
      if (kind === 'west-east') {
        const xb = Math.round((cx + 180) / span), lon = -180 + xb * span;
        const y = Math.floor((cy + 90) / span);
        if (Math.abs(lon - cx) < 0.3 * (e - w) && available(layer, level, xb - 1, y) && available(layer, level, xb, y)) found = [level, [xb - 1, y], [xb, y]];
      } else {
        const yb = Math.round((cy + 90) / span), lat = -90 + yb * span;
        const x = Math.floor((cx + 180) / span);
        if (Math.abs(lat - cy) < 0.3 * (n - s) && available(layer, level, x, yb - 1) && available(layer, level, x, yb)) found = [level, [x, yb - 1], [x, yb]];
      }
    }
    if (!found) { out.errors.push(`no ${kind} tile pair inside the data`); continue; }
    out.edges.push(await edgePair(layer, found[0], found[1], found[2], kind));
  }
  // The tile Cesium samples each point from, at the deepest level available there, and
  // the mesh's own height at the point (the triangle that holds it).
  for (const p of points) {
    let level = maxLevel;
    while (level > 0 && !available(layer, level, ...tileOf(p[0], p[1], level))) level--;
    const [x, y] = tileOf(p[0], p[1], level);
    const { t, mesh } = await fetchMesh(layer, level, x, y);
    const sample = { point: p, level, tile: [x, y], quantization_step: t.quantization_step ?? null, mesh_height: null, triangle: null };
    if (mesh) Object.assign(sample, meshAt(mesh, tileRect(level, x, y), p));
    out.samples.push(sample);
  }
  out.tiles = [...meshCache.values()].map((v) => v.t);
  out.ok = out.errors.length === 0 && out.tiles.every((t) => t.ok) && out.edges.every((r) => r.ok);
  return out;
}

/** The mesh's height at p: the triangle holding p, its corners, and the barycentric mix. */
function meshAt(mesh, rect, p) {
  const n = mesh.vertexData.length / 3, vd = mesh.vertexData, tri = mesh.triangleIndices;
  const u = ((p[0] - rect[0]) / (rect[2] - rect[0])) * 32767, v = ((p[1] - rect[1]) / (rect[3] - rect[1])) * 32767;
  for (let k = 0; k < tri.length; k += 3) {
    const [a, b, c] = [tri[k], tri[k + 1], tri[k + 2]];
    const [ua, va, ub, vb, uc, vc] = [vd[a], vd[n + a], vd[b], vd[n + b], vd[c], vd[n + c]];
    const d = (vb - vc) * (ua - uc) + (uc - ub) * (va - vc);
    if (d === 0) continue;
    const l1 = ((vb - vc) * (u - uc) + (uc - ub) * (v - vc)) / d;
    const l2 = ((vc - va) * (u - uc) + (ua - uc) * (v - vc)) / d;
    const l3 = 1 - l1 - l2;
    const eps = -1e-9;
    if (l1 < eps || l2 < eps || l3 < eps) continue;
    const corner = (i) => [rect[0] + (vd[i] / 32767) * (rect[2] - rect[0]), rect[1] + (vd[n + i] / 32767) * (rect[3] - rect[1]), heightOf(mesh, i)];
    return {
      mesh_height: l1 * heightOf(mesh, a) + l2 * heightOf(mesh, b) + l3 * heightOf(mesh, c),
      triangle: [corner(a), corner(b), corner(c)],
      weights: [l1, l2, l3],
    };
  }
  return { mesh_height: null, triangle: null };
}

// ---------------------------------------------------------------------------------------

async function main() {
  fs.mkdirSync(args.out, { recursive: true });
  const timings = {};
  const t0 = Date.now();
  const fc = await getJSON('/surveys.geojson').catch((e) => fail(`the daemon at ${base.origin}: ${e.message}`, 3));
  const points = args.points || choosePoints(fc);
  const all = fc.features.flatMap((f) => rings(f.geometry)).flat(2);
  const bbox = all.length
    ? [Math.min(...all.map((c) => c[0])), Math.min(...all.map((c) => c[1])), Math.max(...all.map((c) => c[0])), Math.max(...all.map((c) => c[1]))]
    : null;
  let reference = null;
  if (points.length) {
    reference = await getJSON(`/heights?points=${points.flat().join(',')}&error=0&crs=EPSG:4326`).catch((e) => ({ error: e.message }));
  }

  const chromium = process.env.CHROMIUM || '/usr/bin/chromium';
  if (!fs.existsSync(chromium)) fail(`no browser at ${chromium} (set CHROMIUM)`);
  const flags = ['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader',
    '--ignore-gpu-blocklist', '--enable-webgl', '--disable-dev-shm-usage', '--no-first-run', '--hide-scrollbars',
    '--window-size=960,640'];
  let browser;
  try {
    browser = await puppeteer.launch({
      executablePath: chromium, headless: true, args: flags,
      protocolTimeout: (args.timeout + 120) * 1000, timeout: 60000,
    });
  } catch (e) {
    fail(`could not start ${chromium}: ${e.message}`);
  }
  timings.browser_start_ms = Date.now() - t0;

  const log = { console_errors: [], console_warnings: [], bad_responses: [], external_requests: [], responses: 0, by_status: {}, aborted_requests: 0, terrain: { responses: 0, warned: 0, warning: null } };
  const result = {};
  try {
    const probe = await browser.newPage();
    result.browser = await browser.version();
    result.webgl = await probe.evaluate(() => {
      const gl = document.createElement('canvas').getContext('webgl2');
      if (!gl) return null;
      const ext = gl.getExtension('WEBGL_debug_renderer_info');
      return ext ? gl.getParameter(ext.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
    });
    await probe.close();
    if (!result.webgl) fail(`${chromium} started without WebGL 2 (flags: ${flags.join(' ')})`);
    for (const view of ['maplibre', 'cesium']) {
      const t = Date.now();
      result[view] = await runView(browser, view, points, log);
      timings[`${view}_ms`] = Date.now() - t;
    }
  } finally {
    await browser.close().catch(() => {});
  }

  const t2 = Date.now();
  let quantized = null;
  try {
    quantized = bbox ? await quantizedMesh(bbox, points) : { ok: false, errors: ['no footprints'] };
  } catch (e) {
    quantized = { ok: false, errors: [String(e && e.stack || e)] };
  }
  timings.quantized_mesh_ms = Date.now() - t2;
  timings.total_ms = Date.now() - t0;

  const report = {
    base: base.origin,
    browser: result.browser,
    webgl: result.webgl,
    chromium_flags: flags,
    console_errors: log.console_errors,
    console_warnings: log.console_warnings,
    bad_responses: log.bad_responses,
    external_requests: log.external_requests,
    responses: { count: log.responses, by_status: log.by_status, aborted: log.aborted_requests },
    terrain_responses: log.terrain,
    points,
    bbox,
    reference_heights: reference,
    maplibre: result.maplibre,
    cesium: result.cesium,
    quantized_mesh: quantized,
    timings,
  };
  process.stdout.write(JSON.stringify(report, null, 1) + '\n');
}

main().catch((e) => fail(String(e && e.stack || e), 1));
