"""Checks the daemon's web tiles with independent readers, as web map clients and their users
would read them.

    python3 tests/python/web_tiles.py --http http://127.0.0.1:PORT [--grpc 127.0.0.1:PORT] [--token T]

The daemon must hold the Copernicus and NASADEM crops of tests/data (and nothing else over
them). What is checked, against what:

- PNG tiles (terrarium and mapbox, 256 and 512, zooms 10-14) are decoded with Pillow and numpy
  by the formulas and compared with GDAL's bilinear warp (rasterio) of the crops onto the same
  EPSG:3857 tile grid. Two warps: GDAL's own (which widens its bilinear kernel when it
  downsamples, averaging over the output pixel's footprint), and the same warp with
  XSCALE=YSCALE=1, which evaluates each survey's bilinear surface at the pixel centre. Where
  only Copernicus has data (NASADEM three samples away or more), a tile cut at e must lie
  within e of that surface, and at `error=0` match it to the encoding's quantization; against
  GDAL's own warp it may differ by e plus the relief of the samples GDAL averaged. Where both
  have data, it must lie between the two surveys' surfaces, widened by e. Alpha must be 0
  exactly where both warps are nodata, away from the data's edge, where a pixel centre that
  falls within a pixel of a source pixel's edge is decided by each side's half-pixel rounding.
  Both encodings must decode to the same heights within their steps (1/256 m, 0.1 m).
- GeoTIFF tiles (rasterio): EPSG:3857, georeferenced to the tile, nodata -9999, the PNG's
  heights within 1/256 m; with --grpc, the gRPC tile of the same ROI in EPSG:3857.
- quantized-mesh tiles (decoded with quantized-mesh-tile, and with a byte walk of the format
  to check the extensions it skips): headers, gzip applied once, extensions as asked, vertex
  heights against /heights within G(L), and shared edges between neighbouring tiles.
- ETags and 304s, errors, TileJSON, layer.json and the survey footprints.

Prints a summary ending in a line starting "ok: "; exits non-zero at the first failure.
"""

import argparse
import gzip
import http.client
import io
import json
import math
import os
import struct
import sys
import urllib.parse
import warnings

import numpy as np
import rasterio
from numpy.lib.stride_tricks import sliding_window_view
from PIL import Image
from pyproj import Transformer
from quantized_mesh_tile.terrain import TerrainTile
from rasterio.io import MemoryFile
from rasterio.transform import from_bounds
from rasterio.warp import Resampling, reproject

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
COPERNICUS = os.path.join(REPO, "tests", "data", "copernicus_n34w119_crop.tif")
NASADEM = os.path.join(REPO, "tests", "data", "nasadem_n34w119_crop.tif")

# Web Mercator: the half-width of the square world, and the equator's length as the contract
# writes it (e(z) = 0.5 × 40075016.686 / (size · 2^z)).
HALF = math.pi * 6378137.0
EQUATOR = 40075016.686
# Cesium's geometric error of terrain level 0 (two root tiles, 65 heights a side).
G0 = 77067.34
QM_MAX = 32767
QM_ACCEPT = "application/vnd.quantized-mesh;extensions=octvertexnormals-watermask-metadata"
TERRARIUM_STEP = 1.0 / 256.0
MAPBOX_STEP = 0.1
# f32 heights of a few thousand metres, positions carried through two CRSs: well under this.
FLOAT_SLACK = 2e-3

TO_LONLAT = Transformer.from_crs("EPSG:3857", "EPSG:4326", always_xy=True)
TO_ECEF = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)


class Failure(Exception):
    pass


def require(ok, msg):
    """Fails with `msg` (or what the callable `msg` returns) unless `ok`."""
    if not ok:
        raise Failure(msg() if callable(msg) else msg)


def say(msg):
    print(msg, flush=True)


# --- HTTP --------------------------------------------------------------------------------


class Http:
    """GETs on one kept-alive connection; every response is read whole."""

    def __init__(self, base, token=None):
        u = urllib.parse.urlsplit(base)
        require(u.scheme == "http", f"--http must be an http:// URL, not {base}")
        self.base = base.rstrip("/")
        self.host, self.port = u.hostname, u.port or 80
        self.token = token
        self.conn = None
        self.requests = 0

    def get(self, path, headers=None):
        """(status, headers with lower-case names, body bytes) of GET `path`."""
        h = {"Accept-Encoding": "identity"}
        if self.token:
            h["Authorization"] = f"Bearer {self.token}"
        h.update(headers or {})
        for attempt in range(2):
            try:
                if self.conn is None:
                    self.conn = http.client.HTTPConnection(self.host, self.port, timeout=120)
                self.conn.request("GET", path, headers=h)
                r = self.conn.getresponse()
                body = r.read()
                self.requests += 1
                return r.status, {k.lower(): v for k, v in r.getheaders()}, body
            except (http.client.HTTPException, ConnectionError):
                self.conn.close()
                self.conn = None
                if attempt:
                    raise

    def ok(self, path, headers=None, what=None):
        status, hdrs, body = self.get(path, headers)
        require(status == 200, f"GET {path}: {status}, want 200: {body[:300]!r}")
        return hdrs, body

    def json(self, path):
        hdrs, body = self.ok(path)
        try:
            return json.loads(body)
        except ValueError as e:
            raise Failure(f"GET {path}: not JSON ({e}): {body[:200]!r}")


# --- Web Mercator tiles ------------------------------------------------------------------


def merc_bounds(z, x, y):
    """The XYZ tile's (xmin, ymin, xmax, ymax) in EPSG:3857, rows from the north."""
    s = 2 * HALF / 2 ** z
    return (-HALF + x * s, HALF - (y + 1) * s, -HALF + (x + 1) * s, HALF - y * s)


def merc_tile_of(lon, lat, z):
    n = 2 ** z
    x = (lon + 180.0) / 360.0 * n
    y = (1.0 - math.asinh(math.tan(math.radians(lat))) / math.pi) / 2.0 * n
    return min(max(int(x), 0), n - 1), min(max(int(y), 0), n - 1)


def cut_error(z, size):
    return 0.5 * EQUATOR / (size * 2 ** z)


def pixel_centres(bounds, n):
    """Longitudes and latitudes of an n × n tile's pixel centres, rows from the north."""
    xmin, ymin, xmax, ymax = bounds
    px = xmin + (np.arange(n) + 0.5) * (xmax - xmin) / n
    py = ymax - (np.arange(n) + 0.5) * (ymax - ymin) / n
    X, Y = np.meshgrid(px, py)
    return TO_LONLAT.transform(X, Y)


def decode_png(body, what):
    """Heights decoded both ways' raw channels: (rgba uint8 array)."""
    require(body[:8] == b"\x89PNG\r\n\x1a\n", f"{what}: not a PNG: {body[:16]!r}")
    img = Image.open(io.BytesIO(body))
    img.load()
    require(img.mode == "RGBA", f"{what}: PNG mode {img.mode}, want RGBA")
    return np.asarray(img, dtype=np.uint8)


