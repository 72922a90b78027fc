"""Ingest beside GDAL: the time from a DEM file to something servable, ours against writing a
COG with overviews, in one run.

Usage: python3 bench/ingest_vs_gdal.py [--smoke] [--runs N] [--bin PATH] [--data DIR]
                                       [--files FILE ...] [--out DIR]

For each file, N times (5 by default), interleaved pair by pair (ours, then GDAL's, then ours
again...), so that whatever else the machine does falls on both:

- ours: the wall seconds of `patchwork ingest --data-dir DIR FILE` as a subprocess, DIR a fresh,
  empty folder every time. This is drop to committed: the process's start, opening (creating)
  the store, reading, modelling and indexing the file, and the store's commit and flush, up to
  the process's exit, after which the survey is servable. The seconds the command prints for
  the file itself (its own timer, without the process's start, the store's opening and its
  exit) are kept beside them (`ours_engine_s`).
- GDAL: the wall seconds of a fresh `python3 -c` subprocess that imports rasterio (1.4.4, which
  bundles GDAL 3.10) and writes a Cloud Optimized GeoTIFF of the same file with
  `rasterio.shutil.copy(src, dst, driver="COG", COMPRESS="DEFLATE", PREDICTOR=FLOATING_POINT
  (3) for float input or STANDARD (2) for integer input, NUM_THREADS="ALL_CPUS",
  OVERVIEWS="IGNORE_EXISTING", BLOCKSIZE=512)`, into a fresh folder on the same file system.
  IGNORE_EXISTING, not the default AUTO: with AUTO the driver copies the overviews a source
  already has instead of computing them, which the Copernicus file (a COG with overviews 2, 4
  and 8) would let it skip; this way GDAL computes its overviews from the full resolution for
  every file, as OVERVIEWS=AUTO does for a file without any, with the driver's default
  resampling (cubic). A subprocess, so that both sides pay a process's start; what that start
  costs GDAL's side (the interpreter and `import rasterio`) is the wall time less the copy's
  own, timed inside the subprocess, and is reported apart (`gdal_start_s`, with `gdal_copy_s`
  the copy alone).

Both sides read the same input file; it is read once before the first run so that the page
cache holds it for both. After each run the output is checked, and the bench fails (exits
non-zero) where it is wrong: ours with `patchwork surveys --data-dir DIR --json`, which must
list exactly one survey, of that file, not failed; GDAL's by opening the COG: its size, band
count and type must be the input's, its layout COG, deflate with the predictor asked, its
blocks 512², with overviews where the file is larger than a block, and a window at its centre
must equal the input's exactly (deflate is lossless).

Reports for each file its samples (cols × rows), the median seconds of each side with their
min–max, samples per second, the ratio ours ÷ GDAL (the target: 0.5 or less), and the bytes
each wrote (the store's folder, without the fixed 64 MiB disk-space reserve it keeps beside
the folder). Prints a markdown table and writes OUT/ingest_vs_gdal.csv and
OUT/ingest_vs_gdal.png (OUT defaults to docs/bench).

Inputs: the Copernicus GLO-30 (f32, deflate, float predictor) and NASADEM (i16) tiles of cell
N34W119 and the SRTM3 tile N44E005.hgt from ../shared/data (--data, or PATCHWORK_SHARED_DATA),
or the files given with --files. With --smoke, one run on the 300 × 300 Copernicus crop in
tests/data, in seconds, written to a temporary folder unless --out is given. Needs a release
build (`cargo build --release`) and `python3 -m pip install -r bench/requirements.txt`.
"""

import argparse
import csv
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
DATA = os.environ.get("PATCHWORK_SHARED_DATA", os.path.join(REPO, "..", "shared", "data"))
FULL = [
    "Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif",
    "NASADEM_HGT_n34w119.tif",
    "N44E005.hgt",
]
SMOKE = [os.path.join(REPO, "tests", "data", "copernicus_n34w119_crop.tif")]
BLOCK = 512
TARGET = 0.5  # ours ÷ GDAL we aim at

# The GDAL side, run as `python3 -c GDAL_COPY SRC DST PREDICTOR`: prints the seconds of the
# import and of the copy as JSON on its last line.
GDAL_COPY = """
import json, sys, time
t0 = time.perf_counter()
import rasterio
from rasterio.shutil import copy
t1 = time.perf_counter()
copy(sys.argv[1], sys.argv[2], driver="COG", COMPRESS="DEFLATE", PREDICTOR=sys.argv[3],
     NUM_THREADS="ALL_CPUS", OVERVIEWS="IGNORE_EXISTING", BLOCKSIZE="%d")
t2 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "copy_s": t2 - t1}))
""" % BLOCK

