// A PMTiles archive from `patchwork export`, hosted as a CDN or an object store would host it:
// a static file server that answers byte ranges and nothing else, no tile server. MapLibre GL
// JS in a headless Chromium (WebGL on SwiftShader) loads it as 3D terrain through the pmtiles
// JS protocol; close up over each point it reports its terrain height there and the DEM pixels
// it was drawn from. Prints one JSON object for tests/daemon/web_browser.rs to judge, which
// holds the pixels to the daemon's own tiles; exits non-zero only when it could not run.
//
//   node tests/web/pmtiles.mjs --dir DIR --archive NAME --modules DIR/node_modules
//        --points lon,lat,... [--timeout-s 180]
//
// DIR holds the archive. $CHROMIUM names the browser (default /usr/bin/chromium).

import { createRequire } from 'node:module';
import fs from 'node:fs';
import http from 'node:http';
import path from 'node:path';

function fail(msg, code = 2) {
  process.stderr.write(`pmtiles.mjs: ${msg}\n`);
  process.exit(code);
}

const args = { timeout: 180 };
{
  const argv = process.argv.slice(2);
  for (let i = 0; i < argv.length; i += 2) {
    const [k, v] = [argv[i], argv[i + 1]];
    if (k === '--dir') args.dir = v;
    else if (k === '--archive') args.archive = v;
    else if (k === '--modules') args.modules = v;
    else if (k === '--timeout-s') args.timeout = Number(v);
    else if (k === '--points') {
      const n = v.split(',').map(Number);
      args.points = Array.from({ length: n.length >> 1 }, (_, j) => [n[2 * j], n[2 * j + 1]]);
    } else fail(`unknown argument ${k}`);
  }
  if (!args.dir || !args.archive || !args.modules || !args.points) {
    fail('usage: pmtiles.mjs --dir DIR --archive NAME --modules DIR --points lon,lat,...');
  }
}
const require = createRequire(path.resolve(args.modules, '..', 'resolve-from-here.js'));
const puppeteer = require('puppeteer-core');

// The page: the archive as a raster-DEM source through the pmtiles protocol, hillshaded and
// draped as terrain, with nothing from anywhere but this server.
const page = `<!doctype html>
<html><head><meta charset="utf-8"><link rel="icon" href="data:,">
<link rel="stylesheet" href="/lib/maplibre-gl/dist/maplibre-gl.css">
<script src="/lib/maplibre-gl/dist/maplibre-gl.js"></script>
<script src="/lib/pmtiles/dist/pmtiles.js"></script>
<style>html, body, #map { margin: 0; width: 100%; height: 100%; }</style>
</head><body><div id="map"></div><script>
// Missing tiles (beyond the exported area) as errors, not as empty images: MapLibre then
// draws the parent tile magnified, where an empty raster-DEM tile would stall it.
const protocol = new pmtiles.Protocol({ metadata: true, errorOnMissingTile: true });
maplibregl.addProtocol('pmtiles', protocol.tile);
const url = 'pmtiles://' + location.origin + '/${args.archive}';
const map = new maplibregl.Map({
  container: 'map',
  style: {
    version: 8,
    sources: { dem: { type: 'raster-dem', url, encoding: 'terrarium', tileSize: 256 } },
    layers: [{ id: 'shade', type: 'hillshade', source: 'dem' }],
    terrain: { source: 'dem', exaggeration: 1 },
  },
  center: ${JSON.stringify(args.points[0])},
  zoom: 12,
  attributionControl: false,
});
window.map = map;
window.events = [];
for (const t of ['load', 'idle', 'error', 'sourcedata']) map.on(t, (e) => window.events.push(t + (e && e.error ? ': ' + e.error.message : '')));
window.ready = new Promise((res, rej) => {
  map.once('idle', () => res());
  map.on('error', (e) => rej(new Error(String(e && e.error && e.error.message || e))));
});
</script></body></html>`;

// The static server: files of --dir and of the packages, whole or by byte range.
const log = { requests: 0, ranges: 0, bad: [], console_errors: [] };
const server = http.createServer((req, res) => {
  log.requests++;
  const u = new URL(req.url, 'http://x');
  if (u.pathname === '/' || u.pathname === '/index.html') {
    res.writeHead(200, { 'content-type': 'text/html; charset=utf-8' });
    return res.end(page);
  }
  const file = u.pathname.startsWith('/lib/')
    ? path.join(args.modules, decodeURIComponent(u.pathname.slice(5)))
    : path.join(args.dir, decodeURIComponent(u.pathname.slice(1)));
  let size;
  try {
    size = fs.statSync(file).size;
  } catch {
    log.bad.push({ url: req.url, status: 404 });
    res.writeHead(404);
    return res.end();
  }
  const type = file.endsWith('.js') ? 'text/javascript' : file.endsWith('.css') ? 'text/css' : 'application/octet-stream';
  const m = /^bytes=(\d+)-(\d*)$/.exec(req.headers.range || '');
  if (m) {
    log.ranges++;
    const start = Number(m[1]), end = Math.min(m[2] ? Number(m[2]) : size - 1, size - 1);
    res.writeHead(206, {
      'content-type': type, 'accept-ranges': 'bytes',
      'content-range': `bytes ${start}-${end}/${size}`, 'content-length': end - start + 1,
    });
    return fs.createReadStream(file, { start, end }).pipe(res);
  }
  res.writeHead(200, { 'content-type': type, 'content-length': size, 'accept-ranges': 'bytes' });
  fs.createReadStream(file).pipe(res);
});
await new Promise((res) => server.listen(0, '127.0.0.1', res));
const origin = `http://127.0.0.1:${server.address().port}`;