def terrarium(rgba):
    r, g, b = (rgba[..., i].astype(np.float64) for i in range(3))
    return r * 256.0 + g + b / 256.0 - 32768.0


def mapbox(rgba):
    r, g, b = (rgba[..., i].astype(np.float64) for i in range(3))
    return -10000.0 + (r * 65536.0 + g * 256.0 + b) * 0.1


def stable(mask):
    """Where a boolean image equals all eight neighbours (the border counts as unstable)."""
    m = mask.astype(np.int8)
    p = np.pad(m, 1, mode="constant", constant_values=-1)
    out = np.ones(mask.shape, dtype=bool)
    n0, n1 = mask.shape
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            out &= p[dy:dy + n0, dx:dx + n1] == m
    return out


# --- The surveys, and GDAL's warps of them -------------------------------------------------


class Survey:
    """A crop's samples (NaN for nodata) and georeference, as GDAL reads it."""

    def __init__(self, path):
        self.path = path
        with rasterio.open(path) as ds:
            z = ds.read(1).astype(np.float64)
            if ds.nodata is not None:
                z[z == ds.nodata] = np.nan
            self.transform = ds.transform
            self.crs = ds.crs
        z[~np.isfinite(z)] = np.nan
        self.z = z
        self._windows = {}
        # Cell sizes in metres along each axis at the crop's middle latitude, and the steepest
        # slope along each axis (metres of height a metre) between neighbouring samples.
        lat = self.transform.f + self.transform.e * z.shape[0] / 2
        self.dx_m = abs(self.transform.a) * 111_320.0 * math.cos(math.radians(lat))
        self.dy_m = abs(self.transform.e) * 110_574.0
        self.slope_x = float(np.nanmax(np.abs(np.diff(z, axis=1)))) / self.dx_m
        self.slope_y = float(np.nanmax(np.abs(np.diff(z, axis=0)))) / self.dy_m

    def position(self, lon, lat):
        """Fractional sample coordinates (column, row) of points: sample (c, r) is the centre of
        GDAL's pixel (c, r)."""
        inv = ~self.transform
        px = inv.a * lon + inv.b * lat + inv.c
        py = inv.d * lon + inv.e * lat + inv.f
        return px - 0.5, py - 0.5

    def window(self, lon, lat, radius):
        """Over the samples within `radius` samples of each point along both axes (a superset
        square): (min, max, number valid, number of samples in the square)."""
        k = int(math.floor(2 * radius)) + 2
        if k not in self._windows:
            pad = k + 1
            zp = np.pad(self.z, pad, constant_values=np.nan)
            valid = ~np.isnan(zp)
            lo = np.where(valid, zp, np.inf)
            hi = np.where(valid, zp, -np.inf)

            def slide(a, op):
                a = op(sliding_window_view(a, k, axis=1), axis=-1)
                return op(sliding_window_view(a, k, axis=0), axis=-1)

            self._windows[k] = (pad, slide(lo, np.min), slide(hi, np.max), slide(valid.astype(np.int32), np.sum))
        pad, mn, mx, cnt = self._windows[k]
        c, r = self.position(lon, lat)
        c0 = np.clip(np.floor(c - radius).astype(np.int64) + pad, 0, mn.shape[1] - 1)
        r0 = np.clip(np.floor(r - radius).astype(np.int64) + pad, 0, mn.shape[0] - 1)
        return mn[r0, c0], mx[r0, c0], cnt[r0, c0], k * k

    def warp(self, bounds, n, point):
        """GDAL's bilinear warp onto the n × n EPSG:3857 grid over `bounds` (float64, NaN
        nodata). `point`: with XSCALE=YSCALE=1, so that GDAL evaluates the bilinear surface at
        each pixel centre even where it downsamples."""
        out = np.full((n, n), np.nan, dtype=np.float32)
        extra = {"XSCALE": 1, "YSCALE": 1} if point else {}
        with rasterio.open(self.path) as ds:
            reproject(
                source=rasterio.band(ds, 1),
                destination=out,
                dst_transform=from_bounds(*bounds, n, n),
                dst_crs="EPSG:3857",
                dst_nodata=np.nan,
                resampling=Resampling.bilinear,
                **extra,
            )
        return out.astype(np.float64)


def stats(d):
    d = np.abs(d)
    if d.size == 0:
        return 0.0, 0.0
    return float(d.max()), float(np.sqrt((d ** 2).mean()))


# --- PNG and GeoTIFF tiles ---------------------------------------------------------------


class PngResults:
    def __init__(self):
        self.rows = []
        self.tiles = 0


def png_path(z, x, y, encoding, size, error=None):
    q = f"encoding={encoding}&size={size}"
    if error is not None:
        q += f"&error={error:g}"
    return f"/tiles/{z}/{x}/{y}.png?{q}"


def fetch_png(h, z, x, y, encoding, size, error=None):
    path = png_path(z, x, y, encoding, size, error)
    hdrs, body = h.ok(path)
    require(hdrs.get("content-type", "").split(";")[0].strip() == "image/png",
            f"GET {path}: Content-Type {hdrs.get('content-type')!r}, want image/png")
    rgba = decode_png(body, f"GET {path}")
    require(rgba.shape == (size, size, 4), f"GET {path}: a {rgba.shape[1]}×{rgba.shape[0]} PNG, want {size}×{size}")
    a = rgba[..., 3]
    require(np.isin(a, (0, 255)).all(), f"GET {path}: alpha values {sorted(set(np.unique(a)) - {0, 255})[:5]} besides 0 and 255")
    return rgba, hdrs, body


def fetch_tif(h, z, x, y, size, error=None):
    path = f"/tiles/{z}/{x}/{y}.tif?size={size}" + (f"&error={error:g}" if error is not None else "")
    hdrs, body = h.ok(path)
    with MemoryFile(body) as mem, mem.open() as ds:
        require(ds.crs is not None and ds.crs.to_epsg() == 3857, f"GET {path}: CRS {ds.crs}, want EPSG:3857")
        require((ds.width, ds.height, ds.count) == (size, size, 1),
                f"GET {path}: {ds.width}×{ds.height}×{ds.count}, want {size}×{size}×1")
        require(ds.dtypes[0] == "float32", f"GET {path}: {ds.dtypes[0]}, want float32")
        require(ds.nodata == -9999, f"GET {path}: nodata {ds.nodata}, want -9999")
        want = from_bounds(*merc_bounds(z, x, y), size, size)
        got = ds.transform
        off = max(abs(a - b) for a, b in zip(tuple(got)[:6], tuple(want)[:6]))
        require(off < 1e-6 * max(1.0, abs(want.a)) + 1e-6 or off < 1e-3,
                f"GET {path}: transform {tuple(got)[:6]}, want the tile's {tuple(want)[:6]} (off by {off:.3g})")
        v = ds.read(1).astype(np.float64)
    return v, hdrs


