"""Patchwork's cuts beside the meshes of martini (RTIN) and delatin (greedy Delaunay) at the same
maximum error, on the same surveys.

Usage: python3 bench/mesh_compare.py OUT_DIR [--meshes-only [SURVEY ...]]

Reads what `patchwork-bench` wrote in OUT_DIR: the surveys it used (tiles/manifest.json) and
variants.csv, each survey's uniform cut at every error for each mipmap filter and patch kind, with the
surveys taken as exact so that e is the largest deviation from the samples' surface. For each
survey and error, martini and delatin triangulate the same samples within the same maximum
error; their vertex counts go beside our samples shipped. Writes OUT_DIR/meshes.csv and the
charts samples_vs_error.png and variants_time.png. Then the crops of rtin.csv, which our mesh
triangulations made at each error, go to martini and delatin too: rtin_compare.csv,
mesh_triangles.png and mesh_time.png.

With --meshes-only, only that last comparison runs again, from the rtin.csv already there and
the surveys named (by default those of tiles/manifest.json): `patchwork-bench --meshes-only`.

Neither mesher takes voids: they get the survey with voids filled from their neighbours, and
martini a grid padded by repeating the edge to 2^n + 1 samples a side (vertices in the padding
are not counted). Their error is measured at the samples, as ours is.
"""

import csv
import json
import sys
import time
from pathlib import Path

import numpy as np
import rasterio


def heights(path):
    """A survey's samples as float32, voids filled by repeated means of valid neighbours."""
    with rasterio.open(path) as ds:
        z = ds.read(1).astype(np.float32)
        if ds.nodata is not None:
            z[z == ds.nodata] = np.nan
    while np.isnan(z).any():
        p = np.pad(z, 1, mode="edge")
        near = np.stack([p[:-2, 1:-1], p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]])
        n = (~np.isnan(near)).sum(axis=0)
        mean = np.where(n > 0, np.nansum(near, axis=0) / np.maximum(n, 1), np.nan)
        z = np.where(np.isnan(z), mean, z).astype(np.float32)
    return z


def martini_counts(z, errors):
    from pymartini import Martini

    h, w = z.shape
    size = 1 << int(np.ceil(np.log2(max(h, w) - 1)))
    padded = np.pad(z, ((0, size + 1 - h), (0, size + 1 - w)), mode="edge")
    t0 = time.perf_counter()
    # pymartini indexes terrain[x * size + y]: hand it the transpose, row-major.
    tile = Martini(size + 1).create_tile(np.ascontiguousarray(padded.T).ravel())
    build = time.perf_counter() - t0
    out = {}
    for e in errors:
        t0 = time.perf_counter()
        vertices, _ = tile.get_mesh(e)
        ms = (time.perf_counter() - t0 + build) * 1e3
        v = vertices.reshape(-1, 2)
        out[e] = (int(((v[:, 0] < w) & (v[:, 1] < h)).sum()), ms)
    return out


def delatin_counts(z, errors):
    from pydelatin import Delatin

    h, w = z.shape
    out = {}
    for e in errors:
        t0 = time.perf_counter()
        d = Delatin(z, width=w, height=h, max_error=e)
        out[e] = (len(d.vertices), (time.perf_counter() - t0) * 1e3)
    return out


# Meshes with more triangles than this are not measured: matplotlib's point location needs
# tens of GB for millions of triangles.
MEASURE_TRIANGLES = 400_000


def measured_error(z, vertices, triangles):
    """The largest |mesh − z| over every sample of z, the mesh's vertices given as (x, y)
    sample positions: the mesh interpolated linearly at every sample. NaN for a mesh of more
    than MEASURE_TRIANGLES triangles."""
    from matplotlib.tri import LinearTriInterpolator, Triangulation

    if len(np.asarray(triangles).reshape(-1, 3)) > MEASURE_TRIANGLES:
        return float("nan")
    h, w = z.shape
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 2)
    tri = Triangulation(v[:, 0], v[:, 1], np.asarray(triangles, dtype=np.int64).reshape(-1, 3))
    heights = z[v[:, 1].astype(int), v[:, 0].astype(int)]
    ys, xs = np.mgrid[0:h, 0:w]
    at = LinearTriInterpolator(tri, heights)(xs.ravel().astype(np.float64), ys.ravel().astype(np.float64))
    return float(np.nanmax(np.abs(np.asarray(at).reshape(h, w) - z)))


