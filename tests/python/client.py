#!/usr/bin/env python3
"""The Python client package against a running daemon, as a user would script it.

    python tests/python/client.py HOST:PORT

Needs `pip install ./clients/python` and tests/python/requirements.txt. The daemon holds the
Copernicus and NASADEM crops of N34 W119, the SRTM voids crop of N44 E005 (tests/data), and a
coarser copy of part of the Copernicus crop on a rotated lattice.
Checks health, every Terrain call through `patchwork_client`, that `resample` over streamed
patches reproduces the daemon's tile within 1 mm with the same nodata mask (where surveys
meet, at voids and borders), that meshes are made of the cut's heights, that a view
session's patches are the view cut at every step, and runs the README's hillshade example.
With --bicubic, `resample` again in a store of bicubic patches; with --crs, `resample`, points
and tiles across CRSs in a geographic store holding a UTM survey. Prints one summary line and
exits 0, or says what went wrong and exits 1.
"""

import os
import re
import subprocess
import sys

import grpc
import numpy as np
from grpc_health.v1 import health_pb2, health_pb2_grpc

import patchwork_client as pc
from patchwork_client._proto import terrain_pb2, terrain_pb2_grpc

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))

# Where the Copernicus and NASADEM crops overlap, with the Copernicus-only west beside it.
MEET = (-118.99, 34.46, -118.90, 34.53)
# The SRTM crop with 2,008 voids.
VOIDS = (5.80, 44.80, 5.95, 44.95)


class Failure(Exception):
    pass


def require(ok, msg):
    if not ok:
        raise Failure(msg)


def check_resample(c, roi, error, width, height):
    """The daemon's tile against `resample` over the cut's patches; the patches' count, kinds
    and the largest difference."""
    patches = c.query_patches(roi, error)
    require(patches, f"no patch over {roi} at {error} m")
    daemon = c.tile(roi, width, height, error, backend="cpu")
    ours = pc.resample(patches, roi, width, height, blend=c.stats().blend)
    require(daemon.shape == ours.shape == (height, width), f"shapes {daemon.shape} {ours.shape}")
    dn, on = np.isnan(daemon), np.isnan(ours)
    require(
        np.array_equal(dn, on),
        f"{roi} at {error} m: nodata differs at {int((dn != on).sum())} of {dn.size} samples, "
        f"e.g. {np.argwhere(dn != on)[:5].tolist()}",
    )
    require((~dn).any(), f"{roi} at {error} m: the tile has no data")
    diff = float(np.max(np.abs(daemon[~dn] - ours[~dn])))
    require(diff <= 1e-3, f"{roi} at {error} m: resample is {diff:.4g} m off the daemon's tile")
    return patches, diff


def check_conflicts(active):
    """Accuracies as served are what each survey claims, raised where the others contradict
    it; each overlap says where the other survey lies. The rotated copy (d.tif) is a coarser
    copy of the Copernicus crop on a turned lattice: no shift aligns it, so either it is found
    the false one or the pair is undetermined and the finer surveys take the tie; each
    conflict names the test that decided it."""
    by_name = {os.path.basename(s.source): s for s in active}
    for s in active:
        require(s.accuracy_median_m <= s.accuracy_p90_m <= s.accuracy_m + 1e-9, f"{s}")
        require(s.claimed_accuracy_m <= s.accuracy_m + 1e-9, f"{s}")
        for k in s.conflicts:
            require(k.shift_m is not None and k.rms_after_m is not None, f"{k}")
    a, b, d = by_name["a.tif"], by_name["b.tif"], by_name["d.tif"]
    (ab,) = [k for k in a.conflicts if k.survey == b.id]
    (ba,) = [k for k in b.conflicts if k.survey == a.id]
    # Copernicus and NASADEM lie within a metre or two of each other (a cell is ~30 m), and
    # each says so of the other with the sign turned.
    require(np.hypot(ab.shift_m[0], ab.shift_m[1]) < 5.0, f"{ab}")
    require(np.allclose(ab.shift_m, [-v for v in ba.shift_m]), f"{ab} vs {ba}")
    tests = {
        "prediction",
        "detail",
        "transfer",
        "noise",
        "line",
        "consensus",
        "undetermined",
    }
    require(all(k.decided_by in tests for s in active for k in s.conflicts), f"{active}")
    require(len(d.conflicts) == 2, f"{d}")
    require(all(k.distrusted == "this" or (k.distrusted == "both" and not k.takes_tie)
                for k in d.conflicts), f"{d}")
    require(all(k.distrusted == "other" or (k.distrusted == "both" and k.takes_tie)
                for s in (a, b) for k in s.conflicts if k.survey == d.id), f"{a}")
    require(d.accuracy_m > d.claimed_accuracy_m, f"{d}")


