//! The mesh triangulations against martini and delatin: the middle (2ⁿ + 1)² of each survey's
//! own samples (as a cut at e = 0 gives them), triangulated within each error by each
//! [`Method`] (adaptive border), counted in vertices and triangles and timed, with the largest
//! deviation measured. `bench/mesh_compare.py` meshes the same crops with pymartini and
//! pydelatin (voids filled, as they take none) and charts the three.

use super::timed;
use patchwork_core::mesh::{Border, Holes, Method, Options};
use std::fmt::Write as _;
use std::path::Path;

/// One crop triangulated by one method within one error.
#[derive(Clone, Debug)]
pub struct MeshRow {
    /// The file's name.
    pub dataset: String,
    /// The crop: its first column and row in the survey, and its side.
    pub c0: usize,
    /// The crop's first row in the survey.
    pub r0: usize,
    /// The crop's side, samples.
    pub size: usize,
    /// The triangulation method.
    pub method: Method,
    /// The error the mesh is made within, metres.
    pub error: f64,
    /// Vertices of the mesh.
    pub vertices: usize,
    /// Triangles of the mesh.
    pub triangles: usize,
    /// Median time of the triangulation over three runs, milliseconds.
    pub ms: f64,
    /// Largest deviation of the mesh from the crop's samples, metres.
    pub max_deviation: f64,
    /// Void samples in the crop, which the mesh leaves open.
    pub voids: usize,
}

/// Errors the meshes are made at.
pub const ERRORS: [f64; 6] = [1.0, 2.0, 5.0, 10.0, 20.0, 50.0];

/// The largest crop of 2ⁿ + 1 samples a side, at most `cap`, in the middle of each file.
pub fn run(
    files: &[std::path::PathBuf],
    cap: usize,
) -> Result<Vec<MeshRow>, Box<dyn std::error::Error>> {
    let mut rows = Vec::new();
    for f in files {
        let name = f
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let grid = patchwork_read::read_raster(f, &Default::default())?.into_grid()?;
        let side = grid.cols.min(grid.rows).min(cap);
        if side < 3 {
            continue;
        }
        let mut size = 3;
        while 2 * (size - 1) < side {
            size = 2 * (size - 1) + 1;
        }
        let (c0, r0) = ((grid.cols - size) / 2, (grid.rows - size) / 2);
        let crop = grid.window(c0, r0, size, size);
        let voids = crop.samples.iter().filter(|z| z.is_nan()).count();
        for (method, e) in [Method::Rtin, Method::Quadtree]
            .into_iter()
            .flat_map(|m| ERRORS.map(|e| (m, e)))
        {
            let (ms, m) = timed(3, || {
                let o = Options {
                    max_error: e,
                    border: Border::Adaptive,
                    method,
                    holes: Holes::Exact,
                };
                patchwork_core::mesh::triangulate(&crop.samples, size, size, &o)
            });
            println!(
                "{name} {method:?} mesh {size}² e = {e:>4} m: {} vertices, {} triangles, {ms:.1} ms, max deviation {:.3} m",
                m.grid.len(),
                m.triangles.len(),
                m.max_deviation
            );
            rows.push(MeshRow {
                dataset: name.clone(),
                c0,
                r0,
                size,
                method,
                error: e,
                vertices: m.grid.len(),
                triangles: m.triangles.len(),
                ms,
                max_deviation: m.max_deviation,
                voids,
            });
        }
    }
    Ok(rows)
}

/// Writes the rows to `rtin.csv` under `out`.
pub fn write_csv(out: &Path, rows: &[MeshRow]) -> std::io::Result<()> {
    let mut s = String::from(
        "dataset,c0,r0,size,method,error_m,vertices,triangles,ms,max_deviation_m,void_samples\n",
    );
    for r in rows {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{:.2},{:.4},{}",
            r.dataset,
            r.c0,
            r.r0,
            r.size,
            r.method.name(),
            r.error,
            r.vertices,
            r.triangles,
            r.ms,
            r.max_deviation,
            r.voids
        );
    }
    std::fs::write(out.join("rtin.csv"), s)
}
