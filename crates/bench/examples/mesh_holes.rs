//! Meshes of whole surveys with voids, holes kept exact or drawn over within a reach (seed 004's
//! horizontal error): triangles, the time to make them (median of three), the largest vertical
//! deviation at measured samples and the farthest void drawn over. The surveys are meshed at
//! their own size (1201² and 200²: neither is 2ⁿ + 1), at their own samples, as a cut at
//! e = 0 gives them. Last, the middle 2049² of the Copernicus tile (no voids, a 2ⁿ + 1 grid),
//! the bench's own case, for the time each method takes where nothing is padded.
//!
//! cargo run --release -p patchwork-bench --example mesh_holes -- [DATA_DIR] [--baseline]
//!
//! DATA_DIR defaults to ../shared/data; `--baseline` runs only the Copernicus part.

use patchwork_core::index::query::Metric;
use patchwork_core::mesh::{triangulate, Border, Holes, Method, Options};
use std::path::PathBuf;
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let baseline_only = args.iter().any(|a| a == "--baseline");
    let data = PathBuf::from(
        args.iter()
            .find(|a| !a.starts_with("--"))
            .map_or("../shared/data", |a| a.as_str()),
    );
    println!("| survey | size | voids | method | e (m) | reach (cells) | triangles | ms | max deviation (m) | farthest void drawn (m) |");
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let surveys: &[&str] = if baseline_only {
        &[]
    } else {
        &["N44E005.hgt", "N44E005_big_hole.tif"]
    };
    for name in surveys {
        let raster = patchwork_read::read_raster(&data.join(name), &Default::default())
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        let grid = raster.into_grid().expect("a grid");
        let (cols, rows) = (grid.cols, grid.rows);
        let lat = grid.georef.origin[1] - grid.georef.step[1] * rows as f64 / 2.0;
        let scale = Metric::geographic(lat).scale;
        let cell = [
            grid.georef.step[0] * scale[0],
            grid.georef.step[1] * scale[1],
        ];
        let voids = grid.samples.iter().filter(|z| z.is_nan()).count();
        for method in [Method::Rtin, Method::Quadtree] {
            for e in [5.0, 20.0] {
                for cells in [0.0, 1.0, 3.0, 8.0] {
                    let reach = cells * cell[0].max(cell[1]);
                    let o = Options {
                        max_error: e,
                        border: Border::Shared,
                        method,
                        holes: if cells > 0.0 {
                            Holes::Reach { reach, cell }
                        } else {
                            Holes::Exact
                        },
                    };
                    let mut times = Vec::new();
                    let mut mesh = None;
                    for _ in 0..3 {
                        let t = Instant::now();
                        mesh = Some(triangulate(&grid.samples, cols, rows, &o));
                        times.push(t.elapsed().as_secs_f64() * 1e3);
                    }
                    times.sort_by(f64::total_cmp);
                    let m = mesh.expect("made");
                    println!(
                        "| {name} | {cols} × {rows} | {voids} | {} | {e} | {cells} | {} | {:.0} | {:.2} | {:.0} |",
                        method.name(),
                        m.triangles.len(),
                        times[1],
                        m.max_deviation,
                        m.max_reach
                    );
                }
            }
        }
    }
    println!();
    let name = "Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif";
    let raster = patchwork_read::read_raster(&data.join(name), &Default::default())
        .unwrap_or_else(|e| panic!("{name}: {e}"));
    let grid = raster.into_grid().expect("a grid");
    let side = 2049;
    let crop = grid.window((grid.cols - side) / 2, (grid.rows - side) / 2, side, side);
    for (method, e) in [
        (Method::Rtin, 20.0),
        (Method::Quadtree, 20.0),
        (Method::Quadtree, 5.0),
    ] {
        let o = Options {
            max_error: e,
            border: Border::Adaptive,
            method,
            holes: Holes::Exact,
        };
        let mut times = Vec::new();
        let mut count = 0;
        for _ in 0..3 {
            let t = Instant::now();
            count = triangulate(&crop.samples, side, side, &o).triangles.len();
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(f64::total_cmp);
        println!(
            "{name}, middle {side}², {}, {e} m, adaptive border: {count} triangles, {:.0} ms",
            method.name(),
            times[1]
        );
    }
}
