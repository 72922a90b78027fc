"""An export's archives as their own readers see them: the pmtiles package reads the PMTiles
archive, Python's sqlite3 the MBTiles database, Pillow decodes each tile, and every tile is
held, bytes and decoded heights, to the daemon's HTTP tile of the same zoom, column, row and
options."""

import argparse
import io
import json
import sqlite3
import urllib.request

import numpy as np
from PIL import Image
from pmtiles.reader import MmapSource, Reader, all_tiles
from pmtiles.tile import TileType


def heights(data, encoding):
    """The heights of a raster-DEM tile as MapLibre decodes them, NaN where alpha is 0."""
    a = np.asarray(Image.open(io.BytesIO(data)).convert("RGBA")).astype(np.float64)
    r, g, b, alpha = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    if encoding == "terrarium":
        h = r * 256 + g + b / 256 - 32768
    else:
        h = -10000 + (r * 65536 + g * 256 + b) * 0.1
    return np.where(alpha > 0, h, np.nan)


def http_tile(base, z, x, y, ext, query):
    with urllib.request.urlopen(f"{base}/tiles/{z}/{x}/{y}.{ext}?{query}") as r:
        return r.read()


def hold(tiles, base, ext, query, encoding, size):
    """Every (z, x, y, bytes) against the server's; the number of tiles and of data pixels."""
    n = pixels = 0
    for (z, x, y), data in tiles:
        served = http_tile(base, z, x, y, ext, query)
        ours = heights(data, encoding)
        theirs = heights(served, encoding)
        assert ours.shape == (size, size), (z, x, y, ours.shape)
        assert np.array_equal(ours, theirs, equal_nan=True), (
            f"tile {z}/{x}/{y}: heights differ from the server's at "
            f"{int(np.sum(~np.isclose(ours, theirs, equal_nan=True)))} pixels"
        )
        assert data == served, f"tile {z}/{x}/{y}: bytes differ from the server's"
        n += 1
        pixels += int(np.sum(~np.isnan(ours)))
    return n, pixels


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--http", required=True)
    p.add_argument("--pmtiles", required=True)
    p.add_argument("--pmtiles-count", type=int, required=True)
    p.add_argument("--mbtiles", required=True)
    p.add_argument("--mbtiles-count", type=int, required=True)
    p.add_argument("--cog", required=True)
    p.add_argument("--cog-reference", required=True)
    a = p.parse_args()

    with open(a.pmtiles, "rb") as f:
        reader = Reader(MmapSource(f))
        header = reader.header()
        meta = reader.metadata()
        assert header["tile_type"] == TileType.WEBP, header["tile_type"]
        assert meta["encoding"] == "terrarium", meta
        assert meta["format"] == "webp" and meta["tileSize"] == 256, meta
        assert meta["heights"] == "store", meta
        # The surveys credited are those the server credits for the same bounds.
        b = ",".join(str(v) for v in meta["bounds"])
        with urllib.request.urlopen(f"{a.http}/tiles.json?bounds={b}") as r:
            served = json.load(r)
        assert meta["attribution"] == served["attribution"], (meta, served)
        assert "Copernicus" in meta["attribution"], meta
        assert meta["vertical_crs"] == served["vertical_crs"], (meta, served)
        # The header's bounds hold the crops (34.436–34.542 N, 119.000–118.883 W).
        assert header["min_lon_e7"] / 1e7 <= -118.99 and header["max_lon_e7"] / 1e7 >= -118.89
        assert header["min_lat_e7"] / 1e7 <= 34.44 and header["max_lat_e7"] / 1e7 >= 34.54
        tiles = list(all_tiles(reader.get_bytes))
        zooms = sorted({z for (z, _, _), _ in tiles})
        assert (zooms[0], zooms[-1]) == (header["min_zoom"], header["max_zoom"]), (zooms, header)
        n, px = hold(tiles, a.http, "webp", "encoding=terrarium&size=256", "terrarium", 256)
        assert n == a.pmtiles_count, (n, a.pmtiles_count)
        assert px > 0
        print(f"pmtiles: {n} tiles of zooms {zooms[0]}-{zooms[-1]} as served, {px} pixels of data")

    db = sqlite3.connect(a.mbtiles)
    meta = dict(db.execute("SELECT name, value FROM metadata"))
    assert meta["format"] == "png" and meta["encoding"] == "mapbox", meta
    assert "Copernicus" in meta["attribution"], meta
    for k in ("name", "bounds", "center", "minzoom", "maxzoom"):
        assert meta.get(k), (k, meta)
    rows = db.execute("SELECT zoom_level, tile_column, tile_row, tile_data FROM tiles").fetchall()
    # MBTiles rows count from the south.
    tiles = [((z, x, (1 << z) - 1 - row), bytes(d)) for z, x, row, d in rows]
    n, px = hold(tiles, a.http, "png", "encoding=mapbox&size=256", "mapbox", 256)
    assert n == a.mbtiles_count, (n, a.mbtiles_count)
    assert {z for (z, _, _), _ in tiles} == set(range(int(meta["minzoom"]), int(meta["maxzoom"]) + 1))
    print(f"mbtiles: {n} tiles as served, {px} pixels of data")

    # The COG: valid by rio-cogeo's rules (strict: its warnings fail too), and as GDAL reads
    # it, the heights of `patchwork tile` over the same pixels, with overviews halving down.
    import rasterio
    from rio_cogeo.cogeo import cog_validate

    valid, errors, warnings = cog_validate(a.cog, strict=True)
    assert valid, (errors, warnings)
    with rasterio.open(a.cog) as c, rasterio.open(a.cog_reference) as r:
        assert c.is_tiled and c.block_shapes[0] == (512, 512), c.block_shapes
        assert c.crs.to_epsg() == 4326 and c.transform.almost_equals(r.transform), (c.transform, r.transform)
        assert c.overviews(1) == [2], c.overviews(1)
        ours = c.read(1, masked=True).filled(np.nan).astype(np.float64)
        theirs = r.read(1, masked=True).filled(np.nan).astype(np.float64)
        assert ours.shape == theirs.shape, (ours.shape, theirs.shape)
        assert np.array_equal(np.isnan(ours), np.isnan(theirs)), "the voids differ"
        # Each block's pixel centres are worked out from its own corner: the same points to
        # within 1e-15°, and heights to within float32's rounding.
        gap = float(np.nanmax(np.abs(ours - theirs)))
        assert gap <= 1e-3, gap
        half = c.read(1, out_shape=(c.height // 2, c.width // 2), masked=True)
        assert half.count() > 0
        print(f"cog: {c.width} x {c.height}, overviews {c.overviews(1)}, valid, heights as `patchwork tile` within {gap} m")
    print("ok: the archives hold the server's tiles, and the COG is valid")


if __name__ == "__main__":
    main()
