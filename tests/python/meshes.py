"""Reads the mesh encodings `cargo test` wrote with independent decoders, and checks them
against what the daemon's mesh says they hold.

    python3 tests/python/meshes.py DIR

DIR holds tile.terrain (quantized-mesh-1.0, read with quantized-mesh-tile), tile.glb and
planar.glb (read with pygltflib: the geographic tile in metres, and the same mesh as a
projected CRS's), tile.obj and expected.json, written by tests/mesh.rs.
"""

import json
import math
import os
import sys

import numpy as np
import pygltflib
from quantized_mesh_tile.terrain import TerrainTile


class Failure(Exception):
    pass


def require(ok, msg):
    if not ok:
        raise Failure(msg)


def ecef_up(lon, lat):
    lon, lat = math.radians(lon), math.radians(lat)
    return np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)])


def check_terrain(path, want):
    west, south, east, north = want["roi"]
    t = TerrainTile(west=west, east=east, south=south, north=north)
    t.fromFile(path, hasLighting=True)
    n, tris = want["surface_vertices"], want["surface_triangles"]
    require(len(t.u) == n, f"terrain: {len(t.u)} vertices, want {n}")
    require(len(t.indices) == 3 * tris, f"terrain: {len(t.indices) // 3} triangles, want {tris}")
    require(max(t.indices) == n - 1, "terrain: the indices do not reach every vertex")
    coords = t.getVerticesCoordinates()
    lons = np.array([c[0] for c in coords])
    lats = np.array([c[1] for c in coords])
    hs = np.array([c[2] for c in coords])
    tol = (east - west) / 32767 + 1e-9
    require(lons.min() >= west - tol and lons.max() <= east + tol, "terrain: longitudes outside the tile")
    require(lats.min() >= south - tol and lats.max() <= north + tol, "terrain: latitudes outside the tile")
    lo, hi = want["height_range"]
    step = (hi - lo) / 32767 + 1e-3
    require(abs(hs.min() - lo) <= step and abs(hs.max() - hi) <= step,
            f"terrain: heights {hs.min()}..{hs.max()}, want {lo}..{hi}")
    edges = [len(t.westI), len(t.southI), len(t.eastI), len(t.northI)]
    require(edges == want["edges"], f"terrain: edge vertices {edges}, want {want['edges']}")
    require(all(abs(lons[i] - west) <= tol for i in t.westI), "terrain: a west edge vertex is not on the west edge")
    require(all(abs(lats[i] - north) <= tol for i in t.northI), "terrain: a north edge vertex is not on the north edge")
    # Oct-encoded normals: one unit vector per vertex, pointing away from the earth.
    require(len(t.vLight) == n, f"terrain: {len(t.vLight)} normals")
    up = [float(np.dot(np.array(v), ecef_up(lo_, la))) for v, lo_, la in zip(t.vLight, lons, lats)]
    require(min(up) > 0.2, f"terrain: a normal points {min(up):.2f} of the way up")
    return n


def read_glb(path, want):
    """A glb's node and its positions, checked against the accessors and the expected
    counts."""
    g = pygltflib.GLTF2().load(path)
    prim = g.meshes[0].primitives[0]
    pos = g.accessors[prim.attributes.POSITION]
    idx = g.accessors[prim.indices]
    require(pos.count == want["vertices"], f"glb: {pos.count} vertices, want {want['vertices']}")
    require(idx.count == 3 * want["triangles"], f"glb: {idx.count} indices, want {3 * want['triangles']}")
    blob = g.binary_blob()
    view = g.bufferViews[pos.bufferView]
    xyz = np.frombuffer(blob[view.byteOffset:view.byteOffset + view.byteLength], dtype="<f4").reshape(-1, 3)
    view = g.bufferViews[idx.bufferView]
    ind = np.frombuffer(blob[view.byteOffset:view.byteOffset + view.byteLength], dtype="<u4")
    require(int(ind.max()) < pos.count, "glb: an index past the vertices")
    require(np.allclose(xyz.min(axis=0), pos.min, atol=1e-4) and np.allclose(xyz.max(axis=0), pos.max, atol=1e-4),
            "glb: POSITION min/max do not bound the positions")
    return g.nodes[0], xyz.astype(np.float64)