def check_png_tile(h, cop, nas, z, x, y, n, res, grpc=None):
    b = merc_bounds(z, x, y)
    e = cut_error(z, n)
    lon, lat = pixel_centres(b, n)
    where = f"tile {z}/{x}/{y} at {n}"

    terr_rgba, _, _ = fetch_png(h, z, x, y, "terrarium", n)
    mapb_rgba, _, _ = fetch_png(h, z, x, y, "mapbox", n)
    zero_rgba, _, _ = fetch_png(h, z, x, y, "terrarium", n, error=0)
    alpha = terr_rgba[..., 3] == 255
    require(np.array_equal(mapb_rgba[..., 3] == 255, alpha),
            f"{where}: mapbox and terrarium alpha differ at {int(((mapb_rgba[..., 3] == 255) != alpha).sum())} pixels")
    alpha0 = zero_rgba[..., 3] == 255
    terr = np.where(alpha, terrarium(terr_rgba), np.nan)
    mapb = np.where(alpha, mapbox(mapb_rgba), np.nan)
    zero = np.where(zero_rgba[..., 3] == 255, terrarium(zero_rgba), np.nan)

    # The two encodings of one tile: the same heights, each within its step.
    d = np.abs(terr - mapb)[alpha]
    enc_max = float(d.max()) if d.size else 0.0
    require(enc_max <= MAPBOX_STEP + TERRARIUM_STEP + 1e-6,
            f"{where}: terrarium and mapbox decode {enc_max:.4f} m apart, more than 0.1 + 1/256 m")

    # GDAL's warps of each survey.
    pc, gc, pn = cop.warp(b, n, True), cop.warp(b, n, False), nas.warp(b, n, True)
    union = ~np.isnan(pc) | ~np.isnan(pn)
    st = stable(union)
    for name, a in (("", alpha), (" at error=0", alpha0)):
        bad = st & (a != union)
        require(not bad.any(), lambda:
                f"{where}{name}: alpha is {'255' if a[bad][0] else '0'} at {int(bad.sum())} pixels where GDAL's warp "
                f"{'is nodata' if a[bad][0] else 'has data'} (first at row, col {tuple(int(v) for v in np.argwhere(bad)[0])}), "
                f"away from the data's edge")
    edge_disagree = int((~st & (alpha != union)).sum())

    # Where only Copernicus has data: its samples around the point all valid, no NASADEM
    # sample within three.
    _, _, ccount, cfull = cop.window(lon, lat, 2)
    _, _, ncount, _ = nas.window(lon, lat, 3)
    _, _, nin, nfull = nas.window(lon, lat, 2)
    only = (ccount == cfull) & (ncount == 0) & alpha & ~np.isnan(pc)
    both = (ccount == cfull) & (nin == nfull) & alpha & ~np.isnan(pc) & ~np.isnan(pn)
    row = {"z": z, "x": x, "y": y, "size": n, "e": e, "only": int(only.sum()), "both": int(both.sum()),
           "enc_max": enc_max, "edge_disagree": edge_disagree}

    q = TERRARIUM_STEP + FLOAT_SLACK
    # e = 0: the survey's own bilinear surface.
    m0, r0 = stats((zero - pc)[only])
    require(m0 <= q, f"{where}: at error=0 the tile is {m0:.4f} m from Copernicus's bilinear surface "
                     f"(GDAL, XSCALE=YSCALE=1), more than the terrarium step; RMS {r0:.4f} m over {int(only.sum())} pixels")
    # At the zoom's error: within e of it.
    me, re_ = stats((terr - pc)[only])
    require(me <= e + q, f"{where}: the tile cut at e = {e:.3f} m is {me:.3f} m from Copernicus's bilinear surface")
    # Against GDAL's own bilinear warp, which averages over about a pixel's footprint where it
    # downsamples: e plus the relief of the samples under GDAL's kernel, whose radius is a
    # source sample or an output pixel, whichever is larger (taken 1.25 times as large, and as
    # a square, to hold every sample GDAL may weigh).
    c0, _ = cop.position(lon[:, :1], lat[:, :1])
    c1, _ = cop.position(lon[:, 1:2], lat[:, 1:2])
    _, r_a = cop.position(lon[:1, :], lat[:1, :])
    _, r_b = cop.position(lon[1:2, :], lat[1:2, :])
    scale = max(float(np.abs(c1 - c0).max()), float(np.abs(r_b - r_a).max()), 1.0)
    lo_k, hi_k, _, _ = cop.window(lon, lat, 1.25 * scale)
    relief = np.where(only, hi_k - lo_k, 0.0)
    dg = np.abs(terr - gc)
    excess = (dg - (e + q + relief))[only]
    mg, rg = stats((terr - gc)[only])
    require(excess.size == 0 or excess.max() <= 0,
            f"{where}: the tile is {mg:.3f} m from GDAL's bilinear warp, beyond e = {e:.3f} m plus the "
            f"relief under GDAL's kernel by {excess.max() if excess.size else 0:.3f} m")
    # Where both surveys have data: between their surfaces, widened by e (and at e = 0 by the
    # encoding's step alone: the cut is then the best survey's level 0 there).
    lo, hi = np.fmin(pc, pn), np.fmax(pc, pn)
    out_e = np.maximum(np.maximum(lo - terr, terr - hi), 0.0)[both]
    out_0 = np.maximum(np.maximum(lo - zero, zero - hi), 0.0)[both]
    mb, _ = stats(out_e)
    mb0, _ = stats(out_0)
    require(mb <= e + q, f"{where}: where both surveys have data the tile is {mb:.3f} m outside the range of "
                         f"their surfaces, more than e = {e:.3f} m")
    require(mb0 <= q, f"{where}: where both surveys have data the error=0 tile is {mb0:.4f} m outside the range "
                      f"of their surfaces")
    row.update({"e0_max": m0, "e0_rms": r0, "e_max": me, "e_rms": re_, "gdal_max": mg, "gdal_rms": rg,
                "relief_max": float(relief.max()) if only.any() else 0.0, "both_out": mb, "both_out0": mb0})

    # The GeoTIFF of the same tile: the PNG's heights before their encoding.
    tif, _ = fetch_tif(h, z, x, y, n)
    tif_valid = tif != -9999
    require((tif_valid == alpha).all(), f"{where}: the .tif has data at {int(tif_valid.sum())} pixels, the PNG at {int(alpha.sum())}")
    dt = np.abs(tif - terr)[alpha]
    tif_max = float(dt.max()) if dt.size else 0.0
    require(tif_max <= TERRARIUM_STEP + 1e-6, f"{where}: the .tif and the terrarium PNG differ by {tif_max:.5f} m")
    row["tif_max"] = tif_max
    if grpc is not None:
        g = grpc.tile(b, n, n, e, crs="EPSG:3857").astype(np.float64)
        require((~np.isnan(g) == tif_valid).all(), f"{where}: the gRPC tile's data mask differs from the .tif's")
        dg_ = np.abs(g - tif)[tif_valid]
        row["grpc_max"] = float(dg_.max()) if dg_.size else 0.0
        require(row["grpc_max"] <= 1e-3, f"{where}: the .tif is {row['grpc_max']:.4g} m from the gRPC tile of its ROI in EPSG:3857")
    res.rows.append(row)
    res.tiles += 1


