"""One-file exports beside the tools a user would pick instead, in one run.

Usage: python3 bench/export_vs_tools.py [--smoke] [--runs N] [--bin PATH] [--data DIR] [--out DIR]

Two pairs, each run N times (3 by default), interleaved (ours, theirs, ours...) so that
whatever else the machine does falls on both, every run a fresh output file:

- a raster-DEM pyramid of the Copernicus tile, zooms 0 to 12, Mapbox terrain-RGB PNG tiles of 512² (the size
  rio-rgbify writes) in MBTiles:
  `patchwork export --format mbtiles --encoding mapbox --image png` over a store of that
  tile alone, beside `rio rgbify` (rio-rgbify 0.4, the
  classic maker of terrain-RGB MBTiles, GDAL's warp underneath) of the Copernicus tile with the
  same encoding (-b -10000 -i 0.1), zooms and 2 workers;
- a cloud-optimized GeoTIFF of the whole cell at one arc-second with averaged overviews:
  `patchwork export --format cog` beside `rio cogeo create` (rio-cogeo 7, GDAL 3.10 from
  rasterio 1.4.4: deflate, 512² blocks, average overviews);
- and ours alone, the same pyramid over a store of both the Copernicus and NASADEM tiles of
  the cell, blended, which no other tool here makes.

Reports the median wall seconds of each with min–max, the ratio ours ÷ theirs, the bytes each
wrote, and beside them what the tiles hold: over the zoom-12 tiles both wrote, how far our
heights lie from rio-rgbify's where both have data (RMS, 99th percentile, max), the cut's error bound our tiles are
made at (half a pixel at the equator), and for the COGs how far the two agree at full
resolution. Writes OUT/export_vs_tools.csv (OUT defaults to docs/bench). With --smoke, one run
on the Copernicus and NASADEM crops of tests/data, written to a temporary folder. Needs a
release build and `python3 -m pip install -r bench/requirements.txt`.
"""

import argparse
import csv
import io
import os
import shutil
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import rasterio
from PIL import Image

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EQUATOR_M = 40_075_016.686


def run(cmd):
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        sys.exit(f"{' '.join(map(str, cmd))} failed:\n{p.stdout}{p.stderr}")
    return time.perf_counter() - t


