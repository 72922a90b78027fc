"""Holds Cesium's heights to PROJ's: the daemon's quantized-mesh vertices, which it carries from
the store's EGM96 heights to the WGS 84 ellipsoid, against pyproj's vgridshift through the same
geoid grid.

    python3 tests/python/geoid_heights.py --http http://127.0.0.1:PORT --grid GRID
        [--seed S] [--points N] [--level L]

The daemon must hold a survey in EGM96 heights (the SRTM tile of tests/data) and have GRID
(Debian proj-data's egm96_15.gtx) for EPSG:5773. For tiles of level L drawn at random over the
survey (the seed is printed), each tile comes twice: as Cesium asks for it (heights above the
ellipsoid) and with heights=store. N vertices the two share, drawn at random, are carried from
the store's heights to the ellipsoid by pyproj; the ellipsoidal tile's vertex must agree within
0.5 m, and in fact within the two tiles' quantization steps.

Prints the figures and a line starting "ok: "; exits non-zero at the first failure.
"""

import argparse
import io
import json
import random
import statistics
import sys
import urllib.request

from pyproj import Transformer
from quantized_mesh_tile.terrain import TerrainTile


def fail(msg):
    print(f"FAIL: {msg}", file=sys.stderr)
    sys.exit(1)


def get(url):
    with urllib.request.urlopen(url, timeout=60) as r:
        return r.status, dict(r.headers), r.read()


def geo_bounds(level, x, y):
    """The geographic TMS tile's bounds: two root tiles, rows counted from the south."""
    size = 180.0 / 2**level
    west = -180.0 + x * size
    south = -90.0 + y * size
    return west, south, west + size, south + size


def decode(body, bounds):
    t = TerrainTile(west=bounds[0], south=bounds[1], east=bounds[2], north=bounds[3])
    t.fromBytesIO(io.BytesIO(body))
    steps = (t.header["maximumHeight"] - t.header["minimumHeight"]) / t.MAX
    # Vertices by their quantized position (the same grid vertex in both tiles), each with
    # its height in metres.
    heights = [h for _, _, h in t.getVerticesCoordinates()]
    return {(u, v): h for u, v, h in zip(t.u, t.v, heights)}, steps


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--http", required=True)
    p.add_argument("--grid", required=True)
    p.add_argument("--seed", type=int, default=random.SystemRandom().randrange(1 << 30))
    p.add_argument("--points", type=int, default=100)
    p.add_argument("--level", type=int, default=10)
    a = p.parse_args()
    print(f"seed {a.seed}")
    rng = random.Random(a.seed)

    status, _, body = get(f"{a.http}/terrain/layer.json")
    layer = json.loads(body)
    if layer.get("heights") != "ellipsoid":
        fail(f"layer.json says heights {layer.get('heights')!r}, not 'ellipsoid'")
    vertical = (layer.get("vertical_crs") or {}).get("key")
    if vertical != "EPSG:5773":
        fail(f"layer.json says the store's heights are from {vertical!r}, not EPSG:5773")
    west, south, east, north = layer["bounds"]

    # PROJ's own vgridshift through the grid: h = H + N (multiplier +1).
    to_ellipsoid = Transformer.from_pipeline(
        "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
        f"+step +proj=vgridshift +grids={a.grid} +multiplier=1 "
        "+step +proj=unitconvert +xy_in=rad +xy_out=deg"
    )

    level = a.level
    size = 180.0 / 2**level
    xs = range(int((west + 180.0) // size), int((east + 180.0) // size) + 1)
    ys = range(int((south + 90.0) // size), int((north + 90.0) // size) + 1)
    tiles = [(x, y) for x in xs for y in ys]
    rng.shuffle(tiles)
    pairs = []
    worst_step = 0.0
    # Tiles in random order until enough vertices with data are found: the survey's file may
    # hold voids (the SRTM crop is mostly void), which give the ellipsoid's 0 m in both.
    fetched = 0
    for x, y in tiles:
        if len(pairs) >= 5 * a.points or fetched >= 64:
            break
        fetched += 1
        b = geo_bounds(level, x, y)
        path = f"{a.http}/terrain/{level}/{x}/{y}.terrain"
        s1, h1, ell = get(path)
        s2, h2, sto = get(path + "?heights=store")
        if s1 != 200 or s2 != 200:
            fail(f"{path}: {s1} and {s2}")
        if "Warning" in h1 or "warning" in h1:
            fail(f"{path} came with a warning: {h1}")
        e, se = decode(ell, b)
        s, ss = decode(sto, b)
        worst_step = max(worst_step, se + ss)
        for key, h in e.items():
            if key in s:
                lon = b[0] + key[0] / 32767.0 * (b[2] - b[0])
                lat = b[1] + key[1] / 32767.0 * (b[3] - b[1])
                # Only where the survey has data: elsewhere, and in a void no survey is
                # near, both tiles hold the ellipsoid's 0 m.
                no_data = h == 0.0 and s[key] == 0.0
                if west < lon < east and south < lat < north and not no_data:
                    pairs.append((lon, lat, h, s[key], se + ss))
    if len(pairs) < a.points:
        fail(f"only {len(pairs)} shared vertices with data in {fetched} tiles of level {level}")
    held = rng.sample(pairs, a.points)
    offs = []
    for lon, lat, h_ell, h_store, step in held:
        _, _, ref = to_ellipsoid.transform(lon, lat, h_store)
        off = abs(h_ell - ref)
        offs.append(off)
        if off > 0.5:
            fail(
                f"at ({lon:.6f}, {lat:.6f}) the tile gives {h_ell:.3f} m above the ellipsoid, "
                f"PROJ {ref:.3f} m from the store's {h_store:.3f} m: {off:.3f} m apart"
            )
        if off > step + 1e-3:
            fail(
                f"at ({lon:.6f}, {lat:.6f}) {off:.4f} m from PROJ, more than the tiles' "
                f"quantization steps {step:.4f} m"
            )
    n_mean = statistics.mean(h - s for _, _, h, s, _ in held)
    print(
        f"{len(held)} vertices of {len(pairs)} shared in {fetched} tiles of level {level}: |Δ| to PROJ median "
        f"{statistics.median(offs):.4f} m, max {max(offs):.4f} m (quantization up to "
        f"{worst_step:.4f} m); mean N {n_mean:.2f} m"
    )
    print(f"ok: {len(held)} Cesium vertex heights within {max(offs):.4f} m of PROJ's")


if __name__ == "__main__":
    main()
