"""GDAL on the same tiles as Patchwork: time, difference, and both against the point reference.

Usage: python3 bench/gdal_compare.py MANIFEST.json OUT.csv

For every tile `patchwork-bench` wrote, GDAL (through rasterio, which bundles it) warps the same
source files onto the same north-up grid with bilinear resampling, the way `gdal.Warp` or a VRT
mosaic does: sources are drawn in order and each overwrites the last where it has data, so in an
overlap the last source wins. Patchwork instead blends every patch that meets the requested
error there (Formula 1), so an overlap gets a weighted mean of the surveys.

Both are compared with the same point reference: at each sample, the range of heights the
surveys' own bilinear surfaces give there (one value where one survey has data). A Patchwork
tile is bounded by the requested error against it. GDAL's bilinear warp, when it downsamples,
averages over the output pixel's footprint instead of evaluating at the point, so its error is
bounded by the terrain's relief within a pixel, not by any requested figure.
"""

import csv
import json
import sys
import time
from pathlib import Path

import numpy as np
import rasterio
from rasterio.transform import from_bounds
from rasterio.warp import Resampling, reproject


def load(path):
    return np.load(path).astype(np.float64)


def warp(datasets, crs, roi, n):
    """Open datasets warped bilinearly onto an n × n north-up grid over roi, as float32."""
    xmin, ymin, xmax, ymax = roi
    dst = np.full((n, n), np.nan, dtype=np.float32)
    transform = from_bounds(xmin, ymin, xmax, ymax, n, n)
    for src in datasets:
        part = np.full((n, n), np.nan, dtype=np.float32)
        reproject(
            source=rasterio.band(src, 1),
            destination=part,
            src_nodata=src.nodata,
            dst_transform=transform,
            dst_crs=crs,
            dst_nodata=np.nan,
            resampling=Resampling.bilinear,
        )
        # Later sources win where they have data, as in a VRT or gdal.Warp mosaic.
        dst = np.where(np.isnan(part), dst, part)
    return dst


def gdal_tile(sources, crs, roi, n):
    datasets = [rasterio.open(p) for p in sources]
    try:
        return warp(datasets, crs, roi, n).astype(np.float64)
    finally:
        for d in datasets:
            d.close()


def outside(h, lo, hi):
    ok = ~np.isnan(h) & ~np.isnan(lo)
    d = np.maximum(np.maximum(lo - h, h - hi), 0.0)
    return d[ok]


def main():
    manifest_path, out_path = Path(sys.argv[1]), Path(sys.argv[2])
    m = json.loads(manifest_path.read_text())
    tiles_dir = manifest_path.parent
    rows = []
    for t in m["tiles"]:
        n, e = t["size"], t["error"]
        ours = load(tiles_dir / t["ours"])
        lo, hi = load(tiles_dir / t["lo"]), load(tiles_dir / t["hi"])
        # A tile names its own CRS and sources where they are not the manifest's.
        crs, sources = t.get("crs", m["crs"]), t.get("sources", m["sources"])
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            g = gdal_tile(sources, crs, t["roi"], n)
            times.append((time.perf_counter() - t0) * 1e3)
        gdal_ms = sorted(times)[1]
        both = ~np.isnan(ours) & ~np.isnan(g)
        diff = np.abs(ours - g)[both]
        eo, eg = outside(ours, lo, hi), outside(g, lo, hi)
        row = {
            "crs": crs,
            "size": n,
            "error_m": e,
            "ours_ms": round(t["ours_ms"], 3),
            "gdal_ms": round(gdal_ms, 3),
            "time_ratio_ours_over_gdal": round(t["ours_ms"] / gdal_ms, 4),
            "max_diff_m": round(float(diff.max()), 4) if diff.size else 0.0,
            "rms_diff_m": round(float(np.sqrt((diff ** 2).mean())), 4) if diff.size else 0.0,
            "ours_max_err_m": round(float(eo.max()), 4) if eo.size else 0.0,
            "ours_rms_err_m": round(float(np.sqrt((eo ** 2).mean())), 4) if eo.size else 0.0,
            "gdal_max_err_m": round(float(eg.max()), 4) if eg.size else 0.0,
            "gdal_rms_err_m": round(float(np.sqrt((eg ** 2).mean())), 4) if eg.size else 0.0,
            "ours_nodata": int(np.isnan(ours).sum()),
            "gdal_nodata": int(np.isnan(g).sum()),
        }
        rows.append(row)
        print(
            f"{crs} {n}² e={e}: ours {row['ours_ms']} ms, GDAL {row['gdal_ms']} ms "
            f"(ratio {row['time_ratio_ours_over_gdal']}); |ours-GDAL| max {row['max_diff_m']} m; "
            f"vs point reference: ours max {row['ours_max_err_m']} m, GDAL max {row['gdal_max_err_m']} m "
            f"(RMS {row['ours_rms_err_m']} / {row['gdal_rms_err_m']})"
        )
    with out_path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)


if __name__ == "__main__":
    main()