def pick_tiles(z, extent, points):
    """Every tile over `extent` at z, or where there are more than four, the tiles holding
    `points` (each a place worth checking: one survey alone, both, the data's corner)."""
    w, s, e, n = extent
    x0, y0 = merc_tile_of(w, n, z)
    x1, y1 = merc_tile_of(e, s, z)
    every = [(x, y) for y in range(y0, y1 + 1) for x in range(x0, x1 + 1)]
    if len(every) <= 4:
        return every
    out = []
    for lon, lat in points:
        t = merc_tile_of(lon, lat, z)
        if t not in out:
            out.append(t)
    return out


# --- quantized-mesh ----------------------------------------------------------------------


def geo_bounds(level, x, y):
    """A TMS geographic tile's (west, south, east, north): 2·2^L × 2^L tiles of 180/2^L°."""
    s = 180.0 / 2 ** level
    return (-180.0 + x * s, -90.0 + y * s, -180.0 + (x + 1) * s, -90.0 + (y + 1) * s)


def geo_tile_of(lon, lat, level):
    s = 180.0 / 2 ** level
    return int((lon + 180.0) // s), int((lat + 90.0) // s)


def walk_quantized_mesh(body, what):
    """A byte walk of quantized-mesh-1.0, independent of the decoder: the counts, and the
    extensions as [(id, bytes)], requiring the body to end exactly where the last one does."""
    try:
        off = 88
        (n,) = struct.unpack_from("<I", body, off)
        off += 4 + 6 * n
        wide = n > 65536
        if wide and off % 4:
            off += 4 - off % 4
        isz = 4 if wide else 2
        (tris,) = struct.unpack_from("<I", body, off)
        off += 4 + 3 * tris * isz
        edges = []
        for _ in range(4):
            (k,) = struct.unpack_from("<I", body, off)
            edges.append(k)
            off += 4 + k * isz
        require(off <= len(body), f"{what}: the body ends inside the mesh ({len(body)} bytes, mesh needs {off})")
        exts = []
        while off < len(body):
            require(off + 5 <= len(body), f"{what}: {len(body) - off} stray bytes after the extensions")
            ext_id, length = struct.unpack_from("<BI", body, off)
            off += 5
            require(off + length <= len(body), f"{what}: extension {ext_id} of {length} bytes runs past the body")
            exts.append((ext_id, body[off:off + length]))
            off += length
    except struct.error as e:
        raise Failure(f"{what}: truncated quantized mesh ({e})")
    return {"vertices": n, "triangles": tris, "edges": edges, "extensions": exts, "wide": wide}


class Mesh:
    """A decoded terrain tile: vertex lon/lat/height, edges and extensions."""

    def __init__(self, level, x, y, body, what):
        self.level, self.x, self.y = level, x, y
        self.bounds = geo_bounds(level, x, y)
        walk = walk_quantized_mesh(body, what)
        self.walk = walk
        ids = [i for i, _ in walk["extensions"]]
        w, s, e, n = self.bounds
        t = TerrainTile(west=w, east=e, south=s, north=n)
        # The decoder reads normals then the water mask when told to, and skips (with a
        # warning) what follows: tell it what the walk found first.
        lighting = ids[:1] == [1]
        water = (ids[1:2] == [2]) if lighting else (ids[:1] == [2])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t.fromBytesIO(io.BytesIO(body), hasLighting=lighting, hasWatermask=water)
        self.tile = t
        require(len(t.u) == walk["vertices"], f"{what}: the decoder read {len(t.u)} vertices, the walk {walk['vertices']}")
        require(len(t.indices) == 3 * walk["triangles"], f"{what}: {len(t.indices)} indices for {walk['triangles']} triangles")
        self.u = np.array(t.u, dtype=np.int64)
        self.v = np.array(t.v, dtype=np.int64)
        self.hq = np.array(t.h, dtype=np.int64)
        require(walk["vertices"] > 0 and self.u.min() >= 0 and self.u.max() <= QM_MAX and self.v.min() >= 0
                and self.v.max() <= QM_MAX and self.hq.min() >= 0 and self.hq.max() <= QM_MAX,
                f"{what}: quantized vertex coordinates outside 0..32767")
        idx = np.array(t.indices, dtype=np.int64)
        require(walk["triangles"] > 0 and idx.min() >= 0 and idx.max() < walk["vertices"],
                f"{what}: indices from {idx.min()} to {idx.max()} for {walk['vertices']} vertices (high-water-mark codes "
                f"that do not decode)")
        self.triangles = idx.reshape(-1, 3)
        self.lon = w + self.u / QM_MAX * (e - w)
        self.lat = s + self.v / QM_MAX * (n - s)
        lo, hi = t.header["minimumHeight"], t.header["maximumHeight"]
        require(hi >= lo, f"{what}: maximumHeight {hi} below minimumHeight {lo}")
        self.hmin, self.hmax = lo, hi
        self.height = lo + self.hq / QM_MAX * (hi - lo)
        self.step = (hi - lo) / QM_MAX
        for name, ids_, coord, want in (("west", t.westI, self.u, 0), ("east", t.eastI, self.u, QM_MAX),
                                        ("south", t.southI, self.v, 0), ("north", t.northI, self.v, QM_MAX)):
            ii = np.array(ids_, dtype=np.int64)
            require(ii.size > 0, f"{what}: no {name} edge vertices")
            require((coord[ii] == want).all(), f"{what}: a {name} edge index names a vertex off the {name} edge")
            require(ii.size == int((coord == want).sum()),
                    f"{what}: {int((coord == want).sum())} vertices on the {name} edge, {ii.size} listed")
        self.west, self.east = np.array(t.westI), np.array(t.eastI)
        self.south, self.north = np.array(t.southI), np.array(t.northI)
        self.extensions = dict(walk["extensions"])
        require(len(self.extensions) == len(ids), f"{what}: an extension repeated: {ids}")
        self.normals = t.vLight if lighting else None


def check_extensions(mesh, what, want_ids):
    ids = sorted(mesh.extensions)
    require(ids == sorted(want_ids), f"{what}: extensions {ids}, want {sorted(want_ids)}")
    n = mesh.walk["vertices"]
    if 1 in want_ids:
        require(len(mesh.extensions[1]) == 2 * n, f"{what}: {len(mesh.extensions[1])} bytes of normals for {n} vertices")
        require(mesh.normals is not None and len(mesh.normals) == n, f"{what}: the decoder read no normals")
        nv = np.array(mesh.normals, dtype=np.float64)
        require(np.abs(np.linalg.norm(nv, axis=1) - 1).max() < 0.02, f"{what}: normals are not unit vectors")
        # Against the mesh's own normals in the earth-fixed frame (each vertex's triangles'
        # normals weighted by area): none may point into the ground, and most must agree
        # within the oct encoding's precision and the choice of weights.
        X, Y, Z = TO_ECEF.transform(mesh.lon, mesh.lat, mesh.height)
        p = np.stack([X, Y, Z], axis=1)
        tri = mesh.triangles
        face = np.cross(p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]])
        lon, lat = np.radians(mesh.lon), np.radians(mesh.lat)
        up = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=1)
        # Triangles of either winding: face normals turned to the sky.
        face *= np.sign((face * up[tri[:, 0]]).sum(axis=1))[:, None]
        acc = np.zeros_like(p)
        for k in range(3):
            np.add.at(acc, tri[:, k], face)
        ok = np.linalg.norm(acc, axis=1) > 0
        ref = acc[ok] / np.linalg.norm(acc[ok], axis=1)[:, None]
        angle = np.degrees(np.arccos(np.clip((ref * nv[ok]).sum(axis=1), -1, 1)))
        require((nv * up).sum(axis=1).min() > 0, f"{what}: a normal points into the ground")
        require(float(np.median(angle)) < 5, f"{what}: normals {np.median(angle):.1f}° (median) from the mesh's own")
        mesh.normal_angles = angle
    if 2 in want_ids:
        m = mesh.extensions[2]
        require(len(m) in (1, 256 * 256), f"{what}: a water mask of {len(m)} bytes, want 1 or 65536")
    if 4 in want_ids:
        m = mesh.extensions[4]
        require(len(m) >= 4, f"{what}: metadata of {len(m)} bytes")
        (k,) = struct.unpack_from("<I", m, 0)
        require(k == len(m) - 4, f"{what}: metadata jsonLength {k} for {len(m) - 4} bytes of JSON")
        try:
            meta = json.loads(m[4:].decode("utf-8"))
        except ValueError as e:
            raise Failure(f"{what}: metadata is not JSON ({e}): {m[4:100]!r}")
        require(isinstance(meta, dict), f"{what}: metadata {meta!r} is not an object")
        if "available" in meta:
            require(isinstance(meta["available"], list), f"{what}: metadata available is {meta['available']!r}")


