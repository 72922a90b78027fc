"""Web tiles side by side: the daemon's HTTP tiles beside what users would serve instead, in one
run, each warm.

Usage: python3 bench/web_tiles.py [--smoke] [--bin PATH] [--seconds S] [--clients N] [--out DIR]

Contenders, each serving over HTTP on a loopback port:

- patchwork png: the daemon's terrarium PNG tiles (`/tiles/{z}/{x}/{y}.png?encoding=terrarium
  &size=256`, cut at the zoom's error), from a store of the Copernicus and NASADEM N34W119 tiles;
- titiler png: TiTiler (titiler.core's TilerFactory in a FastAPI app, under uvicorn) serving
  `/cog/tiles/WebMercatorQuad/{z}/{x}/{y}.png?url=COG&algorithm=terrarium` from the Copernicus
  COG, bilinear for both resampling and reprojection (its default, nearest, is faster and
  further from the survey);
- patchwork terrain: the daemon's quantized-mesh tiles (`/terrain/{L}/{x}/{y}.terrain`, with
  normals, water mask and metadata, gzip);
- ctod-like terrain: what Cesium Terrain On Demand does, in a Starlette app under uvicorn:
  rio-tiler reads the geographic tile's 257 × 257 window of the same COG (WGS1984Quad, buffer
  0.5 so that pixel centres lie on the tile's edges, bilinear), pydelatin meshes it at max
  error G(L)/2 (the daemon's mesh share of Cesium's G(L) = 77067.34 / 2^L m), nodata filled
  with 0, and quantized-mesh-encoder encodes it with normals and a water mask; gzip by
  Starlette's middleware.

Each Python server runs as many uvicorn workers as there are CPUs; the daemon uses its own
thread pool. For zooms (web mercator) and levels (geographic TMS) 8, 11 and 14, a set of distinct
tiles over the data is requested once (its first-request latency), then timed again, one at a
time on a kept-alive connection (p50, p99). Then 32 concurrent clients (aiohttp) cycle over
every tile of every zoom for a fixed time: tiles per second. Bytes per tile are as sent (gzip
where the server gzips). Errors are against the surveys each contender serves (the daemon: both,
their range where both have data; the COG's servers: Copernicus): PNG heights (decoded)
outside the range of the surveys' bilinear surfaces at the pixel centres (GDAL's warp with
XSCALE=YSCALE=1), and against GDAL's own bilinear warp of the surveys (Copernicus over
NASADEM), which averages over about a pixel where it downsamples; mesh heights outside that
range at the vertices, and over the mesh's surface (its triangles interpolated on a 64² grid
of points inside the tile, in triangles whose vertices all have data).

Inputs: the full files in ../shared/data (or PATCHWORK_SHARED_DATA); with --smoke, the crops in
tests/data, few tiles and a short load, so that it runs in seconds (results go to a temporary
folder unless --out is given). Writes OUT/web_tiles.csv and OUT/web_tiles.png (OUT defaults to
docs/bench) and prints a markdown table. Needs a release build (`cargo build --release`) and
`python3 -m pip install -r bench/requirements.txt`.
"""

import argparse
import asyncio
import csv
import gzip
import importlib.util
import io
import json
import math
import os
import random
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.parse
import warnings

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
DATA = os.environ.get("PATCHWORK_SHARED_DATA", os.path.join(REPO, "..", "shared", "data"))
FULL = [
    os.path.join(DATA, "Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif"),
    os.path.join(DATA, "NASADEM_HGT_n34w119.tif"),
]
SMOKE = [
    os.path.join(REPO, "tests", "data", "copernicus_n34w119_crop.tif"),
    os.path.join(REPO, "tests", "data", "nasadem_n34w119_crop.tif"),
]
ZOOMS = [8, 11, 14]
GRID = 256  # cells a side of the CTOD-like read (257 × 257 vertices)
CONTENDERS = ["patchwork png", "patchwork png, no tile cache", "titiler png",
              "patchwork terrain", "patchwork terrain, no tile cache", "ctod-like terrain"]