def delatin_xy(d, rows):
    """delatin's vertices as (column, row): its y runs north, from the last row."""
    v = np.asarray(d.vertices)
    return np.column_stack([v[:, 0], (rows - 1) - v[:, 1]])


def rtin_compare(out, sources):
    """The crops of rtin.csv meshed by martini and delatin at the same errors, beside ours:
    rtin_compare.csv and the charts mesh_triangles.png and mesh_time.png."""
    ours = list(csv.DictReader(open(out / "rtin.csv")))
    rows = []
    for name in dict.fromkeys(r["dataset"] for r in ours):
        mine = [r for r in ours if r["dataset"] == name]
        c0, r0, size = (int(mine[0][k]) for k in ("c0", "r0", "size"))
        path = next(s for s in sources if Path(s).name == name)
        z = np.ascontiguousarray(heights(path)[r0:r0 + size, c0:c0 + size])
        errors = sorted({float(r["error_m"]) for r in mine})
        for r in mine:
            label = {"rtin": "patchwork RTIN", "quadtree": "patchwork quadtree"}[r["method"]]
            rows.append({"dataset": name, "method": label, "error_m": float(r["error_m"]),
                         "vertices": int(r["vertices"]), "triangles": int(r["triangles"]), "ms": float(r["ms"]),
                         "max_deviation_m": float(r["max_deviation_m"])})
        from pymartini import Martini
        from pydelatin import Delatin

        t0 = time.perf_counter()
        tile = Martini(size).create_tile(np.ascontiguousarray(z.T).ravel())
        build = time.perf_counter() - t0
        for e in errors:
            t0 = time.perf_counter()
            v, t = tile.get_mesh(e)
            ms = (time.perf_counter() - t0 + build) * 1e3
            # martini's vertices are (x, y) of the transposed grid it was given: (row, column).
            v = np.asarray(v).reshape(-1, 2)[:, ::-1]
            t = np.asarray(t).reshape(-1, 3)
            rows.append({"dataset": name, "method": "martini", "error_m": e, "vertices": len(v),
                         "triangles": len(t), "ms": ms, "max_deviation_m": measured_error(z, v, t)})
            t0 = time.perf_counter()
            d = Delatin(z, width=size, height=size, max_error=e)
            ms = (time.perf_counter() - t0) * 1e3
            rows.append({"dataset": name, "method": "delatin", "error_m": e, "vertices": len(d.vertices),
                         "triangles": len(d.triangles), "ms": ms,
                         "max_deviation_m": measured_error(z, delatin_xy(d, size), d.triangles)})
        for r in rows[-(len(mine) + 2 * len(errors)):]:
            print(f"{name} {size}² {r['method']:>15} e = {r['error_m']:>4} m: {r['triangles']} triangles, "
                  f"{r['ms']:.1f} ms, max deviation {r['max_deviation_m']:.2f} m")
    with open(out / "rtin_compare.csv", "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=["dataset", "method", "error_m", "vertices", "triangles", "ms", "max_deviation_m"])
        wr.writeheader()
        for r in rows:
            wr.writerow({**r, "ms": f"{r['ms']:.2f}", "max_deviation_m": f"{r['max_deviation_m']:.4f}"})

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    datasets = list(dict.fromkeys(r["dataset"] for r in rows))
    for what, ylabel, fname in (("triangles", "triangles", "mesh_triangles.png"), ("ms", "ms (build and extract)", "mesh_time.png")):
        fig, axes = plt.subplots(1, len(datasets), figsize=(5.5 * len(datasets), 4.5), squeeze=False)
        for ax, name in zip(axes[0], datasets):
            for method, style in (("patchwork RTIN", "o-"), ("patchwork quadtree", "D-"), ("martini", "s--"), ("delatin", "^:")):
                pts = [r for r in rows if r["dataset"] == name and r["method"] == method]
                ax.plot([r["error_m"] for r in pts], [r[what] for r in pts], style, label=method)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("maximum error (m)")
            ax.set_ylabel(ylabel)
            size = next(int(r["size"]) for r in ours if r["dataset"] == name)
            ax.set_title(f"{name}, middle {size}²", fontsize=10)
            ax.grid(True, which="both", alpha=0.3)
        axes[0][0].legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / fname, dpi=90)
        plt.close(fig)