def mapbox_tiles(path, z):
    """Zoom z's tiles of an MBTiles as heights by (x, y), NaN where transparent."""
    db = sqlite3.connect(path)
    out = {}
    for x, row, data in db.execute(
        "SELECT tile_column, tile_row, tile_data FROM tiles WHERE zoom_level = ?", (z,)
    ):
        a = np.asarray(Image.open(io.BytesIO(data)).convert("RGBA")).astype(np.float64)
        h = -10000 + (a[..., 0] * 65536 + a[..., 1] * 256 + a[..., 2]) * 0.1
        # rio-rgbify has no alpha: where its source has no data it writes 0 m.
        out[(x, (1 << z) - 1 - row)] = np.where((a[..., 3] > 0) & (h != 0), h, np.nan)
    db.close()
    return out


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--smoke", action="store_true")
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--bin", default=os.path.join(REPO, "target/release/patchwork"))
    p.add_argument("--data", default=os.environ.get("PATCHWORK_SHARED_DATA", os.path.join(REPO, "..", "shared", "data")))
    p.add_argument("--out")
    a = p.parse_args()
    if a.smoke:
        files = [os.path.join(REPO, "tests/data", f) for f in ("copernicus_n34w119_crop.tif", "nasadem_n34w119_crop.tif")]
        a.runs = 1
    else:
        files = [os.path.join(a.data, f) for f in ("Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif", "NASADEM_HGT_n34w119.tif")]
    out_dir = a.out or (tempfile.mkdtemp() if a.smoke else os.path.join(REPO, "docs/bench"))
    os.makedirs(out_dir, exist_ok=True)
    work = tempfile.mkdtemp()
    # rasterio's command line, beside this interpreter (a virtual environment) or on PATH (a
    # system-wide pip install puts it in /usr/local/bin).
    rio = os.path.join(os.path.dirname(sys.executable), "rio")
    if not os.path.exists(rio):
        rio = shutil.which("rio") or sys.exit("no `rio` command: python3 -m pip install -r bench/requirements.txt")
    try:
        # Both tools read one file: the comparison is of a store of the Copernicus tile alone.
        # The store of both surveys is exported too, ours alone, as a user of several surveys
        # has no other tool that blends them.
        store = os.path.join(work, "store")
        run([a.bin, "ingest", "--data-dir", store, files[0]])
        pair = os.path.join(work, "pair")
        run([a.bin, "ingest", "--data-dir", pair, *files])
        src = files[0]
        with rasterio.open(src) as s:
            b, res = s.bounds, s.res[0]
        zmax = 12
        pyramid_ours = [a.bin, "export", "--data-dir", store, "--format", "mbtiles", "--encoding", "mapbox",
                        "--image", "png", "--size", "512", "--zooms", f"0-{zmax}"]
        pyramid_theirs = [rio, "rgbify", "-b", "-10000", "-i", "0.1", "--min-z", "0", "--max-z", str(zmax),
                          "--format", "png", "-j", "2"]
        roi = f"{b.left},{b.bottom},{b.right},{b.top}"
        cog_ours = [a.bin, "export", "--data-dir", store, "--format", "cog", "--roi", roi, "--resolution", repr(res)]
        cog_theirs = [rio, "cogeo", "create", "--cog-profile", "deflate", "--overview-resampling", "average",
                      "--blocksize", "512", "--quiet"]
        rows = []
        for name, ours, theirs in [
            ("pyramid z0-12, MBTiles", lambda o: pyramid_ours + [o], lambda o: pyramid_theirs + [src, o]),
            ("COG, 1 arc-second", lambda o: cog_ours + [o], lambda o: cog_theirs + [src, o]),
        ]:
            ext = "mbtiles" if "MBTiles" in name else "tif"
            t_ours, t_theirs = [], []
            for k in range(a.runs):
                o1, o2 = os.path.join(work, f"ours{k}.{ext}"), os.path.join(work, f"theirs{k}.{ext}")
                t_ours.append(run(ours(o1)))
                t_theirs.append(run(theirs(o2)))
            row = {
                "what": name,
                "ours_s": statistics.median(t_ours), "ours_min": min(t_ours), "ours_max": max(t_ours),
                "theirs_s": statistics.median(t_theirs), "theirs_min": min(t_theirs), "theirs_max": max(t_theirs),
                "ours_bytes": os.path.getsize(o1), "theirs_bytes": os.path.getsize(o2),
            }
            if ext == "mbtiles":
                mine, other = mapbox_tiles(o1, zmax), mapbox_tiles(o2, zmax)
                both = [k for k in mine if k in other]
                d = np.concatenate([(mine[k] - other[k]).ravel() for k in both])
                d = np.abs(d[np.isfinite(d)])
                row.update(tiles_compared=len(both), pixels=int(d.size), rms_m=float(np.sqrt(np.mean(d ** 2))),
                           p99_m=float(np.percentile(d, 99)), max_m=float(d.max()),
                           bound_m=0.5 * EQUATOR_M / (512 * 2 ** zmax))
            else:
                with rasterio.open(o1) as x, rasterio.open(o2) as y:
                    assert x.shape == y.shape, (x.shape, y.shape)
                    d = np.abs(x.read(1, masked=True).filled(np.nan).astype(np.float64) - y.read(1, masked=True).filled(np.nan))
                    d = d[np.isfinite(d)]
                row.update(tiles_compared=0, pixels=int(d.size), rms_m=float(np.sqrt(np.mean(d ** 2))),
                           p99_m=float(np.percentile(d, 99)), max_m=float(d.max()), bound_m=0.0)
            rows.append(row)
        t_pair = []
        for k in range(a.runs):
            t_pair.append(run(pyramid_ours[:3] + [pair] + pyramid_ours[4:] + [os.path.join(work, f"pair{k}.mbtiles")]))
        rows.append({
            "what": "pyramid z0-12, MBTiles, both surveys (ours alone)",
            "ours_s": statistics.median(t_pair), "ours_min": min(t_pair), "ours_max": max(t_pair),
            "theirs_s": float("nan"), "theirs_min": float("nan"), "theirs_max": float("nan"),
            "ours_bytes": os.path.getsize(os.path.join(work, f"pair{a.runs - 1}.mbtiles")), "theirs_bytes": 0,
            "tiles_compared": 0, "pixels": 0, "rms_m": float("nan"), "p99_m": float("nan"),
            "max_m": float("nan"), "bound_m": 0.5 * EQUATOR_M / (512 * 2 ** zmax),
        })
        print("| export | ours s (min–max) | theirs s (min–max) | ours ÷ theirs | ours bytes | theirs bytes "
              "| heights apart: RMS / p99 / max m | our cut's bound m |")
        print("|---|---|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['what']} | {r['ours_s']:.2f} ({r['ours_min']:.2f}–{r['ours_max']:.2f}) "
                  f"| {r['theirs_s']:.2f} ({r['theirs_min']:.2f}–{r['theirs_max']:.2f}) "
                  f"| {r['ours_s'] / r['theirs_s']:.2f} | {r['ours_bytes']:,} | {r['theirs_bytes']:,} "
                  f"| {r['rms_m']:.2f} / {r['p99_m']:.2f} / {r['max_m']:.2f} | {r['bound_m']:.1f} |")
        with open(os.path.join(out_dir, "export_vs_tools.csv"), "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        print(f"wrote {os.path.join(out_dir, 'export_vs_tools.csv')}")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
