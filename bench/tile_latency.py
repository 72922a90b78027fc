"""Tile latency side by side: the daemon over gRPC against GDAL, in one run.

Usage: python3 bench/tile_latency.py [--quick]

Builds a store of the Copernicus + NASADEM N34W119 pair from ../shared/data, starts
`target/release/patchwork serve` on it (CPU backend, as on a server without a GPU), and times
tiles of 64², 512² and 2048² over squares of 0.05°, 0.2° and 1° centred on the cell, at
e = 0 and 5 m:

- ours: the Python client (clients/python) asks TileBands and puts the bands together as one
  float32 array (what a client has in hand, decoded);
- GDAL warm: rasterio (GDAL) bilinearly warps the same files onto the same grid with both
  datasets kept open, as a tile server keeps them, the later source winning where both have
  data (a VRT mosaic);
- GDAL cold: the same, opening the files for every tile.

Medians of several requests each. Writes docs/bench/tile_latency.csv and
docs/bench/tile_latency.png; docs/BENCHMARKS.md reads them. Needs `cargo build --release`
first, `python3 -m pip install -r bench/requirements.txt ./clients/python`.
"""

import csv
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import rasterio

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
DATA = os.environ.get("PATCHWORK_SHARED_DATA", os.path.join(REPO, "..", "shared", "data"))
SOURCES = [
    os.path.join(DATA, "Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif"),
    os.path.join(DATA, "NASADEM_HGT_n34w119.tif"),
]
BIN = os.path.join(REPO, "target", "release", "patchwork")
CENTRE = (-118.5, 34.5)
SIZES = [64, 512, 2048]
EXTENTS = [0.05, 0.2, 1.0]
ERRORS = [0.0, 5.0]

from patchwork_client import Client  # noqa: E402  (pip install ./clients/python)
from gdal_compare import warp  # noqa: E402  (the same GDAL warp as the bench's comparison)


def repeats(n, quick):
    base = {64: 41, 512: 15, 2048: 5}[n]
    return max(3, base // 4) if quick else base


def roi_of(extent):
    h = extent / 2
    return (CENTRE[0] - h, CENTRE[1] - h, CENTRE[0] + h, CENTRE[1] + h)


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def gdal_tile(datasets, roi, n):
    return warp(datasets, datasets[0].crs, roi, n)


def median_ms(f, k):
    f()  # the first request of a kind warms caches on both sides
    times = []
    for _ in range(k):
        t0 = time.perf_counter()
        f()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def chart(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(SIZES), figsize=(12, 3.8))
    for ax, n in zip(axes, SIZES):
        sub = [r for r in rows if r["size"] == n]
        x = np.arange(len(EXTENTS))
        w = 0.2
        series = [
            ("ours, e = 0", [r["ours_e0_ms"] for r in sub]),
            ("ours, e = 5", [r["ours_e5_ms"] for r in sub]),
            ("GDAL warm", [r["gdal_warm_ms"] for r in sub]),
            ("GDAL cold", [r["gdal_cold_ms"] for r in sub]),
        ]
        for k, (name, ys) in enumerate(series):
            ax.bar(x + (k - 1.5) * w, ys, w, label=name)
        ax.set_xticks(x, [f"{e:g}°" for e in EXTENTS])
        ax.set_yscale("log")
        ax.set_title(f"{n}² tile")
        ax.set_ylabel("median ms")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def wait_ready(client, seconds=30):
    """Until the daemon answers."""
    import grpc

    deadline = time.monotonic() + seconds
    while True:
        try:
            return client.stats()
        except grpc.RpcError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def main(argv):
    quick = "--quick" in argv

    for s in SOURCES:
        if not os.path.isfile(s):
            sys.exit(f"missing {s}: the shared data folder is expected beside the checkout")
    if not os.path.isfile(BIN):
        sys.exit(f"missing {BIN}: run `cargo build --release` first")
    tmp = tempfile.mkdtemp(prefix="patchwork-tiles-")
    data = os.path.join(tmp, "data")
    subprocess.run([BIN, "ingest", "--data-dir", data] + SOURCES, check=True, stdout=subprocess.DEVNULL)
    port = free_port()
    env = dict(os.environ, PATCHWORK_DATA_DIR=data, PATCHWORK_INBOX=os.path.join(tmp, "inbox"),
               PATCHWORK_LISTEN=f"127.0.0.1:{port}", PATCHWORK_HTTP_LISTEN="", PATCHWORK_LOG="warn",
               PATCHWORK_ALLOW_EMULATED_GPU="0")
    daemon = subprocess.Popen([BIN, "serve"], env=env, stdout=subprocess.DEVNULL)
    rows = []
    try:
        client = Client(f"127.0.0.1:{port}")
        wait_ready(client)
        warm = [rasterio.open(s) for s in SOURCES]
        for n in SIZES:
            for extent in EXTENTS:
                roi = roi_of(extent)
                k = repeats(n, quick)
                row = {"size": n, "extent_deg": extent, "repeats": k}
                for e in ERRORS:
                    def ours_tile():
                        return client.tile_with_info(roi, n, n, e, backend="cpu")

                    arr, info = ours_tile()
                    row[f"ours_e{e:g}_ms"] = median_ms(ours_tile, k)
                    row[f"ours_e{e:g}_patches"] = info.patches
                ours = arr
                row["gdal_warm_ms"] = median_ms(lambda: gdal_tile(warm, roi, n), k)

                def cold():
                    ds = [rasterio.open(s) for s in SOURCES]
                    try:
                        return gdal_tile(ds, roi, n)
                    finally:
                        for d in ds:
                            d.close()

                row["gdal_cold_ms"] = median_ms(cold, max(3, k // 3))
                g = gdal_tile(warm, roi, n)
                both = ~np.isnan(ours) & ~np.isnan(g)
                row["max_abs_diff_m_e5"] = float(np.max(np.abs(ours[both] - g[both]))) if both.any() else 0.0
                for e in ERRORS:
                    row[f"ratio_e{e:g}"] = row[f"ours_e{e:g}_ms"] / row["gdal_warm_ms"]
                rows.append(row)
                print(
                    f"{n:>4}² {extent:>4}°: ours {row['ours_e0_ms']:7.1f} / {row['ours_e5_ms']:7.1f} ms "
                    f"(e = 0 / 5), GDAL warm {row['gdal_warm_ms']:7.1f}, cold {row['gdal_cold_ms']:7.1f} ms; "
                    f"ours ÷ warm {row['ratio_e0']:.2f} / {row['ratio_e5']:.2f}",
                    flush=True,
                )
        for d in warm:
            d.close()
    finally:
        daemon.terminate()
        daemon.wait()
    out = os.path.join(REPO, "docs", "bench")
    fields = list(rows[0].keys())
    with open(os.path.join(out, "tile_latency.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.3f}" if isinstance(v, float) else v) for k, v in r.items()})
    chart(rows, os.path.join(out, "tile_latency.png"))
    print(f"wrote {out}/tile_latency.csv and tile_latency.png")


if __name__ == "__main__":
    main(sys.argv)