def terrain_path(level, x, y, version=None):
    return f"/terrain/{level}/{x}/{y}.terrain" + (f"?v={urllib.parse.quote(str(version))}" if version is not None else "")


def fetch_terrain(h, level, x, y, version, accept=QM_ACCEPT, gz=True):
    """The tile's body as decoded once from gzip (or raw), after the transport checks."""
    path = terrain_path(level, x, y, version)
    headers = {"Accept": accept, "Accept-Encoding": "gzip" if gz else "identity"}
    hdrs, body = h.ok(path, headers)
    ct = hdrs.get("content-type", "")
    require(ct.split(";")[0].strip() == "application/vnd.quantized-mesh",
            f"GET {path}: Content-Type {ct!r}, want application/vnd.quantized-mesh")
    ce = hdrs.get("content-encoding", "identity").strip().lower()
    if gz:
        require(ce == "gzip", f"GET {path} with Accept-Encoding: gzip: Content-Encoding {ce!r}, want gzip")
        require(body[:2] == b"\x1f\x8b", f"GET {path}: Content-Encoding gzip but the body starts {body[:4]!r}")
        try:
            raw = gzip.decompress(body)
        except OSError as e:
            raise Failure(f"GET {path}: the gzip body does not decompress: {e}")
        require(raw[:2] != b"\x1f\x8b", f"GET {path}: the body is gzipped twice")
    else:
        require(ce in ("", "identity"), f"GET {path} without gzip in Accept-Encoding: Content-Encoding {ce!r}")
        require(body[:2] != b"\x1f\x8b", f"GET {path} without gzip in Accept-Encoding: the body is gzipped")
        raw = body
    return raw, hdrs, len(body)


def heights_at(h, lon, lat, error, crs=None):
    """/heights at points, in batches short enough for any URL: float64, NaN for null."""
    out = np.full(len(lon), np.nan)
    for i in range(0, len(lon), 200):
        pts = ",".join(f"{a!r},{b!r}" for a, b in zip(lon[i:i + 200].tolist(), lat[i:i + 200].tolist()))
        path = f"/heights?points={pts}&error={error!r}" + (f"&crs={crs}" if crs else "")
        r = h.json(path)
        hs = r.get("heights")
        require(isinstance(hs, list) and len(hs) == len(lon[i:i + 200]),
                f"GET /heights: {len(hs) if isinstance(hs, list) else hs!r} heights for {len(lon[i:i + 200])} points")
        out[i:i + len(hs)] = [np.nan if v is None else float(v) for v in hs]
    return out


def check_mesh_heights(h, mesh, slope, what):
    """Vertex heights against /heights at the cut's error G/2 (the mesh's vertices are the cut's
    heights at grid points: within a height step, plus the slope over a quantization step of
    position, since an encoder may round or truncate) and at error 0 (within G(L))."""
    G = G0 / 2 ** mesh.level
    w, s, e, n = mesh.bounds
    du = (e - w) / QM_MAX * 111_320.0 * math.cos(math.radians((s + n) / 2))
    dv = (n - s) / QM_MAX * 110_574.0
    pos = slope[0] * du + slope[1] * dv
    cut = heights_at(h, mesh.lon, mesh.lat, G / 2)
    exact = heights_at(h, mesh.lon, mesh.lat, 0.0)
    have = ~np.isnan(cut)
    require((~np.isnan(exact) == have).all(), f"{what}: /heights has data at different vertices at error 0 and G/2")
    d_cut = np.abs(mesh.height - cut)[have]
    d_exact = np.abs(mesh.height - exact)[have]
    m_cut = float(d_cut.max()) if d_cut.size else 0.0
    m_exact = float(d_exact.max()) if d_exact.size else 0.0
    require(m_cut <= mesh.step + pos + FLOAT_SLACK,
            f"{what}: a vertex is {m_cut:.3f} m from /heights at the cut's error G/2 = {G / 2:.3f} m "
            f"(height step {mesh.step:.4f} m, position slack {pos:.4f} m)")
    require(m_exact <= G + mesh.step + pos + FLOAT_SLACK,
            f"{what}: a vertex is {m_exact:.3f} m from /heights at error 0, more than G(L) = {G:.3f} m")
    return {"vertices": int(mesh.walk["vertices"]), "with_data": int(have.sum()), "cut_max": m_cut,
            "exact_max": m_exact, "exact_rms": float(np.sqrt((d_exact ** 2).mean())) if d_exact.size else 0.0, "G": G}