# `patchwork ingest` prints, for each file: OUTCOME SOURCE SURVEY (N samples, S s).
INGESTED = re.compile(r"^(inserted|replaced)\s+(.+) ([0-9a-f]{16}) \((\d+) samples, ([0-9.]+) s\)\s*$", re.M)


def describe(path):
    import rasterio
    from rasterio.errors import RasterioIOError

    try:
        ds = rasterio.open(path)
    except RasterioIOError as e:
        sys.exit(f"GDAL cannot open {path}: {e}")
    with ds:
        return {"cols": ds.width, "rows": ds.height, "count": ds.count, "dtype": ds.dtypes[0],
                "float": np.issubdtype(np.dtype(ds.dtypes[0]), np.floating)}


def disk_bytes(path):
    """The bytes of the file at `path`, or of the files under it: the COG, or the store's
    folder (not the fixed disk-space reserve the store keeps beside that folder)."""
    if os.path.isfile(path):
        return os.path.getsize(path)
    total = 0
    for root, _, files in os.walk(path):
        for f in files:
            p = os.path.join(root, f)
            if not os.path.islink(p):
                total += os.path.getsize(p)
    return total


def patchwork_env():
    """The environment without PATCHWORK_* settings, so that the store is opened with the
    defaults whatever the shell holds."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PATCHWORK_")}
    env["PATCHWORK_LOG"] = "warn"
    return env


def run_ours(bin_path, src, tmp, env):
    """Seconds of one `patchwork ingest` into a fresh store, its own seconds for the file, the
    samples it stored and the store's bytes; fails loudly unless the survey is listed."""
    work = tempfile.mkdtemp(prefix="ours-", dir=tmp)
    data = os.path.join(work, "data")
    try:
        t0 = time.perf_counter()
        p = subprocess.run([bin_path, "ingest", "--data-dir", data, src], env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if p.returncode != 0:
            sys.exit(f"ours: `patchwork ingest` of {src} exited {p.returncode}:\n{p.stdout}{p.stderr}")
        m = INGESTED.search(p.stdout)
        if not m:
            sys.exit(f"ours: `patchwork ingest` of {src} did not say it ingested the file:\n{p.stdout}{p.stderr}")
        engine_s = float(m.group(5))
        q = subprocess.run([bin_path, "surveys", "--data-dir", data, "--json"], env=env, capture_output=True, text=True)
        if q.returncode != 0:
            sys.exit(f"ours: `patchwork surveys` exited {q.returncode}:\n{q.stdout}{q.stderr}")
        try:
            listed = json.loads(q.stdout)
        except ValueError:
            sys.exit(f"ours: `patchwork surveys --json` printed no JSON:\n{q.stdout}{q.stderr}")
        if len(listed) != 1:
            sys.exit(f"ours: the store lists {len(listed)} surveys after ingesting {src}, not 1:\n{q.stdout}")
        s = listed[0]
        if s.get("status") in ("failed", "damaged") or os.path.basename(s.get("source", "")) != os.path.basename(src):
            sys.exit(f"ours: the survey listed is not {src}, servable:\n{q.stdout}")
        if not s.get("samples"):
            sys.exit(f"ours: the survey of {src} holds no samples:\n{q.stdout}")
        return wall, engine_s, int(s["samples"]), disk_bytes(data)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def check_cog(src, dst, info):
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(dst) as out, rasterio.open(src) as ref:
        got = (out.driver, out.width, out.height, out.count, out.dtypes[0])
        want = ("GTiff", info["cols"], info["rows"], info["count"], info["dtype"])
        if got != want:
            sys.exit(f"GDAL: the COG of {src} is {got}, not {want}")
        st = out.tags(ns="IMAGE_STRUCTURE")
        want_st = {"LAYOUT": "COG", "COMPRESSION": "DEFLATE", "PREDICTOR": "3" if info["float"] else "2"}
        if any(st.get(k) != v for k, v in want_st.items()):
            sys.exit(f"GDAL: the COG of {src} has the structure {st}, not {want_st}")
        if out.block_shapes[0] != (BLOCK, BLOCK):
            sys.exit(f"GDAL: the COG of {src} has blocks {out.block_shapes[0]}, not {BLOCK}²")
        if max(info["cols"], info["rows"]) > BLOCK and not out.overviews(1):
            sys.exit(f"GDAL: the COG of {src} has no overviews")
        n = min(256, info["cols"], info["rows"])
        w = Window((info["cols"] - n) // 2, (info["rows"] - n) // 2, n, n)
        a, b = out.read(1, window=w), ref.read(1, window=w)
        if not np.array_equal(a, b, equal_nan=np.issubdtype(a.dtype, np.floating)):
            sys.exit(f"GDAL: the COG of {src} differs from it at the centre")
        return len(out.overviews(1))


def run_gdal(src, tmp, info):
    """Wall seconds of one COG written by a fresh Python process, the copy's own seconds, the
    COG's bytes and its overview count; fails loudly unless the COG is right."""
    work = tempfile.mkdtemp(prefix="gdal-", dir=tmp)
    dst = os.path.join(work, "out.tif")
    predictor = "FLOATING_POINT" if info["float"] else "STANDARD"
    try:
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-c", GDAL_COPY, src, dst, predictor], capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if p.returncode != 0:
            sys.exit(f"GDAL: the COG copy of {src} exited {p.returncode}:\n{p.stdout}{p.stderr}")
        try:
            took = json.loads(p.stdout.strip().splitlines()[-1])
        except (ValueError, IndexError):
            sys.exit(f"GDAL: the COG copy of {src} printed no timing:\n{p.stdout}{p.stderr}")
        if not os.path.isfile(dst):
            sys.exit(f"GDAL: the COG copy of {src} wrote nothing")
        overviews = check_cog(src, dst, info)
        return wall, took["copy_s"], disk_bytes(dst), overviews
    finally:
        shutil.rmtree(work, ignore_errors=True)


def wrapped(name, width=26):
    """A file name over lines of `width` characters at most, broken after underscores."""
    lines, line = [], ""
    for part in re.findall(r"[^_]*_|[^_]+$", name):
        if line and len(line) + len(part) > width:
            lines.append(line)
            line = ""
        line += part
    return "\n".join(lines + [line])


def chart(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(7, 2.6 * len(rows)), 4.6))
    x = np.arange(len(rows))
    w = 0.36
    for off, side, label in ((-w / 2, "ours", "ours: patchwork ingest, drop to committed"),
                             (w / 2, "gdal", "GDAL: COG with overviews (rasterio)")):
        med = np.array([r[f"{side}_s"] for r in rows])
        err = np.array([[r[f"{side}_s"] - r[f"{side}_min_s"] for r in rows],
                        [r[f"{side}_max_s"] - r[f"{side}_s"] for r in rows]])
        ax.bar(x + off, med, w, yerr=err, capsize=3, label=label)
    for k, r in enumerate(rows):
        # The target, over our bar: half GDAL's time.
        ax.hlines(TARGET * r["gdal_s"], k - w, k, colors="k", linestyles="dashed", linewidth=1.2,
                  label=f"target for ours: {TARGET:g}× GDAL" if k == 0 else None)
        top = max(r["ours_max_s"], r["gdal_max_s"])
        ax.annotate(f"ours ÷ GDAL {r['ratio']:.2f}×", (k, top), textcoords="offset points", xytext=(0, 6),
                    ha="center", fontsize=8)
    ax.set_xticks(x, [f"{wrapped(r['file'])}\n{r['cols']}×{r['rows']} {r['dtype']}" for r in rows], fontsize=7)
    ax.set_xlim(-0.7, len(rows) - 0.3)
    ax.set_ylabel("median seconds (whole process; bars: min–max)")
    ax.set_ylim(0, max(max(r["ours_max_s"], r["gdal_max_s"]) for r in rows) * 1.25)
    ax.set_title(f"file to servable, median of {rows[0]['runs']}")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=3, frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--smoke", action="store_true", help="one run on a crop in tests/data, in seconds")
    ap.add_argument("--runs", type=int, help="runs of each side a file (5; 1 with --smoke)")
    ap.add_argument("--bin", default=os.path.join(REPO, "target", "release", "patchwork"))
    ap.add_argument("--data", default=DATA, help="the shared data folder (../shared/data beside the checkout)")
    ap.add_argument("--files", nargs="+", help="these files instead")
    ap.add_argument("--out", help="where the CSV and PNG go (docs/bench; a temporary folder with --smoke)")
    args = ap.parse_args(argv[1:])

    if args.files:
        sources = [os.path.abspath(f) for f in args.files]
    elif args.smoke:
        sources = SMOKE
    else:
        sources = [os.path.abspath(os.path.join(args.data, f)) for f in FULL]
    runs = args.runs or (1 if args.smoke else 5)
    if runs < 1:
        sys.exit("--runs must be at least 1")
    out_dir = args.out or (tempfile.mkdtemp(prefix="ingest-vs-gdal-smoke-") if args.smoke
                           else os.path.join(REPO, "docs", "bench"))
    for s in sources:
        if not os.path.isfile(s):
            sys.exit(f"missing {s}: the shared data folder is expected beside the checkout (or --data, "
                     "PATCHWORK_SHARED_DATA)")
    bin_path = os.path.abspath(args.bin)
    if not os.path.isfile(bin_path):
        sys.exit(f"missing {bin_path}: run `cargo build --release` first, or pass --bin")

    env = patchwork_env()
    tmp = tempfile.mkdtemp(prefix="ingest-vs-gdal-")
    rows = []
    try:
        for src in sources:
            info = describe(src)
            with open(src, "rb") as f:  # into the page cache, for both sides alike
                while f.read(1 << 24):
                    pass
            ours, ours_engine, gdal, gdal_copy, gdal_start = [], [], [], [], []
            for k in range(runs):
                wall, engine_s, samples, ours_bytes = run_ours(bin_path, src, tmp, env)
                ours.append(wall)
                ours_engine.append(engine_s)
                g_wall, copy_s, gdal_bytes, overviews = run_gdal(src, tmp, info)
                gdal.append(g_wall)
                gdal_copy.append(copy_s)
                gdal_start.append(g_wall - copy_s)
                print(f"{os.path.basename(src)} run {k + 1}/{runs}: ours {wall:.3f} s (its own {engine_s:.3f} s), "
                      f"GDAL {g_wall:.3f} s (copy {copy_s:.3f} s)", flush=True)
            n = info["cols"] * info["rows"]
            row = {"file": os.path.basename(src), "dtype": info["dtype"], "cols": info["cols"], "rows": info["rows"],
                   "samples": n, "runs": runs,
                   "ours_s": statistics.median(ours), "ours_min_s": min(ours), "ours_max_s": max(ours),
                   "ours_engine_s": statistics.median(ours_engine),
                   "gdal_s": statistics.median(gdal), "gdal_min_s": min(gdal), "gdal_max_s": max(gdal),
                   "gdal_copy_s": statistics.median(gdal_copy), "gdal_start_s": statistics.median(gdal_start),
                   "predictor": 3 if info["float"] else 2, "gdal_overviews": overviews,
                   "survey_samples": samples, "input_bytes": os.path.getsize(src),
                   "ours_bytes": ours_bytes, "gdal_bytes": gdal_bytes}
            row["ours_samples_per_s"] = n / row["ours_s"]
            row["gdal_samples_per_s"] = n / row["gdal_s"]
            row["ratio"] = row["ours_s"] / row["gdal_s"]
            rows.append(row)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    os.makedirs(out_dir, exist_ok=True)
    fields = ["file", "dtype", "cols", "rows", "samples", "runs", "ours_s", "ours_min_s", "ours_max_s",
              "ours_engine_s", "gdal_s", "gdal_min_s", "gdal_max_s", "gdal_copy_s", "gdal_start_s",
              "ours_samples_per_s", "gdal_samples_per_s", "ratio", "predictor", "gdal_overviews", "survey_samples",
              "input_bytes", "ours_bytes", "gdal_bytes"]
    with open(os.path.join(out_dir, "ingest_vs_gdal.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{r[k]:.4g}" if isinstance(r[k], float) else r[k]) for k in fields})
    chart(rows, os.path.join(out_dir, "ingest_vs_gdal.png"))

    print()
    print(f"{'smoke run: ' if args.smoke else ''}median of {runs} run(s) each, interleaved; whole processes "
          f"(ours: drop to committed; GDAL: python3 + rasterio COG copy), {os.cpu_count()} CPUs")
    print()
    print("| file | samples | ours s (min–max) | ours' own s | GDAL s (min–max) | GDAL copy s | GDAL start s | "
          "ours Msamples/s | GDAL Msamples/s | ours ÷ GDAL | ours MB | GDAL MB |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['file']} | {r['cols']}×{r['rows']} {r['dtype']} | {r['ours_s']:.3f} ({r['ours_min_s']:.3f}–"
              f"{r['ours_max_s']:.3f}) | {r['ours_engine_s']:.3f} | {r['gdal_s']:.3f} ({r['gdal_min_s']:.3f}–"
              f"{r['gdal_max_s']:.3f}) | {r['gdal_copy_s']:.3f} | {r['gdal_start_s']:.3f} | "
              f"{r['ours_samples_per_s'] / 1e6:.1f} | {r['gdal_samples_per_s'] / 1e6:.1f} | {r['ratio']:.2f} | "
              f"{r['ours_bytes'] / 1e6:.1f} | {r['gdal_bytes'] / 1e6:.1f} |")
    print()
    print(f"wrote {os.path.join(out_dir, 'ingest_vs_gdal.csv')} and ingest_vs_gdal.png")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
