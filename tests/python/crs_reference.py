"""What GDAL and PROJ answer, for tests/crs.rs to hold the daemon to.

    crs_reference.py warp SRC DST_CRS XMIN YMIN XMAX YMAX WIDTH HEIGHT OUT
        GDAL's bilinear warp of SRC's first band onto the north-up WIDTH x HEIGHT grid over
        the rectangle of DST_CRS, with the exact transformer (gdalwarp -r bilinear -et 0).
        Where the grid is coarser than SRC, GDAL's bilinear averages over the destination
        pixel rather than sampling at its centre; callers ask for finer grids:
        OUT gets WIDTH * HEIGHT little-endian f32 heights, NaN where GDAL gives nodata, then
        as many bytes, 1 where the point falls in a cell of SRC whose four corners are data
        (where GDAL's bilinear is the plain bilinear surface, without its re-weighting near
        voids and borders), by PROJ's transformation of the point into SRC's CRS.
    crs_reference.py transform IN OUT
        PROJ's transformation of points: IN is JSON [{"from", "to", "points": [[x, y]...]}],
        OUT the same with "out": [[x, y]...] (null where PROJ has none), coordinates in x/y
        (easting or longitude first) order.
    crs_reference.py deviation A B OUT
        How far two surveys of any CRSs disagree: each valid sample of A, at its pixel's
        centre carried into B's CRS by PROJ, against B's bilinear surface there (where the
        cell's four corners are data); and B's samples against A the same way. OUT gets JSON
        {"a_in_b": {"max_m", "rms_m", "samples"}, "b_in_a": {...}}.
"""

import json
import sys

import numpy as np
import pyproj
import rasterio
from rasterio.transform import from_bounds
from rasterio.vrt import WarpedVRT
from rasterio.warp import Resampling


def warp(src, dst_crs, xmin, ymin, xmax, ymax, width, height, out):
    width, height = int(width), int(height)
    xmin, ymin, xmax, ymax = map(float, (xmin, ymin, xmax, ymax))
    dst_transform = from_bounds(xmin, ymin, xmax, ymax, width, height)
    with rasterio.open(src) as d:
        band = d.read(1).astype(np.float64)
        if d.nodata is not None:
            band[band == d.nodata] = np.nan
        transform, crs = d.transform, d.crs
        # A warped VRT, whose transformer takes the tolerance: 1e-9 of a pixel is the exact
        # transformer to rounding (rasterio's reproject() leaves its own at 0.125 pixel,
        # whatever it is given, which moves points by up to a few tenths of a metre).
        with WarpedVRT(d, crs=dst_crs, transform=dst_transform, width=width, height=height,
                       resampling=Resampling.bilinear, tolerance=1e-9, dtype="float64",
                       src_nodata=d.nodata, nodata=np.nan) as vrt:
            dst = vrt.read(1)
    # Where the point's cell of SRC has four valid corners.
    xs = xmin + (np.arange(width) + 0.5) * (xmax - xmin) / width
    ys = ymax - (np.arange(height) + 0.5) * (ymax - ymin) / height
    X, Y = np.meshgrid(xs, ys)
    t = pyproj.Transformer.from_crs(pyproj.CRS(dst_crs), crs, always_xy=True)
    sx, sy = t.transform(X, Y)
    col, row = ~transform * (sx, sy)
    # Pixel centres sit at half-integers of the pixel-corner transform.
    gc, gr = col - 0.5, row - 0.5
    c0, r0 = np.floor(gc).astype(np.int64), np.floor(gr).astype(np.int64)
    rows, cols = band.shape
    inside = (c0 >= 0) & (r0 >= 0) & (c0 + 1 < cols) & (r0 + 1 < rows)
    c0c, r0c = np.clip(c0, 0, cols - 2), np.clip(r0, 0, rows - 2)
    ok = np.isfinite(band)
    whole = ok[r0c, c0c] & ok[r0c, c0c + 1] & ok[r0c + 1, c0c] & ok[r0c + 1, c0c + 1]
    mask = (inside & whole).astype(np.uint8)
    with open(out, "wb") as f:
        f.write(dst.astype("<f4").tobytes())
        f.write(mask.tobytes())


def transform(inp, out):
    with open(inp) as f:
        cases = json.load(f)
    for c in cases:
        t = pyproj.Transformer.from_crs(pyproj.CRS(c["from"]), pyproj.CRS(c["to"]), always_xy=True)
        pts = np.asarray(c["points"], dtype=np.float64).reshape(-1, 2)
        x, y = t.transform(pts[:, 0], pts[:, 1])
        c["out"] = [[a, b] if np.isfinite(a) and np.isfinite(b) else None for a, b in zip(x, y)]
        c["operation"] = t.description
    with open(out, "w") as f:
        json.dump(cases, f)


def _read(path):
    with rasterio.open(path) as d:
        band = d.read(1).astype(np.float64)
        if d.nodata is not None:
            band[band == d.nodata] = np.nan
        return band, d.transform, d.crs


def _against(a, b):
    """A's samples against B's bilinear surface: the largest and RMS difference, and count."""
    band, transform, crs = a
    other, o_transform, o_crs = b
    rows, cols = band.shape
    c, r = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
    x, y = transform * (c, r)
    bx, by = pyproj.Transformer.from_crs(crs, o_crs, always_xy=True).transform(x, y)
    col, row = ~o_transform * (bx, by)
    gc, gr = col - 0.5, row - 0.5
    c0, r0 = np.floor(gc).astype(np.int64), np.floor(gr).astype(np.int64)
    o_rows, o_cols = other.shape
    inside = (c0 >= 0) & (r0 >= 0) & (c0 + 1 < o_cols) & (r0 + 1 < o_rows)
    c0, r0 = np.clip(c0, 0, o_cols - 2), np.clip(r0, 0, o_rows - 2)
    fx, fy = gc - c0, gr - r0
    z00, z10 = other[r0, c0], other[r0, c0 + 1]
    z01, z11 = other[r0 + 1, c0], other[r0 + 1, c0 + 1]
    top = z00 + (z10 - z00) * fx
    bottom = z01 + (z11 - z01) * fx
    d = np.abs(top + (bottom - top) * fy - band)
    ok = inside & np.isfinite(d)
    d = d[ok]
    return {"max_m": float(d.max()), "rms_m": float(np.sqrt(np.mean(d * d))), "samples": int(d.size)}


def deviation(a, b, out):
    a, b = _read(a), _read(b)
    with open(out, "w") as f:
        json.dump({"a_in_b": _against(a, b), "b_in_a": _against(b, a)}, f)


if __name__ == "__main__":
    {"warp": warp, "transform": transform, "deviation": deviation}[sys.argv[1]](*sys.argv[2:])