def check_shared_edge(a, b, axis, what):
    """a's east (axis "x") or north (axis "y") edge against b's west or south edge: the same
    positions along it, heights within one height step of either tile."""
    if axis == "x":
        ia, ib, along_a, along_b = a.east, b.west, a.v, b.v
    else:
        ia, ib, along_a, along_b = a.north, b.south, a.u, b.u
    pa, pb = along_a[ia], along_b[ib]
    require(sorted(pa.tolist()) == sorted(pb.tolist()),
            f"{what}: the shared edge has {len(pa)} vertices on one side and {len(pb)} on the other, "
            f"{len(set(pa.tolist()) ^ set(pb.tolist()))} positions not on both")
    ha = dict(zip(pa.tolist(), a.height[ia].tolist()))
    hb = dict(zip(pb.tolist(), b.height[ib].tolist()))
    step = max(a.step, b.step)
    worst = max(abs(ha[k] - hb[k]) for k in ha)
    require(worst <= step + 1e-6,
            f"{what}: heights along the shared edge differ by {worst:.4f} m, more than a height step ({step:.4f} m)")
    return len(pa), worst


# --- the checks ----------------------------------------------------------------------------


def check_documents(h):
    geo = h.json("/surveys.geojson")
    require(geo.get("type") == "FeatureCollection", f"/surveys.geojson: type {geo.get('type')!r}")
    feats = geo.get("features", [])
    require(len(feats) == 2, f"/surveys.geojson: {len(feats)} features, want the 2 surveys")
    xs, ys = [], []
    for f in feats:
        g = f.get("geometry", {})
        require(g.get("type") == "Polygon", f"/surveys.geojson: a {g.get('type')!r} footprint, want Polygon")
        # The file's name and what its sidecar says, but no path: where the daemon's inbox is
        # is the Admin listing's to tell.
        props = f.get("properties", {})
        want = {"id", "accuracy_m", "file", "title", "license", "attribution", "acquired"}
        require(set(props) == want,
                f"/surveys.geojson: properties {sorted(props)}, want {sorted(want)}")
        require(props["file"].endswith(".tif") and "/" not in props["file"],
                f"/surveys.geojson: file {props['file']!r}, want a file name")
        ring = np.array(g["coordinates"][0], dtype=np.float64)
        xs += ring[:, 0].tolist()
        ys += ring[:, 1].tolist()
    extent = (min(xs), min(ys), max(xs), max(ys))
    cop, nas = rasterio.open(COPERNICUS), rasterio.open(NASADEM)
    want = (min(cop.bounds.left, nas.bounds.left), min(cop.bounds.bottom, nas.bounds.bottom),
            max(cop.bounds.right, nas.bounds.right), max(cop.bounds.top, nas.bounds.top))
    cop.close()
    nas.close()
    off = max(abs(a - b) for a, b in zip(extent, want))
    require(off < 1e-9, f"/surveys.geojson: footprints span {extent}, the crops' pixels {want}")

    for enc, size in (("terrarium", 256), ("mapbox", 512)):
        tj = h.json(f"/tiles.json?encoding={enc}&size={size}")
        for k in ("tiles", "minzoom", "maxzoom", "bounds", "center"):
            require(k in tj, f"/tiles.json: no {k!r}")
        require(str(tj.get("tilejson", "")).startswith("3."), f"/tiles.json: tilejson {tj.get('tilejson')!r}, want 3.0.0")
        require(tj.get("tileSize") == size and tj.get("encoding") == enc,
                f"/tiles.json?encoding={enc}&size={size}: tileSize {tj.get('tileSize')}, encoding {tj.get('encoding')!r}")
        url = tj["tiles"][0]
        require(url.startswith("http://") and "{z}/{x}/{y}" in url and f"encoding={enc}" in url and f"size={size}" in url,
                f"/tiles.json: tile URL {url!r}")
        bw, bs, be, bn = tj["bounds"]
        require(bw <= extent[0] + 1e-3 and bs <= extent[1] + 1e-3 and be >= extent[2] - 1e-3 and bn >= extent[3] - 1e-3,
                f"/tiles.json: bounds {tj['bounds']} do not hold the surveys {extent}")
        # The template, filled in, gives the same tile as the path.
        z = 12
        x, y = merc_tile_of((extent[0] + extent[2]) / 2, (extent[1] + extent[3]) / 2, z)
        u = urllib.parse.urlsplit(url.replace("{z}", str(z)).replace("{x}", str(x)).replace("{y}", str(y)))
        _, body = h.ok(u.path + ("?" + u.query if u.query else ""))
        _, direct = h.ok(png_path(z, x, y, enc, size))
        require(np.array_equal(decode_png(body, url), decode_png(direct, "tile")),
                "/tiles.json: the template's tile differs from the tile's path")

    hdrs, body = h.ok("/")
    require(hdrs.get("content-type", "").startswith("text/html") and b"<html" in body.lower(),
            f"GET /: {len(body)} bytes of {hdrs.get('content-type')!r} ({body[:60]!r}), want the viewer's HTML page")

    layer = h.json("/terrain/layer.json")
    for k, want_v in (("format", "quantized-mesh-1.0"), ("scheme", "tms"), ("projection", "EPSG:4326")):
        require(layer.get(k) == want_v, f"/terrain/layer.json: {k} {layer.get(k)!r}, want {want_v!r}")
    require(set(layer.get("extensions", [])) == {"octvertexnormals", "watermask", "metadata"},
            f"/terrain/layer.json: extensions {layer.get('extensions')}")
    tiles = layer.get("tiles", [])
    require(tiles and "{z}/{x}/{y}.terrain" in tiles[0] and "{version}" in tiles[0],
            f"/terrain/layer.json: tiles {tiles}")
    avail = layer.get("available", [])
    require(len(avail) >= 1 and len(avail[0]) >= 1, f"/terrain/layer.json: available {avail[:2]}")
    return extent, layer


def tile_available(layer, level, x, y):
    av = layer.get("available", [])
    if level >= len(av):
        return False
    return any(r["startX"] <= x <= r["endX"] and r["startY"] <= y <= r["endY"] for r in av[level])


