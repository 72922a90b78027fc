//! A region of the store at a resolution as one cloud-optimized GeoTIFF: the full level
//! resampled block by block at its pixels' centres (the cut, heights and CRS as a GeoTIFF
//! tile of `patchwork tile` gives them, voids kept as nodata), and overviews of it averaged
//! down as GDAL's `average` makes them, in the layout of [`patchwork_read::write_cog`].

use super::{io, ExportError, Progress};
use patchwork_core::crs::Crs;
use patchwork_core::geom::Aabb;
use patchwork_core::resample::Cancel;
use patchwork_engine::{
    Backend, Ctx, Cut, Engine, EngineError, Heights, Metres, Region, TileRequest,
};
use patchwork_read::write_cog::{self, Level, BLOCK};
use rayon::prelude::*;
use std::path::Path;

/// The samples a COG export holds at most: 2²⁸, a GiB of float32 at full resolution, which
/// this process holds while it writes the overviews.
pub const MOST_SAMPLES: u64 = 1 << 28;

/// What to write.
#[derive(Clone, Debug)]
pub struct CogPlan {
    /// The region, in `crs`: its west and north edges are the raster's, and its east and
    /// south ones are moved out to a whole pixel.
    pub roi: Aabb,
    /// The CRS of the region and of the raster; the store's where None.
    pub crs: Option<Crs>,
    /// A pixel's side, in the CRS's units.
    pub resolution: f64,
    /// The cut's error, metres.
    pub error: f64,
    /// What the heights are measured from.
    pub heights: Heights,
}

/// What a COG export wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct CogSummary {
    /// Columns and rows of the full level.
    pub size: (usize, usize),
    /// The levels, the full one with its overviews.
    pub levels: usize,
    /// The file's bytes.
    pub file_bytes: u64,
    /// Samples with no data.
    pub voids: u64,
    /// The largest error the heights' frame conversion may have added, metres.
    pub frame_error_m: f64,
}

/// The value the file gives voids.
const NODATA: f64 = -9999.0;

/// Writes `plan` to `out`, telling `progress` of the blocks of the full level as they are
/// made (in tiles of [`BLOCK`]²).
pub fn write(
    engine: &Engine,
    plan: &CogPlan,
    out: &Path,
    cancel: &Cancel,
    progress: &mut dyn FnMut(Progress),
) -> Result<CogSummary, ExportError> {
    let bad = |m: String| ExportError::Options(m);
    let r = plan.resolution;
    let b = plan.roi;
    if !(r.is_finite() && r > 0.0) {
        return Err(bad(format!("the resolution must be above 0, got {r}")));
    }
    if !(b.is_valid() && b.width() > 0.0 && b.height() > 0.0) {
        return Err(bad(format!("the region {b:?} holds no area")));
    }
    let crs = match &plan.crs {
        Some(c) => c.clone(),
        None => engine
            .crs()
            .ok_or_else(|| bad("the store holds no survey: nothing to export".into()))?,
    };
    // Whole pixels, the region's west and north edges kept.
    let w = (b.width() / r - 1e-9).ceil().max(1.0);
    let h = (b.height() / r - 1e-9).ceil().max(1.0);
    if w * h > MOST_SAMPLES as f64 {
        return Err(bad(format!(
            "{w} × {h} samples is more than the {MOST_SAMPLES} one COG export holds: export a \
             smaller region, or at a coarser resolution"
        )));
    }
    let (w, h) = (w as usize, h as usize);
    engine
        .can_give(&plan.heights)
        .map_err(|e| bad(e.to_string()))?;
    let error = Metres::error(plan.error).map_err(|e| bad(e.to_string()))?;
    let own = (engine.crs().as_ref() != Some(&crs)).then(|| crs.clone());
    let (across, down) = (w.div_ceil(BLOCK), h.div_ceil(BLOCK));
    let mut full = vec![f32::NAN; w * h];
    let mut p = Progress {
        total: (across * down) as u64,
        ..Progress::default()
    };
    progress(p);
    let mut frame_error_m = 0.0f64;
    // A row of blocks at a time: the blocks of a row side by side on the cores.
    for by in 0..down {
        if cancel.is_cancelled() {
            return Err(ExportError::Cancelled);
        }
        let made: Vec<(usize, usize, usize, Vec<f32>, f64)> = (0..across)
            .into_par_iter()
            .map(|bx| {
                let (x0, y0) = (bx * BLOCK, by * BLOCK);
                let (bw, bh) = (BLOCK.min(w - x0), BLOCK.min(h - y0));
                let region = Aabb::new(
                    b.min[0] + x0 as f64 * r,
                    b.max[1] - (y0 + bh) as f64 * r,
                    b.min[0] + (x0 + bw) as f64 * r,
                    b.max[1] - y0 as f64 * r,
                );
                let fail = |source: EngineError| ExportError::Tile {
                    z: 0,
                    x: bx as u32,
                    y: by as u32,
                    source: Box::new(source),
                };
                let cut = Cut::uniform(
                    own.clone(),
                    Region::new(region).map_err(|e| fail(e.into()))?,
                    error,
                );
                let req = TileRequest::new(cut, bw as u32, bh as u32, Backend::Auto)
                    .map_err(|e| fail(e.into()))?
                    .with_heights(plan.heights.clone());
                let (tile, _, frame) = engine.tile(&req, Ctx::until(cancel)).map_err(fail)?;
                Ok((x0, bw, bh, tile.heights, frame.error_m))
            })
            .collect::<Result<_, ExportError>>()?;
        for (x0, bw, bh, heights, fe) in made {
            frame_error_m = frame_error_m.max(fe);
            for j in 0..bh {
                let row = (by * BLOCK + j) * w + x0;
                full[row..row + bw].copy_from_slice(&heights[j * bw..(j + 1) * bw]);
            }
            p.done += 1;
        }
        progress(p);
    }
    let voids = full.iter().filter(|v| v.is_nan()).count() as u64;
    let levels = write_cog::pyramid(Level {
        width: w,
        height: h,
        samples: full,
    });
    let gt = [b.min[0], r, 0.0, b.max[1], 0.0, -r];
    let tmp = out.with_file_name(format!(
        ".{}.tmp",
        out.file_name()
            .map_or("export".into(), |n| n.to_string_lossy())
    ));
    write_cog::write_cog_f32(&tmp, &levels, gt, Some(&crs), NODATA).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        ExportError::Archive {
            path: out.to_path_buf(),
            why: e.to_string(),
        }
    })?;
    std::fs::rename(&tmp, out).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        io(out)(e)
    })?;
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        // The rename itself is durable only once the folder is.
        let _ = std::fs::File::open(dir).and_then(|d| d.sync_all());
    }
    let file_bytes = std::fs::metadata(out).map_err(io(out))?.len();
    Ok(CogSummary {
        size: (w, h),
        levels: levels.len(),
        file_bytes,
        voids,
        frame_error_m,
    })
}
