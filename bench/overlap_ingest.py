"""Ingest into a store of many overlapping surveys: the seconds each file takes as the surveys
it overlaps pile up, for two builds of `patchwork` side by side in one run.

Usage: python3 bench/overlap_ingest.py --bin PATH [--base PATH] [--runs N] [--tiles K]
                                       [--side S] [--step T] [--data DIR] [--out DIR] [--smoke]

Every file that overlaps a survey already stored pays for the comparison of the two over the
overlap (placement, the tests of which claim is false, changed ground) on top of its own
modelling. This bench makes that the common case: a K × K lattice of squares of S samples,
T apart (so neighbours overlap by S − T samples), cut from the Copernicus GLO-30 tile of cell
N34W119 (float32) and the same squares from the NASADEM tile of the same cell (int16), two
independent surveys of the same ground. Each square of one source overlaps up to 8 of its own
neighbours and up to 9 of the other's. The files go in interleaved (Copernicus then NASADEM
at each square, row by row), all into one fresh store with one `patchwork ingest --data-dir
DIR FILE...`, so the last file meets a store of 2K² − 1 surveys.

Measured for each build, N times (3 by default), interleaved run by run (base, then the build,
then base again...), so that whatever else the machine does falls on both:
- the seconds `patchwork ingest` prints for each file (its own timer: read, model, index,
  compare with what it overlaps, commit), by its place in the order;
- the whole process's wall seconds.
After each run the store must list 2K² surveys, none failed (`patchwork surveys --json`).

Prints the median seconds a file in each fifth of the order, and the totals, for each build
and their ratio, and writes OUT/overlap_ingest.csv (run, build, position, file, seconds) and
OUT/overlap_ingest.png (the median seconds a file against the surveys already in the store).
OUT defaults to docs/bench. With --smoke: 2 × 2 squares of 120 samples from the committed
Copernicus crop, one run, its CSV and chart into a temporary folder. Needs release builds and
`python3 -m pip install -r bench/requirements.txt`.
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

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
DATA = os.environ.get("PATCHWORK_SHARED_DATA", os.path.join(REPO, "..", "shared", "data"))
SOURCES = ["Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif", "NASADEM_HGT_n34w119.tif"]
SMOKE = [os.path.join(REPO, "tests", "data", "copernicus_n34w119_crop.tif")]

# `patchwork ingest` prints, for each file: OUTCOME SOURCE SURVEY (N samples, S s).
INGESTED = re.compile(r"^(inserted|replaced)\s+(.+) ([0-9a-f]{16}) \((\d+) samples, ([0-9.]+) s\)\s*$", re.M)


def cut(sources, k, side, step, dest):
    """Writes the K × K squares of each source as deflated GeoTIFFs of the source's type,
    interleaved by square; returns their paths in that order. The lattice starts where the
    first source's grid does, shifted a little into it so that the squares hold no border."""
    import rasterio
    from rasterio.windows import Window

    paths = []
    opened = [rasterio.open(s) for s in sources]
    try:
        first = opened[0]
        x0, y0 = first.transform * (200, 200) if first.width > 200 + (k - 1) * step + side else first.transform * (0, 0)
        for r in range(k):
            for c in range(k):
                for j, ds in enumerate(opened):
                    # The same ground in each source: its window from the first's corner.
                    col, row = ~ds.transform * (x0, y0)
                    win = Window(round(col) + c * step, round(row) + r * step, side, side)
                    data = ds.read(1, window=win)
                    profile = ds.profile.copy()
                    profile.update(driver="GTiff", width=side, height=side, transform=ds.window_transform(win),
                                   compress="deflate", tiled=False, count=1)
                    for key in ("blockxsize", "blockysize", "interleave", "copy_src_overviews", "layout"):
                        profile.pop(key, None)
                    path = os.path.join(dest, f"s{r:02}{c:02}_{j}.tif")
                    with rasterio.open(path, "w", **profile) as out:
                        out.write(data, 1)
                    paths.append(path)
    finally:
        for ds in opened:
            ds.close()
    return paths