def _checks():
    """tests/python/web_tiles.py: the decoders, tile grids and GDAL warps the test uses."""
    spec = importlib.util.spec_from_file_location("web_tiles_check", os.path.join(REPO, "tests", "python", "web_tiles.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


wt = _checks()


# --- the Python servers (run in their own processes by `--serve`) -----------------------


def make_titiler_app():
    from fastapi import FastAPI
    from starlette.responses import PlainTextResponse
    from titiler.core.factory import TilerFactory

    app = FastAPI()
    app.include_router(TilerFactory(router_prefix="/cog").router, prefix="/cog")
    app.add_api_route("/ping", lambda: PlainTextResponse("ok"))
    return app


def make_ctod_app():
    import morecantile
    import quantized_mesh_encoder as qme
    from pydelatin import Delatin
    from quantized_mesh_encoder.extensions import VertexNormalsExtension, WaterMaskExtension
    from rio_tiler.errors import TileOutsideBounds
    from rio_tiler.io import Reader
    from starlette.applications import Starlette
    from starlette.middleware import Middleware
    from starlette.middleware.gzip import GZipMiddleware
    from starlette.responses import PlainTextResponse, Response
    from starlette.routing import Route

    cog = os.environ["WEB_TILES_COG"]
    tms = morecantile.tms.get("WGS1984Quad")

    def terrain(request):
        z, x, y = (int(request.path_params[k]) for k in ("z", "x", "y"))
        if not (0 <= z <= 24 and 0 <= x < 2 ** (z + 1) and 0 <= y < 2 ** z):
            return PlainTextResponse("no such tile", status_code=400)
        accept = request.headers.get("accept", "")
        exts = accept.split("extensions=")[1].split(";")[0].split("-") if "extensions=" in accept else []
        w, s, e, n = wt.geo_bounds(z, x, y)
        heights = np.zeros((GRID + 1, GRID + 1), dtype=np.float32)
        with Reader(cog, tms=tms) as r:
            try:
                img = r.tile(x, 2 ** z - 1 - y, z, tilesize=GRID, buffer=0.5,
                             resampling_method="bilinear", reproject_method="bilinear")
                heights = img.array[0].filled(0).astype(np.float32)
            except TileOutsideBounds:
                pass
        mesh = Delatin(heights, max_error=wt.G0 / 2 ** z / 2)
        v, tri = first_use_order(mesh.vertices, mesh.triangles)
        pos = np.empty((len(v), 3), dtype=np.float64)
        pos[:, 0] = w + v[:, 0] / GRID * (e - w)
        # pydelatin counts y from the array's last row up (heights[GRID - y, x] = z).
        pos[:, 1] = s + v[:, 1] / GRID * (n - s)
        pos[:, 2] = v[:, 2]
        extensions = []
        if "octvertexnormals" in exts:
            extensions.append(VertexNormalsExtension(indices=tri, positions=pos))
        if "watermask" in exts:
            extensions.append(WaterMaskExtension(data=0))
        buf = io.BytesIO()
        qme.encode(buf, pos, tri, bounds=(w, s, e, n), extensions=extensions)
        return Response(buf.getvalue(), media_type="application/vnd.quantized-mesh")

    return Starlette(
        routes=[Route("/terrain/{z}/{x}/{y}.terrain", terrain), Route("/ping", lambda r: PlainTextResponse("ok"))],
        middleware=[Middleware(GZipMiddleware, minimum_size=0)],
    )


def first_use_order(vertices, triangles):
    """Vertices renumbered in the order the triangles first use them, which quantized-mesh's
    high-water-mark index encoding needs (quantized-mesh-encoder writes the indices as given)."""
    flat = triangles.ravel().astype(np.int64)
    ids, first = np.unique(flat, return_index=True)
    order = ids[np.argsort(first)]
    remap = np.empty(len(vertices), dtype=np.int64)
    remap[order] = np.arange(len(order))
    return vertices[order], remap[triangles].astype(np.uint32)


def serve(kind, port, cog, workers):
    import uvicorn

    os.environ["WEB_TILES_COG"] = cog
    factory = {"titiler": "make_titiler_app", "ctod": "make_ctod_app"}[kind]
    uvicorn.run(f"web_tiles:{factory}", factory=True, host="127.0.0.1", port=port, workers=workers,
                app_dir=HERE, log_level="warning", access_log=False)


# --- processes -------------------------------------------------------------------------------


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_http(base, path, seconds, proc, what):
    h = wt.Http(base)
    deadline = time.monotonic() + seconds
    while True:
        if proc.poll() is not None:
            sys.exit(f"{what} exited ({proc.returncode}) before it answered")
        try:
            status, _, _ = h.get(path)
            if status == 200:
                return
        except OSError:
            pass
        if time.monotonic() > deadline:
            sys.exit(f"{what} did not answer {path} within {seconds} s")
        time.sleep(0.2)


def start_daemon(bin_path, sources, tmp, config=None):
    """A daemon on free loopback ports with a store under `tmp`, the sources dropped into its
    inbox (by rename, as docs/OPERATIONS.md says), with `config` (TOML text) as its config file."""
    grpc_port, http_port = free_port(), free_port()
    inbox = os.path.join(tmp, "inbox")
    os.makedirs(inbox)
    env = dict(os.environ, PATCHWORK_DATA_DIR=os.path.join(tmp, "data"), PATCHWORK_INBOX=inbox,
               PATCHWORK_LISTEN=f"127.0.0.1:{grpc_port}", PATCHWORK_HTTP_LISTEN=f"127.0.0.1:{http_port}",
               PATCHWORK_SETTLE_MS="300", PATCHWORK_LOG="warn", PATCHWORK_ALLOW_EMULATED_GPU="0")
    for k in ("PATCHWORK_READ_TOKEN", "PATCHWORK_ADMIN_TOKEN", "PATCHWORK_CONFIG"):
        env.pop(k, None)
    if config is not None:
        env["PATCHWORK_CONFIG"] = os.path.join(tmp, "patchwork.toml")
        with open(env["PATCHWORK_CONFIG"], "w") as f:
            f.write(config)
    log = open(os.path.join(tmp, "serve.log"), "wb")
    proc = subprocess.Popen([bin_path, "serve"], env=env, stdout=log, stderr=log)
    base = f"http://127.0.0.1:{http_port}"
    wait_http(base, "/surveys.geojson", 60, proc, "the daemon")
    for src in sources:
        name = os.path.basename(src)
        shutil.copy(src, os.path.join(inbox, name + ".part"))
        os.rename(os.path.join(inbox, name + ".part"), os.path.join(inbox, name))
    return proc, base


def wait_ingest(proc, base, n, what):
    """Until the daemon lists `n` survey footprints."""
    t0 = time.monotonic()
    h = wt.Http(base)
    while True:
        if proc.poll() is not None:
            sys.exit(f"{what} exited ({proc.returncode}); see its serve.log")
        _, _, body = h.get("/surveys.geojson")
        try:
            feats = json.loads(body).get("features", [])
        except ValueError:
            feats = []
        if len(feats) == n:
            return time.monotonic() - t0
        if time.monotonic() - t0 > 900:
            sys.exit(f"{what}: the surveys were not ingested within 15 minutes")
        time.sleep(0.5)


def start_python_server(kind, cog, workers):
    port = free_port()
    proc = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--serve", kind, "--port", str(port),
                             "--cog", cog, "--workers", str(workers)])
    base = f"http://127.0.0.1:{port}"
    wait_http(base, "/ping", 120, proc, kind)
    return proc, base


