#!/usr/bin/env python3
"""A client not written in this crate: talks to a running Patchwork daemon from the .proto alone.

    python3 tests/python/client.py HOST:PORT

Generates Python stubs from proto/patchwork/v1/*.proto with grpcio-tools into a temporary
folder, then checks health, lists surveys, streams patches and resamples a tile. Prints one
summary line and exits 0, or prints what went wrong to stderr and exits non-zero.

Needs: python3 -m pip install -r tests/python/requirements.txt
"""

import math
import os
import subprocess
import sys
import tempfile

# The Copernicus test crop covers lon -119.0..-118.917, lat 34.458..34.542.
ROI = (-119.0, 34.45, -118.9, 34.55)
ERROR_M = 5.0
TILE = 64
TIMEOUT_S = 30.0

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
PROTO = os.path.join(REPO, "proto")


class Failure(Exception):
    pass


def require(ok, msg):
    if not ok:
        raise Failure(msg)


def generate(out_dir):
    """Stubs for package patchwork.v1, as any outside client would build them."""
    v1 = os.path.join(PROTO, "patchwork", "v1")
    protos = sorted(
        os.path.join("patchwork", "v1", f) for f in os.listdir(v1) if f.endswith(".proto")
    )
    require(protos, f"no .proto files in {v1}")
    cmd = [
        sys.executable, "-m", "grpc_tools.protoc",
        "-I", PROTO,
        f"--python_out={out_dir}",
        f"--grpc_python_out={out_dir}",
    ] + protos
    r = subprocess.run(cmd, cwd=PROTO, capture_output=True, text=True)
    require(
        r.returncode == 0,
        f"grpc_tools.protoc failed ({r.returncode}): {' '.join(cmd)}\n{r.stdout}{r.stderr}",
    )