def resample_tiles(c):
    """check_resample where two surveys meet (with fallback patches at e = 0 where the coarser
    one alone has data), at voids and borders: the largest difference, the kinds of patch met,
    the fallback patches and each kind's wire bytes."""
    worst, kinds, fallback = 0.0, set(), 0
    per_patch = {}
    for roi, error in [(MEET, 0.0), (MEET, 5.0), (MEET, 20.0), (MEET, 100.0), (VOIDS, 0.0), (VOIDS, 20.0)]:
        patches, diff = check_resample(c, roi, error, 300, 240)
        worst = max(worst, diff)
        kinds |= {p.kind for p in patches}
        fallback += sum(p.fallback for p in patches)
        for p in patches:
            per_patch.setdefault(p.kind, []).append(p.wire_bytes)
    return worst, kinds, fallback, per_patch


def run_bicubic(address):
    """In a store of bicubic patches, `resample` is the daemon's tile."""
    with pc.Client(address) as c:
        worst, kinds, fallback, _ = resample_tiles(c)
        require(kinds == {"bicubic", "edge"}, f"the cuts hold only {kinds} patches")
    print(f"ok: bicubic patches; resample within {worst * 1000:.3g} mm of the daemon on 6 tiles ({fallback} fallback patches)")


def run_crs(address):
    """In a geographic store holding Mont Ventoux in WGS 84 and in UTM 31N: `resample`, given
    the store's CRS, carries the samples to the UTM survey's patches with pyproj and is the
    daemon's tile (which carries them through its lattice); a tile, a cut and points asked in
    UTM 31N are the same ground as in the store's CRS."""
    import pyproj

    with pc.Client(address) as c:
        stats = c.stats()
        require(stats.crs_key == "EPSG:4326", f"the store's CRS is {stats.crs_key!r}")
        crss = sorted(s.crs_key for s in c.surveys() if s.status == pc.SurveyStatus.ACTIVE)
        require(crss == ["EPSG:32631", "EPSG:4326"], f"the surveys' CRSs are {crss}")
        worst, others = 0.0, 0
        # The pair's overlap, the UTM survey's part alone (its east), and a tile across both.
        for roi in [(5.26, 44.12, 5.34, 44.21), (5.37, 44.10, 5.41, 44.22), (5.22, 44.10, 5.40, 44.22)]:
            for error in (0.0, 5.0, 30.0):
                patches = c.query_patches(roi, error)
                others += sum(bool(p.crs) for p in patches)
                try:
                    pc.resample(patches, roi, 200, 160)
                    raise Failure("resample took patches of another CRS without the store's")
                except ValueError:
                    pass
                daemon = c.tile(roi, 200, 160, error, backend="cpu")
                ours = pc.resample(patches, roi, 200, 160, crs=stats.crs_key, blend=stats.blend)
                dn, on = np.isnan(daemon), np.isnan(ours)
                require(np.array_equal(dn, on), f"{roi} at {error} m: nodata differs at {int((dn != on).sum())} samples")
                require((~dn).any(), f"{roi} at {error} m: the tile has no data")
                diff = float(np.max(np.abs(daemon[~dn] - ours[~dn])))
                require(diff <= 1e-3, f"{roi} at {error} m: resample is {diff:.4g} m off the daemon's tile")
                worst = max(worst, diff)
        require(others > 0, "no cut held a patch of the UTM survey")

        # Points asked in UTM 31N are the store's heights at the same ground, to pyproj's
        # transformation.
        to_utm = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:32631", always_xy=True)
        rng = np.random.default_rng(7)
        lon, lat = rng.uniform(5.22, 5.38, 200), rng.uniform(44.12, 44.20, 200)
        x, y = to_utm.transform(lon, lat)
        geo = c.sample(np.column_stack([lon, lat]), 0.0)
        utm = c.sample(np.column_stack([x, y]), 0.0, crs="EPSG:32631")
        ok = ~np.isnan(geo)
        require(ok.sum() > 150 and np.array_equal(ok, ~np.isnan(utm)), f"{ok.sum()} of 200 points have heights")
        point_diff = float(np.max(np.abs(geo[ok] - utm[ok])))
        require(point_diff <= 1e-3, f"points asked in UTM are {point_diff:.4g} m off the same ground asked in degrees")
        # Each height names the survey that served it, one of the store's; none where no height.
        ids = {s.id for s in c.surveys()}
        served = c.sources(np.column_stack([lon, lat]), 0.0)
        require(len(served) == 200, f"{len(served)} sources for 200 points")
        for k, s in enumerate(served):
            require((s is None) == (not ok[k]), f"point {k}: a source {s} with height {geo[k]}")
            if s is not None:
                require(s["survey"] in ids and s["cell_m"] > 0.0 and s["error_m"] >= 0.0, f"point {k}: {s}")

        # A UTM tile is in UTM: its info names the CRS, and its heights are the store's at
        # its pixels' centres carried back to degrees.
        box = (x.min(), y.min(), x.min() + 4000.0, y.min() + 3000.0)
        tile, info = c.tile_with_info(box, 80, 60, 0.0, crs="EPSG:32631")
        require(info.crs_key == "EPSG:32631", f"the UTM tile says it is in {info.crs_key!r}")
        cx = box[0] + (np.arange(80) + 0.5) * 50.0
        cy = box[3] - (np.arange(60) + 0.5) * 50.0
        X, Y = np.meshgrid(cx, cy)
        lon2, lat2 = to_utm.transform(X.ravel(), Y.ravel(), direction="INVERSE")
        back = c.sample(np.column_stack([lon2, lat2]), 0.0).reshape(60, 80)
        tn = np.isnan(tile)
        require(np.array_equal(tn, np.isnan(back)) and (~tn).any(), "the UTM tile's nodata is not the store's")
        tile_diff = float(np.max(np.abs(tile[~tn] - back[~tn])))
        require(tile_diff <= 1e-3, f"the UTM tile is {tile_diff:.4g} m off the store's heights at its pixels")
    print(
        f"ok: a geographic store with a UTM survey; resample across CRSs within {worst * 1000:.3g} mm of the "
        f"daemon on 9 tiles ({others} patches of the UTM survey); points and tiles asked in UTM within "
        f"{max(point_diff, tile_diff) * 1000:.3g} mm of the same ground asked in degrees"
    )