def stop(proc):
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def ensure_cog(path, tmp):
    """`path` if it already is a COG (tiled, with overviews), else a COG of it written with
    rasterio (GDAL's COG driver)."""
    import rasterio
    from rasterio.shutil import copy as rio_copy

    with rasterio.open(path) as ds:
        tiled = ds.block_shapes[0][0] > 1 and ds.block_shapes[0][0] != ds.height
        if tiled and ds.overviews(1):
            return path
    out = os.path.join(tmp, "copernicus_cog.tif")
    rio_copy(path, out, driver="COG", COMPRESS="DEFLATE", PREDICTOR="3", BLOCKSIZE="128", OVERVIEWS="AUTO")
    return out


# --- tiles -----------------------------------------------------------------------------------


def data_extent(path):
    import rasterio

    with rasterio.open(path) as ds:
        b = ds.bounds
    return (b.left, b.bottom, b.right, b.top)


def merc_tiles(z, extent, k, rng):
    w, s, e, n = extent
    x0, y0 = wt.merc_tile_of(w, n, z)
    x1, y1 = wt.merc_tile_of(e, s, z)
    inside = []
    for y in range(y0, y1 + 1):
        for x in range(x0, x1 + 1):
            b = wt.merc_bounds(z, x, y)
            lon, lat = wt.TO_LONLAT.transform((b[0] + b[2]) / 2, (b[1] + b[3]) / 2)
            if w < lon < e and s < lat < n:
                inside.append((x, y))
    if not inside:
        inside = [wt.merc_tile_of((w + e) / 2, (s + n) / 2, z)]
    return sorted(rng.sample(inside, min(k, len(inside))))


