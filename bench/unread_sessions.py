#!/usr/bin/env python3
"""What view sessions whose clients never read cost another client's tile, on a daemon.

Starts `patchwork serve` on a fresh store holding the full Copernicus N34W119 tile, opens 500
`ViewSession` streams over 10 channels, each sent one camera (3 km up, a 4,096-pixel viewport,
0.5 px) and never read, then times 64×64 `ResampleTile`s on a channel of their own while the
sessions stay open, and prints the daemon's resident memory beside them. Past
`limits.max_streams` the sessions are refused; those it keeps must cost the tile nothing.

    cargo build --release
    python3 bench/unread_sessions.py [--daemon target/release/patchwork] [--tiles 5]

Needs grpcio and the client's stubs (clients/python).
"""

import argparse
import os
import queue
import shutil
import socket
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "clients", "python"))

import grpc  # noqa: E402
from patchwork_client._proto import admin_pb2, admin_pb2_grpc, terrain_pb2, terrain_pb2_grpc  # noqa: E402

TILE = "Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


LOOK_Z = 400.0


def camera(k: int) -> terrain_pb2.ViewCut:
    """3 km up over the tile, looking north-east; each session a little further on."""
    s = (k % 40) / 40.0
    x, y = -118.8 + 0.5 * s, 34.2 + 0.5 * s
    return terrain_pb2.ViewCut(eye_x=x, eye_y=y, eye_z=3000.0, look_x=x + 0.05, look_y=y + 0.06,
                               look_z=LOOK_Z, fov_deg=60.0, viewport_px=4096, pixel_error=0.5)


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1e3
    return float("nan")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--daemon", default=os.path.join(ROOT, "target", "release", "patchwork"))
    ap.add_argument("--data", default=os.environ.get("PATCHWORK_SHARED_DATA",
                                                     os.path.join(ROOT, "..", "shared", "data")))
    ap.add_argument("--sessions", type=int, default=500)
    ap.add_argument("--tiles", type=int, default=5)
    ap.add_argument("--look-z", type=float, default=LOOK_Z,
                    help="the height looked at, 0.05° east and 0.06° north of the eye")
    a = ap.parse_args()
    globals()["LOOK_Z"] = a.look_z
    tmp = tempfile.mkdtemp()
    port = free_port()
    inbox = os.path.join(tmp, "inbox")
    env = dict(os.environ, PATCHWORK_DATA_DIR=os.path.join(tmp, "data"), PATCHWORK_INBOX=inbox,
               PATCHWORK_LISTEN=f"127.0.0.1:{port}", PATCHWORK_HTTP_LISTEN="")
    os.makedirs(inbox)
    daemon = subprocess.Popen([a.daemon, "serve"], env=env, stderr=subprocess.DEVNULL)
    opts = [("grpc.max_receive_message_length", 1 << 30)]
    try:
        channel = grpc.insecure_channel(f"127.0.0.1:{port}", options=opts)
        grpc.channel_ready_future(channel).result(timeout=30)
        admin = admin_pb2_grpc.AdminStub(channel)
        shutil.copy(os.path.join(a.data, TILE), os.path.join(inbox, TILE))
        admin.Ingest(admin_pb2.IngestRequest(paths=[os.path.join(inbox, TILE)]), timeout=600)
        print(f"ingested; daemon resident {rss_mb(daemon.pid):.0f} MB")
        # One session read whole: what each step's cut weighs.
        q = queue.Queue()
        q.put(camera(20))
        patches, size, t0 = 0, 0, time.perf_counter()
        for d in terrain_pb2_grpc.TerrainStub(channel).ViewSession(iter(q.get, None)):
            patches += len(d.added)
            size += d.ByteSize()
            if d.last:
                break
        q.put(None)
        print(f"one step read whole: {patches} patches, {size / 1e6:.1f} MB, "
              f"{time.perf_counter() - t0:.2f} s")
        # Each channel its own connection (a distinct option keeps grpcio from sharing one).
        chans = [grpc.insecure_channel(f"127.0.0.1:{port}", options=opts + [("patchwork.conn", k)])
                 for k in range(10)]
        sessions = []
        for k in range(a.sessions):
            q = queue.Queue()
            q.put(camera(k))
            stub = terrain_pb2_grpc.TerrainStub(chans[k % 10])
            sessions.append((q, stub.ViewSession(iter(q.get, None))))
        time.sleep(1.0)
        tile_chan = grpc.insecure_channel(f"127.0.0.1:{port}", options=opts + [("patchwork.conn", "tile")])
        terrain = terrain_pb2_grpc.TerrainStub(tile_chan)
        req = terrain_pb2.TileRequest(
            uniform=terrain_pb2.UniformCut(
                roi=terrain_pb2.Rect(xmin=-118.55, ymin=34.45, xmax=-118.45, ymax=34.55), error=0.0),
            width=64, height=64)
        worst = 0.0
        for k in range(a.tiles):
            t0 = time.perf_counter()
            try:
                terrain.ResampleTile(req, timeout=120)
                ok = "ok"
            except grpc.RpcError as e:
                ok = e.code().name
            s = time.perf_counter() - t0
            worst = max(worst, s)
            print(f"tile {k}: {s:.3f} s ({ok}); daemon resident {rss_mb(daemon.pid):.0f} MB")
            time.sleep(1.0)
        print(f"worst 64x64 tile beside {a.sessions} unread sessions: {worst:.3f} s")
        for q, call in sessions:
            call.cancel()
            q.put(None)
    finally:
        daemon.terminate()
        daemon.wait()
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
