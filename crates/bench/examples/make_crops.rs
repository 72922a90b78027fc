//! Regenerates the real-terrain crops under `tests/data/` from the full files in a data folder.
//!
//! cargo run --release -p patchwork-bench --example make_crops -- ../shared/data tests/data

use patchwork_read::write_tiff::{write_geotiff_f32, write_geotiff_i16};
use patchwork_read::{read_raster, Raster, ReadLimits};
use std::path::{Path, PathBuf};

const SIZE: usize = 300;

/// The window of `SIZE` samples (on a coarse scan) with the largest height range: the most
/// demanding terrain for patch errors.
fn roughest(r: &Raster) -> (usize, usize) {
    let mut best = (0, 0, -1.0f32);
    for row in (0..r.rows - SIZE).step_by(150) {
        for col in (0..r.cols - SIZE).step_by(150) {
            let c = r.crop(col, row, SIZE, SIZE);
            let (lo, hi) = c
                .samples
                .iter()
                .filter(|v| !v.is_nan())
                .fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
            if hi - lo > best.2 {
                best = (col, row, hi - lo);
            }
        }
    }
    (best.0, best.1)
}

/// The window with the most voids, short of being mostly void.
fn holiest(r: &Raster) -> (usize, usize) {
    let mut best = (0, 0, 0usize);
    for row in (0..r.rows - SIZE).step_by(50) {
        for col in (0..r.cols - SIZE).step_by(50) {
            let n = r.crop(col, row, SIZE, SIZE).nodata_count();
            if n > best.2 && n < SIZE * SIZE / 4 {
                best = (col, row, n);
            }
        }
    }
    (best.0, best.1)
}

/// The `side`-sample window whose void fraction is nearest `fraction`.
fn voided(r: &Raster, side: usize, fraction: f64) -> (usize, usize) {
    let mut best = (0, 0, f64::INFINITY);
    for row in (0..r.rows - side).step_by(25) {
        for col in (0..r.cols - side).step_by(25) {
            let f = r.crop(col, row, side, side).nodata_count() as f64 / (side * side) as f64;
            if (f - fraction).abs() < best.2 {
                best = (col, row, (f - fraction).abs());
            }
        }
    }
    (best.0, best.1)
}

fn i16s(r: &Raster) -> Vec<i16> {
    r.samples
        .iter()
        .map(|&v| if v.is_nan() { -32768 } else { v as i16 })
        .collect()
}

fn main() {
    let args: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    let (src, dst) = match args.as_slice() {
        [a, b] => (a.clone(), b.clone()),
        _ => (PathBuf::from("../shared/data"), PathBuf::from("tests/data")),
    };
    let read = |name: &str| read_raster(&src.join(name), &ReadLimits::default()).expect(name);
    let out = |name: &str| -> PathBuf { Path::new(&dst).join(name) };

    let cop = read("Copernicus_DSM_COG_10_N34_00_W119_00_DEM.tif");
    let (col, row) = roughest(&cop);
    let c = cop.crop(col, row, SIZE, SIZE);
    write_geotiff_f32(
        &out("copernicus_n34w119_crop.tif"),
        SIZE,
        SIZE,
        &c.samples,
        c.geotransform,
        c.crs.crs.as_ref(),
        None,
    )
    .unwrap();
    // NASADEM is co-registered with Copernicus; offset its crop so the pair overlaps in part.
    let nasa = read("NASADEM_HGT_n34w119.tif");
    let n = nasa.crop(col + 120, row + 80, SIZE, SIZE);
    write_geotiff_i16(
        &out("nasadem_n34w119_crop.tif"),
        SIZE,
        SIZE,
        &i16s(&n),
        n.geotransform,
        n.crs.crs.as_ref(),
        Some(-32768.0),
    )
    .unwrap();
    println!(
        "Copernicus crop at col {col}, row {row}; NASADEM at col {}, row {}",
        col + 120,
        row + 80
    );

    let hgt = read("N44E005.hgt");
    let (col, row) = holiest(&hgt);
    let h = hgt.crop(col, row, SIZE, SIZE);
    write_geotiff_i16(
        &out("srtm_n44e005_voids_crop.tif"),
        SIZE,
        SIZE,
        &i16s(&h),
        h.geotransform,
        h.crs.crs.as_ref(),
        Some(-32768.0),
    )
    .unwrap();
    println!(
        "N44E005 crop at col {col}, row {row} with {} voids",
        h.nodata_count()
    );

    // Three quarters void: what is left of the ground below 1,000 m, in pieces.
    let holes = read("N44E005_big_hole.tif");
    let side = 200;
    let (col, row) = voided(&holes, side, 0.76);
    let v = holes.crop(col, row, side, side);
    write_geotiff_i16(
        &out("srtm_n44e005_big_hole_crop.tif"),
        side,
        side,
        &i16s(&v),
        v.geotransform,
        v.crs.crs.as_ref(),
        Some(-32768.0),
    )
    .unwrap();
    println!(
        "N44E005_big_hole crop at col {col}, row {row}: {:.1}% void",
        100.0 * v.nodata_count() as f64 / (side * side) as f64
    );
}