def check_png(h, cop, nas, extent, grpc):
    res = PngResults()
    w, s, e, n = extent
    # Places worth a tile each: Copernicus alone, both surveys, NASADEM alone, and the data's
    # north-west corner, where its edge runs through the tile.
    points = [(-118.985, 34.53), (-118.94, 34.49), (-118.895, 34.445), (w + 0.002, n - 0.002)]
    for z in range(10, 15):
        for size in (256, 512):
            for x, y in pick_tiles(z, extent, points):
                check_png_tile(h, cop, nas, z, x, y, size, res, grpc)
    rows = res.rows
    say(f"png: {res.tiles} tiles (zooms 10-14, 256 and 512, terrarium, mapbox, error=0 and .tif each) "
        f"against GDAL's bilinear warp of the crops:")
    say("  zoom size   e(z) m | Copernicus alone, px | e=0 max/RMS m | at e max/RMS m | GDAL's warp max/RMS m "
        "(relief under its kernel, max) | both surveys: outside range, m (e / 0)")
    for z in range(10, 15):
        for size in (256, 512):
            sub = [r for r in rows if r["z"] == z and r["size"] == size]
            if not sub:
                continue
            only = sum(r["only"] for r in sub)

            def agg(k, rms=None):
                m = max(r[k] for r in sub)
                if rms is None:
                    return m
                tot = sum(r["only"] for r in sub)
                rr = math.sqrt(sum(r[rms] ** 2 * r["only"] for r in sub) / tot) if tot else 0.0
                return m, rr

            m0, r0 = agg("e0_max", "e0_rms")
            me, re_ = agg("e_max", "e_rms")
            mg, rg = agg("gdal_max", "gdal_rms")
            say(f"  {z:>4} {size:>4} {sub[0]['e']:>7.3f} | {only:>20} | {m0:.4f} / {r0:.4f} | {me:7.3f} / {re_:6.3f} | "
                f"{mg:7.3f} / {rg:6.3f} ({agg('relief_max'):7.2f}) | {agg('both_out'):.3f} / {agg('both_out0'):.4f}")
    say(f"  terrarium vs mapbox: at most {max(r['enc_max'] for r in rows):.4f} m apart; .tif vs terrarium at most "
        f"{max(r['tif_max'] for r in rows):.5f} m" +
        (f"; .tif vs gRPC tile at most {max(r['grpc_max'] for r in rows):.3g} m" if grpc is not None else ""))
    say(f"  alpha = 0 exactly where GDAL's warps are nodata, away from the data's edge; at its edge "
        f"{sum(r['edge_disagree'] for r in rows)} pixels differ, over {res.tiles} tiles")
    return res


def check_terrain(h, layer, extent, slope):
    version = layer.get("version")
    w, s, e, n = extent
    cx, cy = (w + e) / 2, (s + n) / 2
    meshes = {}
    height_rows = []
    total_bytes = raw_bytes = 0
    # Levels up to layer.json's maxzoom, the deepest Cesium asks for.
    top = int(layer.get("maxzoom", 14))
    levels = sorted({min(8, top), min(10, top), max(top - 1, 0), top})
    for level in levels:
        x0, y0 = geo_tile_of(w, s, level)
        x1, y1 = geo_tile_of(e, n, level)
        mx, my = geo_tile_of(cx, cy, level)
        xs = range(max(x0, mx - 1), min(x1, mx + 1) + 1)
        ys = range(max(y0, my - 1), min(y1, my + 1) + 1)
        for y in ys:
            for x in xs:
                what = f"terrain {level}/{x}/{y}"
                if not tile_available(layer, level, x, y):
                    # In the data's bounding box but over neither survey: Cesium upsamples
                    # its parent there and never asks for it.
                    continue
                raw, hdrs, nbytes = fetch_terrain(h, level, x, y, version)
                raw2, _, _ = fetch_terrain(h, level, x, y, version, gz=False)
                require(raw2 == raw, f"{what}: the raw body ({len(raw2)} bytes) is not the gzip body decompressed ({len(raw)} bytes)")
                total_bytes += nbytes
                raw_bytes += len(raw)
                m = Mesh(level, x, y, raw, what)
                check_extensions(m, what, [1, 2, 4])
                height_rows.append(check_mesh_heights(h, m, slope, what))
                meshes[(level, x, y)] = m
    # Extensions as asked: none, and normals alone.
    level, x, y = next(iter(meshes))
    raw, _, _ = fetch_terrain(h, level, x, y, version, accept="application/vnd.quantized-mesh")
    check_extensions(Mesh(level, x, y, raw, "terrain without extensions"), "terrain without extensions", [])
    raw, _, _ = fetch_terrain(h, level, x, y, version, accept="application/vnd.quantized-mesh;extensions=octvertexnormals")
    check_extensions(Mesh(level, x, y, raw, "terrain with normals"), "terrain with normals", [1])

    # Neighbours share their edges.
    pairs = 0
    worst = 0.0
    for (level, x, y), a in meshes.items():
        for axis, key in (("x", (level, x + 1, y)), ("y", (level, x, y + 1))):
            if key in meshes:
                _, d = check_shared_edge(a, meshes[key], axis, f"terrain {level}/{x}/{y} and {key[0]}/{key[1]}/{key[2]}")
                pairs += 1
                worst = max(worst, d)
    require(pairs >= 8, f"terrain: only {pairs} neighbouring pairs checked")

    # A root tile away from the data: flat, and all water.
    x_far = 1 if geo_tile_of(cx, cy, 0)[0] == 0 else 0
    raw, _, _ = fetch_terrain(h, 0, x_far, 0, version)
    far = Mesh(0, x_far, 0, raw, f"terrain 0/{x_far}/0")
    check_extensions(far, f"terrain 0/{x_far}/0", [1, 2, 4])
    require(far.hmax == far.hmin or np.ptp(far.height) == 0, f"terrain 0/{x_far}/0 (no data): heights {far.hmin}..{far.hmax}, want flat")
    require(far.extensions[2] in (b"\xff", b"\xff" * 65536), "terrain 0/{x_far}/0 (no data): the water mask is not all water")

    say(f"terrain: {len(meshes)} quantized-mesh tiles at levels {', '.join(map(str, levels))}, gzip once ({total_bytes} bytes, "
        f"{raw_bytes} raw), the same body raw; extensions 1, 2, 4 as asked; {pairs} shared edges, heights at "
        f"most {worst:.4f} m apart:")
    say("  level    G(L) m | vertices (with data) | vs /heights at G/2 max m | vs /heights at 0 max/RMS m")
    for level in levels:
        sub = [r for r, k in zip(height_rows, meshes) if k[0] == level]
        if sub:
            vt, wd = sum(r["vertices"] for r in sub), sum(r["with_data"] for r in sub)
            rms = math.sqrt(sum(r["exact_rms"] ** 2 * r["with_data"] for r in sub) / max(wd, 1))
            say(f"  {level:>5} {sub[0]['G']:>9.3f} | {vt:>9} ({wd:>8}) | {max(r['cut_max'] for r in sub):24.4f} | "
                f"{max(r['exact_max'] for r in sub):.3f} / {rms:.3f}")
    return meshes


