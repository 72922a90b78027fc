use patchwork::index::geom::Aabb;
use patchwork::index::lod::IndexConfig;
use patchwork::model::accuracy::{self, AccuracySpec};
use patchwork::model::grid::Grid;
use patchwork::model::patch::PatchLayout;
use patchwork::model::survey::Survey;
use patchwork::terrain::Terrain;
use std::sync::Arc;
use std::time::Instant;

fn decimate(g: &Grid, k: usize, off: usize) -> Grid {
    let cols = (g.cols - off - 1) / k + 1;
    let rows = (g.rows - off - 1) / k + 1;
    let mut s = Vec::with_capacity(cols * rows);
    for r in 0..rows {
        for c in 0..cols {
            s.push(g.at(off + c * k, off + r * k));
        }
    }
    let mut geo = g.georef;
    geo.origin = g.georef.to_world(off as f64, off as f64);
    geo.step = [g.georef.step[0] * k as f64, g.georef.step[1] * k as f64];
    Grid::new(cols, rows, s, geo).unwrap()
}

fn main() {
    let path = std::env::args().nth(1).unwrap();
    let r = patchwork::read::read_raster(std::path::Path::new(&path), &Default::default()).unwrap();
    let full = r.into_grid().unwrap();
    let n = 1200.min(full.cols);
    let crop = {
        let mut s = Vec::new();
        for rr in 0..n {
            for c in 0..n {
                s.push(full.at(c, rr));
            }
        }
        Grid::new(n, n, s, full.georef).unwrap()
    };
    let layout = PatchLayout::default();
    for k in [1usize, 2, 3, 4, 8] {
        let g = if k == 1 {
            crop.clone()
        } else {
            decimate(&crop, k, 0)
        };
        let t = Survey::tiling_of(&g, &layout);
        let t0 = Instant::now();
        let e = accuracy::estimate(&g, &t, 2);
        let dt = t0.elapsed();
        let dev = if k == 1 {
            None
        } else {
            accuracy::deviation(&crop, &g)
        };
        let mut vals = e.kernels.values.clone();
        vals.sort_by(f64::total_cmp);
        println!("k={k}: alpha {:.2} rms2 {:.2} rms4 {:.2} est max {:.2} median {:.2}  measured {:?}  ({:?})", e.alpha, e.rms2, e.rms4, e.kernels.max(), vals[vals.len()/2], dev, dt);
    }
    // issue scenario 1: fine + 3x coarse copy, auto accuracy
    let fine =
        Arc::new(Survey::build(crop.clone(), AccuracySpec::Auto, Some(4326), layout).unwrap());
    let coarse = Arc::new(
        Survey::build(
            decimate(&crop, 3, 0),
            AccuracySpec::Auto,
            Some(4326),
            layout,
        )
        .unwrap(),
    );
    let mut t = Terrain::new(IndexConfig::default());
    t.insert(coarse.clone());
    t.insert(fine.clone());
    println!(
        "fine eps {:.2}, coarse eps {:.2}",
        fine.accuracy, coarse.accuracy
    );
    let b = fine.levels[0].world_bounds();
    let roi = Aabb::new(
        b.min[0] + 0.1 * b.width(),
        b.min[1] + 0.1 * b.height(),
        b.min[0] + 0.4 * b.width(),
        b.min[1] + 0.4 * b.height(),
    );
    for e in [0.0, 1.0, 3.0, 10.0, 30.0] {
        let ps = t.uniform(&roi, e);
        let nf = ps.iter().filter(|x| x.survey == fine.id).count();
        let nc = ps.iter().filter(|x| x.survey == coarse.id).count();
        let tile = t.tile(&roi, 256, 256, e);
        let grid = patchwork::resample::SampleGrid::uniform(&roi, 256, 256);
        let (mut mx, mut ss, mut cnt) = (0.0f64, 0.0, 0);
        for (p, z) in grid.points.iter().zip(&tile.heights) {
            if let Some(h) = fine.levels[0].bilinear(*p) {
                let d = (*z as f64 - h).abs();
                mx = mx.max(d);
                ss += d * d;
                cnt += 1;
            }
        }
        println!(
            "e={e}: {} patches ({nf} fine, {nc} coarse, {} other), max {:.2} rms {:.3}",
            ps.len(),
            ps.len() - nf - nc,
            mx,
            (ss / cnt as f64).sqrt()
        );
    }
}