// In the page: close up over each point, MapLibre's terrain height and the DEM pixels around
// it, from the tile of the deepest zoom the view drew.
async function sample(points, ms) {
  const map = window.map, terrain = map.terrain, ml = window.maplibregl;
  const out = [];
  const deepest = terrain.tileManager.getSource().maxzoom;
  for (const p of points) {
    map.jumpTo({ center: p, zoom: deepest + 1, pitch: 0, bearing: 0 });
    const idle = await Promise.race([
      map.once('idle').then(() => true),
      new Promise((res) => setTimeout(() => res(false), ms)),
    ]);
    if (!idle) throw new Error(`the map did not settle over ${p}`);
    const zoom = Math.min(Math.max(...terrain.tileManager.getRenderableTiles().filter(Boolean)
      .map((t) => t.tileID.canonical.z)), deepest);
    const elevation = map.queryTerrainElevation(p);
    const ll = ml.LngLat.convert(p);
    const { tileID } = terrain._getOverscaledTileIDFromLngLatZoom(ll, zoom);
    const tile = terrain.tileManager.getSourceTile(tileID, true);
    if (!tile || !tile.dem) {
      out.push({ point: p, elevation, zoom, dem: null });
      continue;
    }
    const c = tile.tileID.canonical, dim = tile.dem.dim;
    const m = ml.MercatorCoordinate.fromLngLat(ll);
    const px = m.x * 2 ** c.z * dim - c.x * dim, py = m.y * 2 ** c.z * dim - c.y * dim;
    const cx = Math.floor(px), cy = Math.floor(py);
    const pixels = [[cx, cy], [cx + 1, cy], [cx, cy + 1], [cx + 1, cy + 1]];
    out.push({
      point: p, elevation, zoom, tile: [c.z, c.x, c.y], dim,
      pixels, dem: pixels.map(([i, j]) => tile.dem.get(i, j)),
    });
  }
  return out;
}

const chromium = process.env.CHROMIUM || '/usr/bin/chromium';
const browser = await puppeteer.launch({
  executablePath: chromium, headless: true,
  args: ['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--ignore-gpu-blocklist',
    '--enable-webgl', '--disable-dev-shm-usage', '--no-first-run', '--window-size=480,360'],
  protocolTimeout: (args.timeout + 120) * 1000, timeout: 60000,
}).catch((e) => fail(`could not start ${chromium}: ${e.message}`));
const report = { origin, ready: false, error: null };
try {
  const tab = await browser.newPage();
  await tab.setViewport({ width: 480, height: 360 });
  tab.on('console', (m) => { if (m.type() === 'error') log.console_errors.push(m.text()); });
  tab.on('pageerror', (e) => log.console_errors.push(String(e && e.stack || e)));
  tab.on('request', (r) => {
    const u = r.url();
    if (!u.startsWith(origin + '/') && !/^(data|blob|about):/.test(u)) log.bad.push({ url: u, external: true });
  });
  const t0 = Date.now();
  await tab.goto(origin + '/', { waitUntil: 'load', timeout: args.timeout * 1000 });
  const r = await tab.evaluate((ms) => Promise.race([
    window.ready.then(() => ({ ok: true }), (e) => ({ ok: false, error: String(e && e.message || e) })),
    new Promise((res) => setTimeout(() => res({ ok: false, error: `not ready after ${ms / 1000} s` }), ms)),
  ]), args.timeout * 1000);
  report.ready = r.ok;
  report.error = r.error || null;
  report.ready_ms = Date.now() - t0;
  report.events = await tab.evaluate(() => window.events.slice(0, 40));
  if (r.ok) report.samples = await tab.evaluate(sample, args.points, args.timeout * 1000);
} catch (e) {
  report.error = String(e && e.message || e);
} finally {
  await browser.close().catch(() => {});
  server.close();
}
Object.assign(report, log);
process.stdout.write(JSON.stringify(report, null, 1) + '\n');
process.exit(0);