def geo_tiles(level, extent, k, rng):
    w, s, e, n = extent
    x0, y0 = wt.geo_tile_of(w, s, level)
    x1, y1 = wt.geo_tile_of(e, n, level)
    inside = []
    for y in range(y0, y1 + 1):
        for x in range(x0, x1 + 1):
            b = wt.geo_bounds(level, x, y)
            if w < (b[0] + b[2]) / 2 < e and s < (b[1] + b[3]) / 2 < n:
                inside.append((x, y))
    if not inside:
        inside = [wt.geo_tile_of((w + e) / 2, (s + n) / 2, level)]
    return sorted(rng.sample(inside, min(k, len(inside))))


def requests_for(contender, base, cog, z, tiles, version):
    """(path, headers) for each tile."""
    out = []
    for x, y in tiles:
        if contender.startswith("patchwork png"):
            out.append((f"/tiles/{z}/{x}/{y}.png?encoding=terrarium&size=256", {"Accept-Encoding": "gzip"}))
        elif contender == "titiler png":
            q = urllib.parse.urlencode({"url": cog, "algorithm": "terrarium", "resampling": "bilinear",
                                        "reproject": "bilinear"})
            out.append((f"/cog/tiles/WebMercatorQuad/{z}/{x}/{y}.png?{q}", {"Accept-Encoding": "gzip"}))
        else:
            v = f"?v={urllib.parse.quote(str(version))}" if contender.startswith("patchwork") and version is not None else ""
            out.append((f"/terrain/{z}/{x}/{y}.terrain{v}", {"Accept": wt.QM_ACCEPT, "Accept-Encoding": "gzip"}))
    return out


def timed(h, path, headers):
    t0 = time.perf_counter()
    hdrs, body = h.ok(path, headers)
    return (time.perf_counter() - t0) * 1e3, hdrs, body


def percentile(xs, p):
    xs = sorted(xs)
    if not xs:
        return float("nan")
    k = (len(xs) - 1) * p / 100
    lo, hi = math.floor(k), math.ceil(k)
    return xs[lo] + (xs[hi] - xs[lo]) * (k - lo)


async def _load(base, reqs, clients, seconds):
    import aiohttp

    done = failed = 0
    nbytes = 0
    conn = aiohttp.TCPConnector(limit=clients)
    async with aiohttp.ClientSession(base_url=base, connector=conn, auto_decompress=False,
                                     timeout=aiohttp.ClientTimeout(total=300)) as session:
        stop_at = time.perf_counter() + seconds

        async def client(k):
            nonlocal done, failed, nbytes
            order = reqs[:]
            random.Random(k).shuffle(order)
            i = 0
            while time.perf_counter() < stop_at:
                path, headers = order[i % len(order)]
                i += 1
                async with session.get(path, headers=headers) as r:
                    body = await r.read()
                    if r.status == 200:
                        done += 1
                        nbytes += len(body)
                    else:
                        failed += 1

        t0 = time.perf_counter()
        await asyncio.gather(*(client(k) for k in range(clients)))
        elapsed = time.perf_counter() - t0
    return done / elapsed, done, failed, elapsed


# --- errors against the surveys -------------------------------------------------------------


def bilinear(survey, lon, lat):
    """The survey's bilinear surface at points (NaN off its valid cells)."""
    c, r = survey.position(lon, lat)
    c0, r0 = np.floor(c).astype(np.int64), np.floor(r).astype(np.int64)
    rows, cols = survey.z.shape
    ok = (c0 >= 0) & (r0 >= 0) & (c0 < cols - 1) & (r0 < rows - 1)
    c0, r0 = np.clip(c0, 0, cols - 2), np.clip(r0, 0, rows - 2)
    fc, fr = c - c0, r - r0
    z = survey.z
    v = (z[r0, c0] * (1 - fc) * (1 - fr) + z[r0, c0 + 1] * fc * (1 - fr)
         + z[r0 + 1, c0] * (1 - fc) * fr + z[r0 + 1, c0 + 1] * fc * fr)
    return np.where(ok, v, np.nan)


def outside(h, lo, hi):
    ok = ~np.isnan(h) & ~np.isnan(lo)
    return np.maximum(np.maximum(lo - h, h - hi), 0.0)[ok]