def run(address):
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    with tempfile.TemporaryDirectory(prefix="patchwork-py-stubs-") as stubs:
        generate(stubs)
        sys.path.insert(0, stubs)
        from patchwork.v1 import admin_pb2, admin_pb2_grpc, terrain_pb2, terrain_pb2_grpc
        import numpy as np

        options = [
            ("grpc.max_receive_message_length", 64 << 20),
            ("grpc.max_send_message_length", 64 << 20),
        ]
        with grpc.insecure_channel(address, options=options) as channel:
            try:
                grpc.channel_ready_future(channel).result(timeout=TIMEOUT_S)
            except grpc.FutureTimeoutError:
                raise Failure(f"could not connect to {address} within {TIMEOUT_S:.0f} s")

            # 1. Health of the whole server.
            health = health_pb2_grpc.HealthStub(channel)
            h = health.Check(health_pb2.HealthCheckRequest(service=""), timeout=TIMEOUT_S)
            require(
                h.status == health_pb2.HealthCheckResponse.SERVING,
                f"Health.Check(\"\") = {health_pb2.HealthCheckResponse.ServingStatus.Name(h.status)},"
                " want SERVING",
            )

            # 2. At least one active survey.
            admin = admin_pb2_grpc.AdminStub(channel)
            listed = admin.ListSurveys(admin_pb2.ListSurveysRequest(), timeout=TIMEOUT_S)
            active = [s for s in listed.surveys if s.status == "active"]
            require(
                active,
                "Admin.ListSurveys has no active survey: "
                + repr([(s.source, s.status, s.error) for s in listed.surveys]),
            )

            terrain = terrain_pb2_grpc.TerrainStub(channel)
            roi = terrain_pb2.Rect(xmin=ROI[0], ymin=ROI[1], xmax=ROI[2], ymax=ROI[3])
            cut = terrain_pb2.UniformCut(roi=roi, error=ERROR_M)

            # 3. Patches, streamed in batches; each window holds cols × rows samples.
            batches = 0
            patches = []
            for batch in terrain.QueryPatches(
                terrain_pb2.PatchQuery(uniform=cut), timeout=TIMEOUT_S
            ):
                batches += 1
                patches.extend(batch.patches)
            require(patches, f"QueryPatches over {ROI} at error {ERROR_M} m returned no patch")
            whole = [p for p in patches if p.cols > 0 and p.rows > 0 and len(p.samples) == p.cols * p.rows]
            require(
                whole,
                "no patch has cols × rows samples: "
                + repr([(p.id, p.cols, p.rows, len(p.samples)) for p in patches[:10]]),
            )
            bad = [p.id for p in patches if len(p.samples) != p.cols * p.rows]
            require(not bad, f"{len(bad)} patches whose samples are not cols × rows, e.g. {bad[:5]}")

            # 4. A resampled tile with real heights in it.
            tile = terrain.ResampleTile(
                terrain_pb2.TileRequest(uniform=cut, width=TILE, height=TILE),
                timeout=TIMEOUT_S,
            )
            n = TILE * TILE
            require(
                tile.width == TILE and tile.height == TILE,
                f"ResampleTile gave {tile.width}×{tile.height}, asked for {TILE}×{TILE}",
            )
            require(len(tile.heights) == n, f"tile has {len(tile.heights)} heights, want {n}")
            require(len(tile.valid) == n, f"tile has {len(tile.valid)} valid bytes, want {n}")
            valid = [z for z, v in zip(tile.heights, tile.valid) if v == 1]
            require(valid, "the tile has no valid sample")
            nonfinite = [z for z in valid if not math.isfinite(z)]
            require(not nonfinite, f"{len(nonfinite)} valid samples are not finite, e.g. {nonfinite[:5]}")

            # 5. The same tile as bands of f32 bytes, put together as one numpy array, and a
            # tile too big for gRPC's default 4 MB limit as one message, which this channel
            # keeps.
            arr, first = tile_array(terrain, terrain_pb2.TileRequest(uniform=cut, width=TILE, height=TILE))
            require(arr.shape == (TILE, TILE), f"TileBands gave {arr.shape}")
            same = np.array(tile.heights, dtype="<f4").reshape(TILE, TILE)
            require(
                np.array_equal(arr, same, equal_nan=True),
                "TileBands and ResampleTile disagree",
            )
            require(first.backend == tile.backend, f"TileBands ran on {first.backend!r}")
            with grpc.insecure_channel(address) as plain:
                small_limit = terrain_pb2_grpc.TerrainStub(plain)
                big, _ = tile_array(
                    small_limit, terrain_pb2.TileRequest(uniform=cut, width=1800, height=1200)
                )
            require(big.shape == (1200, 1800), f"the big tile came as {big.shape}")
            require(np.isfinite(big).any(), "the big tile has no valid sample")

            print(
                f"ok: {address} SERVING, {len(active)} active survey(s), "
                f"{len(patches)} patches in {batches} batch(es) at error {ERROR_M:g} m, "
                f"tile {TILE}x{TILE} by {tile.backend}: {len(valid)}/{n} valid, "
                f"heights {min(valid):.1f}..{max(valid):.1f} m"
            )


def tile_array(terrain, request):
    """A tile from TileBands as one float32 array of height × width, NaN where there is no
    data, and the first band (which says what ran and how many patches were blended)."""
    import numpy as np

    arr, first = None, None
    for band in terrain.TileBands(request, timeout=TIMEOUT_S):
        if first is None:
            first = band
            arr = np.empty((band.height, band.width), dtype="<f4")
        rows = np.frombuffer(band.heights, dtype="<f4").reshape(band.rows, band.width)
        arr[band.row : band.row + band.rows] = rows
    require(first is not None, "TileBands sent no band")
    return arr, first


def main(argv):
    if len(argv) != 2:
        print(f"usage: {argv[0]} HOST:PORT", file=sys.stderr)
        return 2
    try:
        import grpc  # noqa: F401
        import grpc_tools.protoc  # noqa: F401
        import grpc_health.v1.health_pb2  # noqa: F401
        import numpy  # noqa: F401
    except ImportError as e:
        print(
            f"FAIL: {e}; install the client's packages with:"
            " python3 -m pip install -r tests/python/requirements.txt",
            file=sys.stderr,
        )
        return 3
    import grpc

    try:
        run(argv[1])
    except Failure as e:
        print(f"FAIL: {e}", file=sys.stderr)
        return 1
    except grpc.RpcError as e:
        print(f"FAIL: RPC error {e.code().name}: {e.details()}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
