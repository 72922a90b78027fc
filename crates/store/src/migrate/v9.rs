//! The edge patch record as versions 3 to 9 wrote it (`e/`): a frozen copy, its grid whole
//! (every sample of its window), so that the step that reads it (9 → 10) keeps doing so
//! whatever the record becomes. Its other parts are the current forms', unchanged since
//! version 4.

use crate::form::{CellRect, Edge, EdgeGrid, Georef};
use patchwork_core::model::edge;
use serde::{Deserialize, Serialize};

/// An edge patch's grid of versions 3 to 9: every sample of its window.
#[derive(Serialize, Deserialize)]
pub struct EdgeGridV9 {
    pub(super) cols: usize,
    pub(super) rows: usize,
    pub(super) heights: Vec<f32>,
    pub(super) flags: Vec<u8>,
    pub(super) georef: Georef,
}

/// An edge patch record of versions 3 to 9.
#[derive(Serialize, Deserialize)]
pub struct EdgeV9 {
    pub(super) owner: u64,
    pub(super) id: u64,
    pub(super) tile: [i64; 2],
    pub(super) members: Vec<u64>,
    pub(super) kernel: CellRect,
    pub(super) window: CellRect,
    pub(super) kernel_cells: u32,
    pub(super) flat: f64,
    pub(super) centre: [f64; 2],
    pub(super) half: [f64; 2],
    pub(super) valid: Vec<[f64; 4]>,
    pub(super) error: f64,
    pub(super) grid: EdgeGridV9,
}

impl EdgeV9 {
    /// The same record as version 10 writes it: the samples at its edge cells' corners, and
    /// the window's slope measured on the whole grid as the build does.
    pub fn now(self) -> Result<Edge, String> {
        let g = self.grid;
        if g.heights.len() != g.cols * g.rows || g.flags.len() != g.cols * g.rows {
            return Err(format!(
                "edge patch {:016x}: {} heights and {} flags for {} × {} samples",
                self.id,
                g.heights.len(),
                g.flags.len(),
                g.cols,
                g.rows
            ));
        }
        let sparse =
            edge::EdgeGrid::from_dense(g.cols, g.rows, &g.heights, &g.flags, g.georef.into());
        Ok(Edge {
            owner: self.owner,
            id: self.id,
            tile: self.tile,
            members: self.members,
            kernel: self.kernel,
            window: self.window,
            kernel_cells: self.kernel_cells,
            flat: self.flat,
            centre: self.centre,
            half: self.half,
            valid: self.valid,
            error: self.error,
            grid: EdgeGrid {
                cols: g.cols,
                rows: g.rows,
                kept: sparse.kept().to_vec(),
                heights: sparse.kept_heights().to_vec(),
                flags: sparse.kept_flags().to_vec(),
                slope: sparse.slope,
                georef: g.georef,
            },
        })
    }
}