def check_caching(h, extent, version):
    z = 13
    x, y = merc_tile_of((extent[0] + extent[2]) / 2, (extent[1] + extent[3]) / 2, z)
    etags = {}
    for enc, size, err in (("terrarium", 256, None), ("mapbox", 256, None), ("terrarium", 512, None), ("terrarium", 256, 0)):
        path = png_path(z, x, y, enc, size, err)
        h1, _ = h.ok(path)
        h2, _ = h.ok(path)
        tag = h1.get("etag")
        require(tag, f"GET {path}: no ETag")
        require(h1.get("cache-control"), f"GET {path}: no Cache-Control")
        require(h2.get("etag") == tag, f"GET {path} twice: ETags {tag!r} and {h2.get('etag')!r}")
        status, hdrs, body = h.get(path, {"If-None-Match": tag})
        require(status == 304, f"GET {path} with If-None-Match: {tag}: {status}, want 304")
        require(body == b"", f"GET {path} with If-None-Match: a 304 with {len(body)} bytes of body")
        status, _, _ = h.get(path, {"If-None-Match": '"not-this-one"'})
        require(status == 200, f"GET {path} with a stale If-None-Match: {status}, want 200")
        etags[(enc, size, err)] = tag
    require(len(set(etags.values())) == len(etags), f"PNG tiles of different encoding, size or error share an ETag: {etags}")
    for path, headers in ((f"/tiles/{z}/{x}/{y}.tif?size=256", {}),
                          (terrain_path(12, *geo_tile_of((extent[0] + extent[2]) / 2, (extent[1] + extent[3]) / 2, 12), version),
                           {"Accept": QM_ACCEPT, "Accept-Encoding": "gzip"})):
        hd, _ = h.ok(path, headers)
        tag = hd.get("etag")
        require(tag, f"GET {path}: no ETag")
        status, _, body = h.get(path, dict(headers, **{"If-None-Match": tag}))
        require(status == 304 and body == b"", f"GET {path} with If-None-Match: {status}, {len(body)} bytes; want 304, none")
    status, hdrs, _ = h.get(png_path(z, x, y, "terrarium", 256), {"Origin": "http://example.org"})
    require(hdrs.get("access-control-allow-origin") in ("*", "http://example.org"),
            f"a tile asked from another origin: Access-Control-Allow-Origin {hdrs.get('access-control-allow-origin')!r}")
    say(f"caching: one ETag a tile and variant, 304 with no body on If-None-Match (PNG, .tif, .terrain), "
        f"{len(etags)} variants with {len(set(etags.values()))} ETags; CORS open")


def check_errors(h):
    bad = [
        "/tiles/3/8/0.png?encoding=terrarium&size=256",
        "/tiles/3/0/8.png?encoding=terrarium&size=256",
        "/tiles/25/0/0.png?encoding=terrarium&size=256",
        "/tiles/0/1/0.png?encoding=mapbox&size=512",
        "/tiles/3/8/0.tif?size=256",
        "/terrain/3/16/0.terrain",
        "/terrain/3/0/8.terrain",
        "/terrain/25/0/0.terrain",
    ]
    for path in bad:
        status, _, body = h.get(path, {"Accept": QM_ACCEPT})
        require(status == 400, f"GET {path}: {status}, want 400 ({body[:120]!r})")
    for path in ("/tiles/12/0/0.png?encoding=bogus&size=256", "/tiles/12/0/0.png?encoding=terrarium&size=300"):
        status, _, body = h.get(path)
        require(400 <= status < 500, f"GET {path}: {status}, want a 4xx ({body[:120]!r})")
    status, _, _ = h.get("/terrain/3/15/7.terrain", {"Accept": QM_ACCEPT})
    require(status == 200, f"GET /terrain/3/15/7.terrain (the last tile of level 3): {status}, want 200")
    # Far from the data: a transparent tile of the size asked.
    for size in (256, 512):
        for enc in ("terrarium", "mapbox"):
            rgba, _, _ = fetch_png(h, 10, 0, 0, enc, size)
            require((rgba[..., 3] == 0).all(), f"tile 10/0/0 ({enc}, {size}), far from the data: {int((rgba[..., 3] != 0).sum())} opaque pixels")
    v, _ = fetch_tif(h, 10, 0, 0, 256)
    require((v == -9999).all(), "tile 10/0/0.tif, far from the data: not all nodata")
    say(f"errors: {len(bad)} tiles out of range give 400, bad encoding and size a 4xx; far from the data, "
        f"transparent PNGs of 256 and 512 and an all-nodata .tif")


def check_heights_grpc(h, grpc, extent):
    w, s, e, n = extent
    rng = np.random.default_rng(7)
    lon = rng.uniform(w - 0.01, e + 0.01, 300)
    lat = rng.uniform(s - 0.01, n + 0.01, 300)
    for err in (0.0, 5.0):
        web = heights_at(h, lon, lat, err)
        rpc = grpc.sample(np.stack([lon, lat], axis=1), err, crs="EPSG:4326").astype(np.float64)
        require((np.isnan(web) == np.isnan(rpc)).all(), f"/heights and gRPC SampleHeights differ in which points have data (error {err})")
        d = np.abs(web - rpc)[~np.isnan(web)]
        require(d.size == 0 or d.max() <= 1e-3, f"/heights is {d.max():.4g} m from gRPC SampleHeights (error {err})")
    say("heights: /heights equals gRPC SampleHeights at 300 points, at errors 0 and 5")


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--http", required=True, help="the daemon's HTTP base URL, http://127.0.0.1:PORT")
    ap.add_argument("--grpc", help="its gRPC address, host:port (to compare tiles and heights with)")
    ap.add_argument("--token", help="a read token, where the daemon has one")
    args = ap.parse_args(argv[1:])
    h = Http(args.http, args.token)
    grpc = None
    try:
        if args.grpc:
            from patchwork_client import Client

            grpc = Client(args.grpc, token=args.token)
        cop, nas = Survey(COPERNICUS), Survey(NASADEM)
        slope = (max(cop.slope_x, nas.slope_x), max(cop.slope_y, nas.slope_y))
        extent, layer = check_documents(h)
        say(f"documents: /surveys.geojson has the 2 footprints over {tuple(round(v, 4) for v in extent)}; "
            f"/tiles.json, /terrain/layer.json and the viewer page as specified")
        check_errors(h)
        check_caching(h, extent, layer.get("version"))
        check_png(h, cop, nas, extent, grpc)
        check_terrain(h, layer, extent, slope)
        if grpc is not None:
            check_heights_grpc(h, grpc, extent)
    except Failure as e:
        print(f"FAIL: {e}", file=sys.stderr)
        return 1
    except (OSError, http.client.HTTPException) as e:
        print(f"FAIL: cannot talk to the daemon at {args.http}: {e}", file=sys.stderr)
        return 1
    say(f"ok: the daemon's web tiles read back with Pillow, rasterio and quantized-mesh-tile as specified "
        f"({h.requests} requests)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