def check_glb(path, want, lonlat):
    """A geographic tile's glb is in metres, east-north-up about the tile's centre: carried back
    through PROJ's earth-fixed frame it gives the OBJ's longitudes, latitudes and heights. A
    projected one is relative to the south-west corner, which the translation restores."""
    node, xyz = read_glb(path, want)
    if lonlat is None:
        tx, _, tz = node.translation
        west, south, east, north = want["roi"]
        require(abs(tx - west) < 1e-9 and abs(-tz - south) < 1e-9, f"glb: translation {node.translation}")
        # y-up: heights in the second coordinate.
        lo, hi = want["all_height_range"]
        require(abs(float(xyz[:, 1].min()) - lo) < 1e-2 and abs(float(xyz[:, 1].max()) - hi) < 1e-2, "glb: heights")
        return 0.0
    require(not node.translation, f"glb: a geographic tile's node is translated by {node.translation}")
    lon0, lat0, _ = node.extras["origin_lon_lat_height"]
    west, south, east, north = want["roi"]
    require(abs(lon0 - (west + east) / 2) < 1e-12 and abs(lat0 - (south + north) / 2) < 1e-12, f"glb: origin {lon0}, {lat0}")
    import pyproj

    to_ecef = pyproj.Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    ox, oy, oz = to_ecef.transform(lon0, lat0, 0.0)
    l, p = np.radians(lon0), np.radians(lat0)
    east_v = np.array([-np.sin(l), np.cos(l), 0.0])
    north_v = np.array([-np.sin(p) * np.cos(l), -np.sin(p) * np.sin(l), np.cos(p)])
    up_v = np.array([np.cos(p) * np.cos(l), np.cos(p) * np.sin(l), np.sin(p)])
    e, u, n = xyz[:, 0], xyz[:, 1], -xyz[:, 2]
    X = ox + e * east_v[0] + n * north_v[0] + u * up_v[0]
    Y = oy + e * east_v[1] + n * north_v[1] + u * up_v[1]
    Z = oz + e * east_v[2] + n * north_v[2] + u * up_v[2]
    glon, glat, gh = to_ecef.transform(X, Y, Z, direction="INVERSE")
    lon, lat, h = lonlat[:, 0], lonlat[:, 1], lonlat[:, 2]
    mx = 111_320.0 * np.cos(np.radians(lat0))
    horizontal = float(np.max(np.hypot((glon - lon) * mx, (glat - lat) * 111_132.0)))
    vertical = float(np.max(np.abs(gh - h)))
    # f32 positions tens of kilometres from the origin: a few millimetres.
    require(horizontal < 0.02 and vertical < 0.02,
            f"glb: {horizontal:.3g} m across and {vertical:.3g} m up from the OBJ's vertices")
    return max(horizontal, vertical)


def check_obj(path, want):
    """The OBJ's counts; its vertices (x, y, height), in order."""
    vs, f = [], 0
    with open(path) as fh:
        for line in fh:
            if line.startswith("v "):
                vs.append([float(w) for w in line.split()[1:4]])
            f += line.startswith("f ")
    require((len(vs), f) == (want["vertices"], want["triangles"]), f"obj: {len(vs)} vertices, {f} faces")
    return np.array(vs)


def main(argv):
    if len(argv) != 2:
        print(f"usage: {argv[0]} DIR", file=sys.stderr)
        return 2
    d = argv[1]
    want = json.load(open(os.path.join(d, "expected.json")))
    try:
        n = check_terrain(os.path.join(d, "tile.terrain"), want)
        lonlat = check_obj(os.path.join(d, "tile.obj"), want)
        off = check_glb(os.path.join(d, "tile.glb"), want, lonlat)
        check_glb(os.path.join(d, "planar.glb"), want, None)
    except Failure as e:
        print(f"FAIL: {e}", file=sys.stderr)
        return 1
    print(f"ok: quantized-mesh-tile read {n} vertices with normals and edges; pygltflib read {want['vertices']} vertices, "
          f"in metres within {off * 1000:.3g} mm of the OBJ's through PROJ")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