def patchwork_env():
    """The environment without PATCHWORK_* settings: the store opens with the defaults."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PATCHWORK_")}
    env["PATCHWORK_LOG"] = "warn"
    return env


def run_one(bin_path, files, tmp, env):
    """One ingest of every file into a fresh store: (wall seconds, [seconds a file])."""
    work = tempfile.mkdtemp(prefix="store-", dir=tmp)
    data = os.path.join(work, "data")
    try:
        t0 = time.perf_counter()
        p = subprocess.run([bin_path, "ingest", "--data-dir", data, *files], env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if p.returncode != 0:
            sys.exit(f"{bin_path} ingest exited {p.returncode}:\n{p.stdout}{p.stderr}")
        seen = {os.path.basename(m.group(2)): float(m.group(5)) for m in INGESTED.finditer(p.stdout)}
        missing = [f for f in files if os.path.basename(f) not in seen]
        if missing:
            sys.exit(f"{bin_path}: no time printed for {missing[:3]}:\n{p.stdout[-2000:]}")
        q = subprocess.run([bin_path, "surveys", "--data-dir", data, "--json"], env=env, capture_output=True, text=True)
        listed = json.loads(q.stdout)
        rows = listed["surveys"] if isinstance(listed, dict) else listed
        active = [s for s in rows if s.get("status", "active") not in ("failed", "deferred", "skipped")]
        if len(active) != len(files):
            sys.exit(f"{bin_path}: the store lists {len(active)} surveys of {len(files)} files")
        return wall, [seen[os.path.basename(f)] for f in files]
    finally:
        shutil.rmtree(work, ignore_errors=True)


def chart(medians, labels, path, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.4))
    for build, label in zip(medians, labels):
        ax.plot(range(len(medians[build])), medians[build], marker=".", linewidth=1, label=label)
    ax.set_xlabel("surveys already in the store")
    ax.set_ylabel("median seconds to ingest the file")
    ax.set_ylim(0, None)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", default=os.path.join(REPO, "target", "release", "patchwork"))
    ap.add_argument("--base", help="a second build to run beside it (the one before a change)")
    ap.add_argument("--base-label", default="before")
    ap.add_argument("--label", default="after")
    ap.add_argument("--runs", type=int)
    ap.add_argument("--tiles", type=int, default=4, help="squares a side (K)")
    ap.add_argument("--side", type=int, default=480, help="samples a side of a square (S)")
    ap.add_argument("--step", type=int, default=360, help="samples between squares (T)")
    ap.add_argument("--data", default=DATA)
    ap.add_argument("--out")
    ap.add_argument("--smoke", action="store_true")
    args = ap.parse_args(argv[1:])
    if args.smoke:
        sources, k, side, step, runs = SMOKE, 2, 120, 90, args.runs or 1
    else:
        sources = [os.path.join(args.data, s) for s in SOURCES]
        k, side, step, runs = args.tiles, args.side, args.step, args.runs or 3
    for s in sources:
        if not os.path.exists(s):
            sys.exit(f"missing input {s} (--data names the shared data folder)")
    builds = [("base", args.base, args.base_label)] if args.base else []
    builds.append(("build", args.bin, args.label))
    for _, b, _ in builds:
        if not os.access(b, os.X_OK):
            sys.exit(f"no build at {b} (cargo build --release)")
    tmp = tempfile.mkdtemp(prefix="overlap-ingest-")
    out = args.out or (tempfile.mkdtemp(prefix="overlap-ingest-out-") if args.smoke else os.path.join(REPO, "docs", "bench"))
    os.makedirs(out, exist_ok=True)
    env = patchwork_env()
    try:
        files = cut(sources, k, side, step, tmp)
        print(f"{len(files)} files of {side}² samples, {step} apart ({side - step} overlapping), "
              f"from {', '.join(os.path.basename(s) for s in sources)}")
        times = {name: [] for name, _, _ in builds}
        walls = {name: [] for name, _, _ in builds}
        rows = []
        for run in range(runs):
            for name, b, _ in builds:
                wall, each = run_one(b, files, tmp, env)
                times[name].append(each)
                walls[name].append(wall)
                for pos, (f, s) in enumerate(zip(files, each)):
                    rows.append([run, name, pos, os.path.basename(f), f"{s:.4f}"])
                print(f"run {run} {name}: {wall:.2f} s in all, {sum(each):.2f} s in the files")
        medians = {name: [statistics.median(t[pos] for t in times[name]) for pos in range(len(files))]
                   for name, _, _ in builds}
        n = len(files)
        fifth = max(1, n // 5)
        print("| files in the order | " + " | ".join(label for _, _, label in builds) + " |")
        print("|---|" + "---|" * len(builds))
        for q in range(0, n, fifth):
            cells = [f"{statistics.median(medians[name][q:q + fifth]):.3f} s" for name, _, _ in builds]
            print(f"| {q + 1}–{min(n, q + fifth)} | " + " | ".join(cells) + " |")
        totals = {name: statistics.median(walls[name]) for name, _, _ in builds}
        print("| whole process, median | " + " | ".join(f"{totals[name]:.2f} s" for name, _, _ in builds) + " |")
        if args.base:
            print(f"{args.label} ÷ {args.base_label}: {totals['build'] / totals['base']:.2f}× the whole process, "
                  f"{sum(medians['build']) / sum(medians['base']):.2f}× the files' own seconds")
        with open(os.path.join(out, "overlap_ingest.csv"), "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["run", "build", "position", "file", "seconds"])
            w.writerows(rows)
        chart(medians, [label for _, _, label in builds], os.path.join(out, "overlap_ingest.png"),
              f"{n} overlapping files ({side}², {side - step} samples of overlap), median of {runs} runs")
        print(f"wrote {out}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main(sys.argv)