def main(argv):
    if len(argv) < 2 or (argv[2:] and argv[2] != "--meshes-only"):
        sys.exit(__doc__)
    out = Path(argv[1])
    if argv[3:]:
        sources = argv[3:]
    else:
        sources = json.loads((out / "tiles" / "manifest.json").read_text())["sources"]
    if argv[2:]:
        # Only the comparison of the mesh triangulations (rtin.csv), again.
        rtin_compare(out, sources)
        return
    rows = list(csv.DictReader(open(out / "variants.csv")))
    datasets = list(dict.fromkeys(r["dataset"] for r in rows))
    mesh_rows = []
    for name in datasets:
        path = next(s for s in sources if Path(s).name == name)
        z = heights(path)
        # At e = 0 both keep every sample; below 1 m on a 16-bit survey the same.
        errors = sorted({float(r["error_m"]) for r in rows if r["dataset"] == name and float(r["error_m"]) >= 1})
        for method, counts in (("martini", martini_counts(z, errors)), ("delatin", delatin_counts(z, errors))):
            for e, (n, ms) in counts.items():
                mesh_rows.append({"dataset": name, "method": method, "error_m": e, "vertices": n, "ms": f"{ms:.2f}"})
                print(f"{name} {method:>8} e = {e:>5} m: {n} vertices, {ms:.1f} ms")
    with open(out / "meshes.csv", "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=["dataset", "method", "error_m", "vertices", "ms"])
        wr.writeheader()
        wr.writerows(mesh_rows)
    charts(out, datasets, rows, mesh_rows)
    rtin_compare(out, sources)


def charts(out, datasets, rows, mesh_rows):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for what, ylabel, fname in (
        ("samples", "values shipped (samples or vertices)", "samples_vs_error.png"),
        ("time", "ms (cut + 512² tile; mesh build)", "variants_time.png"),
    ):
        fig, axes = plt.subplots(1, len(datasets), figsize=(5.5 * len(datasets), 4.5), squeeze=False)
        for ax, name in zip(axes[0], datasets):
            ours = [r for r in rows if r["dataset"] == name]
            for flt, kind in dict.fromkeys((r["filter"], r["kind"]) for r in ours):
                pts = [
                    r
                    for r in ours
                    if (r["filter"], r["kind"]) == (flt, kind) and float(r["error_m"]) > 0
                ]
                x = [float(r["error_m"]) for r in pts]
                if what == "samples":
                    y = [int(r["samples"]) for r in pts]
                else:
                    y = [float(r["query_ms"]) + float(r["resample_ms"]) for r in pts]
                style = "o-" if kind == "bilinear" else "^:"
                ax.plot(x, y, style, label=f"{kind} patches, {flt} mipmap")
            for method in ("martini", "delatin"):
                pts = [m for m in mesh_rows if m["dataset"] == name and m["method"] == method]
                x = [m["error_m"] for m in pts]
                y = [m["vertices"] if what == "samples" else float(m["ms"]) for m in pts]
                ax.plot(x, y, "s--", label=method)
            if what == "samples":
                ax.axhline(int(ours[0]["raw_samples"]), color="black", lw=1, label="the survey's samples")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("maximum error e (m)")
            ax.set_ylabel(ylabel)
            ax.set_title(name, fontsize=10)
            ax.grid(True, which="both", alpha=0.3)
        axes[0][0].legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / fname, dpi=90)
        plt.close(fig)


if __name__ == "__main__":
    main(sys.argv)