def run(address):
    with grpc.insecure_channel(address) as ch:
        try:
            grpc.channel_ready_future(ch).result(timeout=30)
        except grpc.FutureTimeoutError:
            raise Failure(f"could not connect to {address}")
        h = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(service=""), timeout=30)
        require(h.status == health_pb2.HealthCheckResponse.SERVING, f"health says {h.status}")

    with pc.Client(address) as c:
        surveys = c.surveys()
        active = [s for s in surveys if s.status == "active"]
        require(len(active) == 4, f"want 4 active surveys, have {[(s.source, s.status) for s in surveys]}")
        check_conflicts(active)

        # 1. resample over streamed patches is the daemon's tile.
        worst, kinds, fallback, per_patch = resample_tiles(c)
        require(kinds == {"bilinear", "edge"}, f"the cuts hold only {kinds} patches")
        bytes_per_patch = {k: int(np.median(v)) for k, v in per_patch.items()}

        # 2. Tiles: bands put together equal the unary ResampleTile, and a tile far past gRPC's
        # default 4 MB comes through a channel that keeps that limit.
        cut = terrain_pb2.UniformCut(roi=terrain_pb2.Rect(xmin=MEET[0], ymin=MEET[1], xmax=MEET[2], ymax=MEET[3]), error=5.0)
        # Both on the CPU: `auto` may send the two to different backends, which agree only to
        # the GPU's tolerance, and this compares them bit for bit.
        unary = c.terrain.ResampleTile(terrain_pb2.TileRequest(uniform=cut, width=64, height=48,
                                                               backend=terrain_pb2.BACKEND_CPU), timeout=30)
        banded, info = c.tile_with_info(MEET, 64, 48, 5.0, backend="cpu")
        require(np.array_equal(banded, np.array(unary.heights, dtype=np.float32).reshape(48, 64), equal_nan=True),
                "TileBands and ResampleTile disagree")
        require(info.backend == unary.backend and info.patches == unary.patches, f"{info} vs {unary.backend}")
        with grpc.insecure_channel(address) as plain:
            stub = terrain_pb2.TileRequest(uniform=cut, width=1800, height=1200)
            n = sum(b.rows for b in terrain_pb2_grpc.TerrainStub(plain).TileBands(stub, timeout=60))
        require(n == 1200, f"the big tile came with {n} rows")

        # 3. Heights at points are the tile's at its pixel centres.
        w, hgt = 64, 48
        tile = c.tile(MEET, w, hgt, 5.0, backend="cpu")
        xs = MEET[0] + (np.arange(w) + 0.5) * (MEET[2] - MEET[0]) / w
        ys = MEET[3] - (np.arange(hgt) + 0.5) * (MEET[3] - MEET[1]) / hgt
        X, Y = np.meshgrid(xs, ys)
        z = c.sample(np.stack([X.ravel(), Y.ravel()], axis=1), 5.0).reshape(hgt, w)
        require(np.allclose(z, tile, atol=1e-3, equal_nan=True), "sample() differs from the tile")

        # 4. A mesh's vertices are the cut's heights at its grid's corners, within the ROI; a
        # reach draws the surface over voids, no farther from data than it says.
        for roi, kw in [(MEET, dict(size=65, rows=40)), (VOIDS, dict(size=129, hole_reach=300.0))]:
            m = c.mesh(roi, 5.0, mesh_error=2.0, backend="cpu", **kw)
            v = m.vertices
            require(len(m.triangles) > 0 and m.triangles.max() < len(v), f"mesh over {roi}: {len(m.triangles)} triangles")
            inside = (v[:, 0] >= roi[0] - 1e-9) & (v[:, 0] <= roi[2] + 1e-9) & (v[:, 1] >= roi[1] - 1e-9) & (v[:, 1] <= roi[3] + 1e-9)
            require(inside.all(), f"mesh over {roi}: vertices outside it")
            z = c.sample(v[:, :2], 5.0)
            measured = ~np.isnan(z)
            require(np.allclose(v[measured, 2], z[measured], atol=1e-3), f"mesh over {roi}: vertex heights are not the cut's")
            require(m.max_deviation <= 2.0 + 1e-9, f"mesh over {roi}: max deviation {m.max_deviation}")
            require(0.0 <= m.max_hole_reach <= kw.get("hole_reach", 0.0) + 1e-3, f"mesh over {roi}: reach {m.max_hole_reach}")
            if roi is VOIDS:
                require((~measured).any() and m.max_hole_reach > 0, "the voids crop's mesh draws no void over")

        # 5. A view session follows the view cut along a flight.
        steps = []
        with c.view_session() as session:
            for k in range(8):
                x, y = -119.02 + 0.01 * k, 34.44 + 0.01 * k
                cam = pc.Camera(eye=(x, y, 1500.0), look=(x + 0.05, y + 0.06, 400.0), fov_deg=60, viewport_px=800, pixel_error=2.0)
                step = session.update(cam)
                full = {p.id for p in c.query_view(cam)}
                require(set(session.patches) == full, f"frame {k}: the session holds {len(session.patches)} patches, the cut {len(full)}")
                require(step.patches == len(full), f"frame {k}: the step says {step.patches}")
                steps.append(step)
        require(all(s.frame == k for k, s in enumerate(steps)), "frames out of order")
        require(sum(len(s.added) for s in steps[1:]) < sum(s.patches for s in steps[1:]), "deltas resend the whole cut")

        # A session with a cache and prefetch, out and back: the cut stays exact, patches come
        # back from the cache, and the cache stays within its bytes.
        with c.view_session(cache_bytes=2 << 20, prefetch_bytes=64 << 10) as session:
            restored = prefetched = 0
            for k in list(range(8)) + list(range(7, -1, -1)):
                x, y = -119.02 + 0.01 * k, 34.44 + 0.01 * k
                cam = pc.Camera(eye=(x, y, 1500.0), look=(x + 0.05, y + 0.06, 400.0), fov_deg=60, viewport_px=800, pixel_error=2.0)
                step = session.update(cam)
                full = {p.id: p for p in c.query_view(cam)}
                require(set(session.patches) == set(full), f"cached frame {k}: the session's cut differs from the view cut")
                require(all(np.array_equal(session.patches[i].samples, full[i].samples, equal_nan=True) for i in full),
                        f"cached frame {k}: a patch's samples differ")
                require(session._cached <= session.cache_bytes, "the cache outgrew its bytes")
                restored += len(step.restored)
                prefetched += len(step.prefetched)
            require(restored > 0, "nothing came back from the cache on the way back")
            require(prefetched > 0, "nothing was prefetched")

        # 6. Admin calls.
        stats = c.stats()
        require(stats.surveys == 4 and stats.patches > 0, f"stats: {stats}")
        v = c.verify()
        require(v.ok, f"verify: {v.problems}")

    # 7. The README's example, as written there, with this daemon's address.
    readme = open(os.path.join(REPO, "clients", "python", "README.md")).read()
    example = re.search(r"```python\n(.*?)```", readme, re.S).group(1)
    out = os.path.join(os.environ.get("TMPDIR", "/tmp"), f"hillshade-{os.getpid()}.png")
    env = dict(os.environ, PATCHWORK_ADDRESS=address, HILLSHADE_PNG=out, MPLBACKEND="Agg")
    r = subprocess.run([sys.executable, "-c", example], env=env, capture_output=True, text=True, timeout=120)
    require(r.returncode == 0, f"the README example failed:\n{r.stdout}{r.stderr}")
    require(os.path.getsize(out) > 10_000, "the README example wrote no image")
    os.remove(out)

    print(
        f"ok: {address} SERVING, {len(active)} surveys; resample within {worst * 1000:.3g} mm of the daemon "
        f"on 6 tiles ({fallback} fallback patches); median bytes per patch {bytes_per_patch}; "
        f"view session {len(steps)} frames, {sum(s.wire_bytes for s in steps[1:])} B of deltas after the first"
    )


def run_accurate(address):
    """In a store that blends with the accurate blend, of bilinear or bicubic patches,
    `resample` given the store's blend is the daemon's tile."""
    with pc.Client(address) as c:
        require(c.stats().blend == "accurate", f"the store blends with {c.stats().blend}")
        worst, kinds, fallback, _ = resample_tiles(c)
    print(f"ok: the accurate blend of {sorted(kinds)} patches; resample within {worst * 1000:.3g} mm of the "
          f"daemon on 6 tiles ({fallback} fallback patches)")


def main(argv):
    modes = {(): run, ("--bicubic",): run_bicubic, ("--crs",): run_crs, ("--accurate",): run_accurate}
    if len(argv) < 2 or tuple(argv[2:]) not in modes:
        print(f"usage: {argv[0]} HOST:PORT [--bicubic | --crs | --accurate]", file=sys.stderr)
        return 2
    try:
        modes[tuple(argv[2:])](argv[1])
    except Failure as e:
        print(f"FAIL: {e}", file=sys.stderr)
        return 1
    except grpc.RpcError as e:
        print(f"FAIL: {e.code()}: {e.details()}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