def summary(d):
    d = np.abs(np.asarray(d))
    if d.size == 0:
        return float("nan"), float("nan")
    return float(d.max()), float(np.sqrt((d ** 2).mean()))


def png_errors(bodies, z, tiles, surveys, datasets):
    from PIL import Image
    from gdal_compare import warp

    outs, gdal, missing, total = [], [], 0, 0
    for (x, y), body in zip(tiles, bodies):
        img = np.asarray(Image.open(io.BytesIO(body)).convert("RGBA"))
        h = np.where(img[..., 3] == 255, wt.terrarium(img), np.nan)
        b = wt.merc_bounds(z, x, y)
        n = img.shape[0]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: no survey there
            pts = np.stack([s.warp(b, n, True) for s in surveys])
            lo, hi = np.nanmin(pts, axis=0), np.nanmax(pts, axis=0)
        outs.append(outside(h, lo, hi))
        # GDAL's own warp of the surveys, Copernicus drawn last (over NASADEM).
        g = warp(datasets[::-1], "EPSG:3857", b, n).astype(np.float64)
        both = ~np.isnan(h) & ~np.isnan(g)
        gdal.append((h - g)[both])
        missing += int((np.isnan(h) & ~np.isnan(lo)).sum())
        total += int((~np.isnan(lo)).sum())
    return summary(np.concatenate(outs)), summary(np.concatenate(gdal)), missing / max(total, 1)


def mesh_errors(raws, level, tiles, surveys):
    """Mesh heights outside the surveys' range at the vertices, and over the triangles
    (interpolated on a 64² grid of points inside the tile, where the triangle's three vertices
    all have data: a server draws something across the data's edge, but it is no survey's)."""
    import matplotlib.tri as mtri

    vert, surf, nv = [], [], []
    for (x, y), raw in zip(tiles, raws):
        m = wt.Mesh(level, x, y, raw, f"terrain {level}/{x}/{y}")
        nv.append(m.walk["vertices"])
        ref = np.stack([bilinear(s, m.lon, m.lat) for s in surveys])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            lo, hi = np.nanmin(ref, axis=0), np.nanmax(ref, axis=0)
        vert.append(outside(m.height, lo, hi))
        have = ~np.isnan(lo)
        w, s, e, n = m.bounds
        k = 64
        gx = w + (np.arange(k) + 0.5) * (e - w) / k
        gy = s + (np.arange(k) + 0.5) * (n - s) / k
        X, Y = np.meshgrid(gx, gy)
        try:
            tri = mtri.Triangulation(m.lon, m.lat, m.triangles)
            hz = mtri.LinearTriInterpolator(tri, m.height)(X, Y).filled(np.nan)
            t_of = tri.get_trifinder()(X, Y)
        except (ValueError, RuntimeError):
            continue
        inside = (t_of >= 0) & have[m.triangles[np.maximum(t_of, 0)]].all(axis=-1)
        ref = np.stack([bilinear(sv, X, Y) for sv in surveys])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            surf.append(outside(np.where(inside, hz, np.nan), np.nanmin(ref, axis=0), np.nanmax(ref, axis=0)))
    return (summary(np.concatenate(vert)), summary(np.concatenate(surf)) if surf else (float("nan"),) * 2,
            statistics.mean(nv))


# --- the run ------------------------------------------------------------------------------------


