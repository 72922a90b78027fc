#!/usr/bin/env python3
"""What requests whose clients hang up cost the requests after them.

Starts `patchwork serve` on a fresh store holding the full Copernicus N34W119 tile, sends
16 quadtree meshes of 2049² over the whole tile, each with a 0.3 s deadline on the client's
side (the client cancels the call then, as a browser does when a user pans away), and times
a 16×16 tile sent right after. The same again with meshes that are waited for, as the
baseline: what the tile would wait behind work that nobody abandons.

    cargo build --release
    python3 bench/abandoned_requests.py [--daemon target/release/patchwork] [--runs 5]

Needs grpcio and the client's stubs (clients/python); prints medians over the runs.
"""

import argparse
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "clients", "python"))

import grpc  # noqa: E402
from patchwork_client._proto import admin_pb2, admin_pb2_grpc, terrain_pb2, terrain_pb2_grpc  # noqa: E402

TILE = "Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif"
ROI = terrain_pb2.Rect(xmin=-119.0, ymin=34.0, xmax=-118.0, ymax=35.0)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def mesh_request() -> terrain_pb2.MeshRequest:
    return terrain_pb2.MeshRequest(
        cut=terrain_pb2.UniformCut(roi=ROI, error=0.0), size=2049, rows=2049, mesh_error=0.5,
        method=terrain_pb2.MESH_METHOD_QUADTREE, backend=terrain_pb2.BACKEND_CPU)


def small_tile(terrain) -> float:
    """Seconds for a 16×16 tile of the middle of the survey."""
    req = terrain_pb2.TileRequest(
        uniform=terrain_pb2.UniformCut(
            roi=terrain_pb2.Rect(xmin=-118.55, ymin=34.45, xmax=-118.45, ymax=34.55), error=5.0),
        width=16, height=16, backend=terrain_pb2.BACKEND_CPU)
    t0 = time.perf_counter()
    terrain.ResampleTile(req, timeout=60)
    return time.perf_counter() - t0


def burst(terrain, abandon: bool) -> float:
    """16 meshes at once, abandoned after 0.3 s or not; then the small tile's wait."""
    def one():
        try:
            terrain.MeshTile(mesh_request(), timeout=0.3 if abandon else 120)
        except grpc.RpcError:
            pass
    threads = [threading.Thread(target=one) for _ in range(16)]
    for t in threads:
        t.start()
    time.sleep(0.35)
    waited = small_tile(terrain)
    for t in threads:
        t.join()
    return waited


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--daemon", default=os.path.join(ROOT, "target", "release", "patchwork"))
    ap.add_argument("--data", default=os.environ.get("PATCHWORK_SHARED_DATA",
                                                     os.path.join(ROOT, "..", "shared", "data")))
    ap.add_argument("--runs", type=int, default=5)
    a = ap.parse_args()
    tmp = tempfile.mkdtemp()
    port = free_port()
    inbox = os.path.join(tmp, "inbox")
    env = dict(os.environ, PATCHWORK_DATA_DIR=os.path.join(tmp, "data"), PATCHWORK_INBOX=inbox,
               PATCHWORK_LISTEN=f"127.0.0.1:{port}", PATCHWORK_HTTP_LISTEN="")
    os.makedirs(inbox)
    daemon = subprocess.Popen([a.daemon, "serve"], env=env, stderr=subprocess.DEVNULL)
    try:
        channel = grpc.insecure_channel(f"127.0.0.1:{port}", options=[
            ("grpc.max_receive_message_length", 1 << 30)])
        grpc.channel_ready_future(channel).result(timeout=30)
        admin = admin_pb2_grpc.AdminStub(channel)
        terrain = terrain_pb2_grpc.TerrainStub(channel)
        shutil.copy(os.path.join(a.data, TILE), os.path.join(inbox, TILE))
        admin.Ingest(admin_pb2.IngestRequest(paths=[os.path.join(inbox, TILE)]), timeout=600)
        idle = statistics.median(small_tile(terrain) for _ in range(a.runs))
        abandoned = statistics.median(burst(terrain, True) for _ in range(a.runs))
        kept = statistics.median(burst(terrain, False) for _ in range(1))
        print(f"16x16 tile, idle daemon:                         {idle * 1e3:8.1f} ms")
        print(f"16x16 tile after 16 meshes abandoned at 0.3 s:   {abandoned * 1e3:8.1f} ms")
        print(f"16x16 tile behind 16 meshes that are waited for: {kept * 1e3:8.1f} ms")
    finally:
        daemon.terminate()
        daemon.wait()
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
