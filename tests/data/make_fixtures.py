"""Cuts the real-file fixtures in tests/data/real from the full files in ../shared/data.

Usage: python3 tests/data/make_fixtures.py [SHARED_DATA_DIR]

GDAL (through rasterio) writes each crop in the encoding of the file it was cut from: tiled
deflate with the float predictor, strips of 16-bit integers, tiles with padding, deflate
strips, a declared nodata of 0 beside a NaN. So the readers are tested on files written by
other software, in the variants people have, without the full files beside the checkout. It
prints what each crop holds; the reader tests assert those figures.
"""

import os
import sys

import numpy as np
import rasterio
from rasterio.windows import Window

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "real")
SHARED = sys.argv[1] if len(sys.argv) > 1 else os.path.join(HERE, "..", "..", "..", "shared", "data")


def crop(src_name, out_name, col, row, cols, rows, **options):
    with rasterio.open(os.path.join(SHARED, src_name)) as src:
        w = Window(col, row, cols, rows)
        data = src.read(1, window=w)
        profile = dict(src.profile)
        for k in ("blockxsize", "blockysize", "tiled", "compress", "predictor", "interleave"):
            profile.pop(k, None)
        profile.update(width=cols, height=rows, transform=src.window_transform(w), **options)
        tags = src.tags()
    path = os.path.join(OUT, out_name)
    with rasterio.open(path, "w", **profile) as dst:
        dst.update_tags(**tags)
        dst.write(data, 1)
    describe(path)


def describe(path):
    with rasterio.open(path) as d:
        a = d.read(1)
        nodata = d.nodata
        voids = int(np.isnan(a).sum()) if a.dtype.kind == "f" else 0
        if nodata is not None:
            voids += int((a == nodata).sum())
        print(
            f"{os.path.basename(path)}: {d.width}x{d.height} {a.dtype} epsg={d.crs.to_epsg() if d.crs else None} "
            f"nodata={nodata} voids={voids} transform={tuple(d.transform)[:6]} "
            f"blocks={d.block_shapes[0]} {d.profile.get('compress')} {d.tags().get('AREA_OR_POINT')} "
            f"bytes={os.path.getsize(path)}"
        )


def main():
    os.makedirs(OUT, exist_ok=True)
    # Copernicus GLO-30: a COG of deflated float tiles with the float predictor, PixelIsPoint.
    crop("Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif", "copernicus_cog.tif", 0, 1650, 300, 300,
         tiled=True, blockxsize=128, blockysize=128, compress="deflate", predictor=3)
    # NASADEM over the same window: 16-bit integer strips of one row, PixelIsPoint.
    crop("NASADEM_HGT_n34w119.tif", "nasadem_strips.tif", 0, 1650, 300, 300,
         tiled=False, blockysize=1)
    # SRTM resampled to UTM 31N: 16-bit strips of four rows, with voids.
    crop("N44E005_UTM.tif", "srtm_utm.tif", 300, 0, 200, 240, tiled=False, blockysize=4)
    # A lidar DTM declaring nodata 0, with a NaN as well: float strips.
    crop("dtm_philondenx_32630_nan.tif", "philondenx_zero_nan.tif", 0, 0, 512, 64,
         tiled=False, blockysize=4)
    # The Rhine basin: deflated float strips of two rows, nodata -9999 outside the basin.
    crop("rhine_elv0.tif", "rhine_deflate_strips.tif", 600, 300, 200, 150,
         tiled=False, blockysize=2, compress="deflate")
    # A lidar DEM in uncompressed 128 x 128 tiles: 200 x 200 leaves padding in the last ones.
    crop("lidar_dem_26915.tif", "lidar_tiles_padded.tif", 100, 100, 200, 200,
         tiled=True, blockxsize=128, blockysize=128)
    # SRTM with every sample above 1,000 m removed; the file declares -32678 (sic).
    crop("N44E005_big_hole.tif", "srtm_big_hole.tif", 600, 225, 200, 200,
         tiled=False, blockysize=3)
    # Mont Ventoux in two CRSs, for surveys of different CRSs in one store: SRTM3 in
    # geographic WGS 84 (from the .hgt), and the same ground as shareloc resampled it to UTM
    # 31N, the two windows overlapping over most of the summit.
    crop("N44E005.hgt", "ventoux_geographic.tif", 240, 900, 200, 200,
         driver="GTiff", tiled=False, blockysize=8, compress="deflate")
    crop("N44E005_UTM.tif", "ventoux_utm31.tif", 240, 960, 160, 200,
         tiled=False, blockysize=8, compress="deflate")
    # An SRTM3 .hgt must be the whole 1201 x 1201 tile: Mont Ventoux's 400 x 400 samples are
    # kept, the rest made void, which keeps the file small in the repository.
    with open(os.path.join(SHARED, "N44E005.hgt"), "rb") as f:
        full = np.frombuffer(f.read(), dtype=">i2").reshape(1201, 1201)
    hgt = np.full_like(full, -32768)
    r0, c0 = 791, 135
    hgt[r0:r0 + 400, c0:c0 + 400] = full[r0:r0 + 400, c0:c0 + 400]
    os.makedirs(os.path.join(OUT, "hgt"), exist_ok=True)
    path = os.path.join(OUT, "hgt", "N44E005.hgt")
    hgt.astype(">i2").tofile(path)
    print(f"hgt/N44E005.hgt: kept rows {r0}..{r0 + 400}, cols {c0}..{c0 + 400}; "
          f"voids={int((hgt == -32768).sum())} summit={int(full[r0:r0 + 400, c0:c0 + 400].max())}")
    # The same summit as an ESRI ASCII grid, written by GDAL's AAIGrid driver.
    with rasterio.open(os.path.join(SHARED, "N44E005.hgt")) as src:
        w = Window(c0 + 100, r0 + 150, 120, 100)
        data = src.read(1, window=w)
        profile = dict(driver="AAIGrid", width=120, height=100, count=1, dtype="int16",
                       crs=src.crs, transform=src.window_transform(w), nodata=-32768)
    path = os.path.join(OUT, "ventoux.asc")
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data, 1)
    for extra in ("ventoux.prj", "ventoux.asc.aux.xml"):
        p = os.path.join(OUT, extra)
        if os.path.exists(p) and extra.endswith(".aux.xml"):
            os.remove(p)
    describe(path)


if __name__ == "__main__":
    main()