def chart(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(16, 8))
    axes = axes.ravel()
    x = np.arange(len(ZOOMS))
    wdt = 0.8 / len(CONTENDERS)
    panels = [("p50_first_ms", "first request p50, ms"), ("p50_ms", "warm p50, ms"), ("p99_ms", "warm p99, ms"),
              ("bytes_per_tile", "bytes per tile"), ("surface_err_max_m", "largest error against the surveys, m")]
    for k, c in enumerate(CONTENDERS):
        sub = {r["zoom"]: r for r in rows if r["contender"] == c}
        off = (k - (len(CONTENDERS) - 1) / 2) * wdt
        for ax, (key, _) in zip([axes[0], axes[1], axes[2], axes[4], axes[5]], panels):
            ax.bar(x + off, [float(sub[z][key]) for z in ZOOMS], wdt, label=c)
        axes[3].bar(k, sub[ZOOMS[0]]["tiles_per_s"], 0.6, label=c)
    for ax, (_, title) in zip([axes[0], axes[1], axes[2], axes[4], axes[5]], panels):
        ax.set_title(title)
        ax.set_xticks(x, [f"zoom / level {z}" for z in ZOOMS])
        ax.set_yscale("log")
    axes[3].set_title("tiles/s, 32 clients, every zoom")
    axes[3].set_yscale("log")
    axes[3].set_xticks(range(len(CONTENDERS)), [c.replace(" ", "\n", 1).replace(", ", ",\n") for c in CONTENDERS],
                       fontsize=7)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv):
    ap = argparse.ArgumentParser()
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--bin", default=os.path.join(REPO, "target", "release", "patchwork"))
    ap.add_argument("--seconds", type=float)
    ap.add_argument("--clients", type=int, default=32)
    ap.add_argument("--tiles", type=int, help="distinct tiles a zoom (24; 3 with --smoke)")
    ap.add_argument("--out")
    ap.add_argument("--serve", choices=["titiler", "ctod"], help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--cog", help=argparse.SUPPRESS)
    ap.add_argument("--workers", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args(argv[1:])
    if args.serve:
        return serve(args.serve, args.port, args.cog, args.workers)

    sys.path.insert(0, HERE)
    import rasterio

    sources = SMOKE if args.smoke else FULL
    seconds = args.seconds or (2.0 if args.smoke else 10.0)
    per_zoom = args.tiles or (3 if args.smoke else 24)
    passes = 2 if args.smoke else 3
    out_dir = args.out or (tempfile.mkdtemp(prefix="web-tiles-smoke-") if args.smoke else os.path.join(REPO, "docs", "bench"))
    for s in sources:
        if not os.path.isfile(s):
            sys.exit(f"missing {s}: the shared data folder is expected beside the checkout (or PATCHWORK_SHARED_DATA)")
    if not os.path.isfile(args.bin):
        sys.exit(f"missing {args.bin}: run `cargo build --release` first, or pass --bin")
    workers = os.cpu_count() or 1
    tmp = tempfile.mkdtemp(prefix="web-tiles-")
    cog = ensure_cog(sources[0], tmp)
    surveys = [wt.Survey(p) for p in sources]
    extent = data_extent(sources[0])
    rng = random.Random(1)
    merc = {z: merc_tiles(z, extent, per_zoom, rng) for z in ZOOMS}
    geo = {z: geo_tiles(z, extent, per_zoom, rng) for z in ZOOMS}

    procs = []
    rows = []
    try:
        # The daemon as configured by default (64 MiB of encoded tiles kept), and one that
        # keeps none, so that its warm requests are cuts and encodings, as TiTiler's are.
        daemon, daemon_base = start_daemon(args.bin, sources, os.path.join(tmp, "daemon"))
        procs.append(daemon)
        bare, bare_base = start_daemon(args.bin, sources, os.path.join(tmp, "daemon-no-cache"),
                                       "[http]\ntile_cache_mb = 0\n")
        procs.append(bare)
        took = max(wait_ingest(daemon, daemon_base, len(sources), "the daemon"),
                   wait_ingest(bare, bare_base, len(sources), "the daemon without a tile cache"))
        print(f"daemons: {len(sources)} surveys ingested by each in {took:.1f} s (both at once)", flush=True)
        version = wt.Http(daemon_base).json("/terrain/layer.json").get("version")
        titiler, titiler_base = start_python_server("titiler", cog, workers)
        procs.append(titiler)
        ctod, ctod_base = start_python_server("ctod", cog, workers)
        procs.append(ctod)
        bases = {"patchwork png": daemon_base, "patchwork png, no tile cache": bare_base, "titiler png": titiler_base,
                 "patchwork terrain": daemon_base, "patchwork terrain, no tile cache": bare_base,
                 "ctod-like terrain": ctod_base}
        datasets = [rasterio.open(p) for p in sources]
        for c in CONTENDERS:
            h = wt.Http(bases[c])
            tiles_of = merc if "png" in c else geo
            all_reqs = []
            for z in ZOOMS:
                reqs = requests_for(c, bases[c], cog, z, tiles_of[z], version)
                all_reqs += reqs
                first = [timed(h, p, hd)[0] for p, hd in reqs]
                warm, bodies, sizes = [], [], []
                for _ in range(passes):
                    for p, hd in reqs:
                        ms, hdrs, body = timed(h, p, hd)
                        warm.append(ms)
                        if len(bodies) < len(reqs):
                            bodies.append(body)
                            sizes.append(len(body))
                row = {"contender": c, "zoom": z, "tiles": len(reqs), "requests_timed": len(warm),
                       "p50_first_ms": statistics.median(first), "p50_ms": percentile(warm, 50),
                       "p99_ms": percentile(warm, 99), "bytes_per_tile": statistics.mean(sizes)}
                # Each against the surveys it serves: the daemon both, the COG's servers Copernicus.
                own = slice(None) if c.startswith("patchwork") else slice(0, 1)
                if "png" in c:
                    (em, er), (gm, gr), miss = png_errors(bodies, z, tiles_of[z], surveys[own], datasets[own])
                    row.update({"err_max_m": em, "err_rms_m": er, "surface_err_max_m": em, "surface_err_rms_m": er,
                                "vs_gdal_max_m": gm, "vs_gdal_rms_m": gr, "nodata_frac": miss, "vertices": ""})
                else:
                    raws = [gzip.decompress(b) if b[:2] == b"\x1f\x8b" else b for b in bodies]
                    (em, er), (sm, sr), nv = mesh_errors(raws, z, tiles_of[z], surveys[own])
                    row.update({"err_max_m": em, "err_rms_m": er, "surface_err_max_m": sm, "surface_err_rms_m": sr,
                                "vs_gdal_max_m": "", "vs_gdal_rms_m": "", "nodata_frac": "", "vertices": nv,
                                "raw_bytes_per_tile": statistics.mean(len(r) for r in raws)})
                row.setdefault("raw_bytes_per_tile", row["bytes_per_tile"])
                rows.append(row)
                print(f"{c:>18} z{z:<2}: {len(reqs)} tiles, first {row['p50_first_ms']:.1f} ms, warm p50 "
                      f"{row['p50_ms']:.1f} / p99 {row['p99_ms']:.1f} ms, {row['bytes_per_tile']:.0f} B, "
                      f"error max {row['err_max_m']:.3f} m", flush=True)
            tps, done, failed, elapsed = asyncio.run(_load(bases[c], all_reqs, args.clients, seconds))
            if failed:
                print(f"{c}: {failed} requests failed under load", flush=True)
            for r in rows:
                if r["contender"] == c:
                    r["tiles_per_s"] = tps
                    r["load_failed"] = failed
            print(f"{c:>18}: {tps:.1f} tiles/s with {args.clients} clients ({done} in {elapsed:.1f} s)", flush=True)
        for d in datasets:
            d.close()
    finally:
        for p in procs:
            stop(p)
        shutil.rmtree(tmp, ignore_errors=True)

    os.makedirs(out_dir, exist_ok=True)
    fields = ["contender", "zoom", "tiles", "requests_timed", "p50_first_ms", "p50_ms", "p99_ms", "tiles_per_s",
              "load_failed", "bytes_per_tile", "raw_bytes_per_tile", "vertices", "err_max_m", "err_rms_m",
              "surface_err_max_m", "surface_err_rms_m", "vs_gdal_max_m", "vs_gdal_rms_m", "nodata_frac"]
    with open(os.path.join(out_dir, "web_tiles.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{r[k]:.4g}" if isinstance(r.get(k), float) else r.get(k, "")) for k in fields})
    chart(rows, os.path.join(out_dir, "web_tiles.png"))

    print()
    print(f"{'smoke run: crops, ' if args.smoke else ''}{per_zoom} tiles a zoom at most, {passes} warm passes, "
          f"{args.clients} clients for {seconds:g} s, {workers} uvicorn workers a Python server")
    print()
    print("| contender | zoom | first p50 ms | warm p50 ms | warm p99 ms | tiles/s (32 clients) | bytes/tile | "
          "error at samples max / RMS m | surface error max / RMS m | vs GDAL warp max / RMS m |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        vs = f"{r['vs_gdal_max_m']:.2f} / {r['vs_gdal_rms_m']:.2f}" if r["vs_gdal_max_m"] != "" else "—"
        print(f"| {r['contender']} | {r['zoom']} | {r['p50_first_ms']:.1f} | {r['p50_ms']:.1f} | {r['p99_ms']:.1f} | "
              f"{r['tiles_per_s']:.0f} | {r['bytes_per_tile']:.0f} | {r['err_max_m']:.2f} / {r['err_rms_m']:.3f} | "
              f"{r['surface_err_max_m']:.2f} / {r['surface_err_rms_m']:.3f} | {vs} |")
    print()
    print(f"wrote {os.path.join(out_dir, 'web_tiles.csv')} and web_tiles.png")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
