//! A flight through a view session (§6.4, Fig. 7): bytes per frame of the delta that the
//! server sends beside the whole cut that a stateless client would fetch, at two speeds.

use patchwork_core::geom::Aabb;
use patchwork_engine::{Camera, Cut, Engine};
use patchwork_server::api::ViewSession;
use patchwork_server::convert;
use patchwork_server::proto as pb;
use prost::Message;
use std::fmt::Write as _;
use std::path::Path;

/// One frame of a flight.
#[derive(Clone, Debug)]
pub struct FlightRow {
    /// `slow` or `fast`, as named in [`SPEEDS`].
    pub speed: &'static str,
    /// The frame's number in its flight, from 0.
    pub frame: usize,
    /// Patches of the frame's cut.
    pub patches: usize,
    /// Patches the step's messages add.
    pub added: usize,
    /// Patches the step's first message removes.
    pub removed: usize,
    /// The step's messages, as encoded on the wire.
    pub delta_bytes: usize,
    /// Every patch of the cut, as QueryPatches would send it.
    pub full_bytes: usize,
}

/// Ground covered per frame, as a fraction of the survey's diagonal: the slow flight crosses a
/// tenth of it in 200 frames, the fast one half.
pub const SPEEDS: [(&str, f64); 2] = [("slow", 0.1 / 200.0), ("fast", 0.5 / 200.0)];

/// Flies along the diagonal of `over`, 1,500 m up, looking ahead as the bench's view cuts do, for `frames` frames at each
/// speed, with 1 px of screen error on a 1024 px viewport.
pub fn fly(engine: &Engine, over: &Aabb, frames: usize) -> Result<Vec<FlightRow>, String> {
    let t = engine.snapshot();
    let mut rows = Vec::new();
    for (speed, step) in SPEEDS {
        let mut session = ViewSession::default();
        for k in 0..frames {
            let f = 0.15 + step * k as f64;
            let at = |g: f64| {
                [
                    over.min[0] + g * over.width(),
                    over.min[1] + g * over.height(),
                ]
            };
            let (e, l) = (at(f), at(f + 0.3));
            let v = pb::ViewCut {
                eye_x: e[0],
                eye_y: e[1],
                eye_z: 1500.0,
                look_x: l[0],
                look_y: l[1],
                look_z: 300.0,
                fov_deg: 60.0,
                viewport_px: 1024,
                pixel_error: 1.0,
            };
            let deltas = session.step(engine, &v).map_err(|e| e.to_string())?;
            let cut = Cut::View(Camera::try_from(&v).map_err(|e| e.to_string())?);
            let (_, ps) = engine.query(&cut).map_err(|e| e.to_string())?;
            let patches: Vec<pb::Patch> = ps
                .iter()
                .filter_map(|x| convert::patch(&t, x).ok().flatten())
                .collect();
            if k == 0 && speed == SPEEDS[0].0 {
                print_sizes(&patches);
            }
            let full_bytes = patches
                .into_iter()
                .map(|p| pb::PatchBatch { patches: vec![p] }.encoded_len())
                .sum();
            rows.push(FlightRow {
                speed,
                frame: k,
                patches: ps.len(),
                added: deltas.iter().map(|d| d.added.len()).sum(),
                removed: deltas[0].removed.len(),
                delta_bytes: deltas.iter().map(|d| d.encoded_len()).sum(),
                full_bytes,
            });
        }
        let (d, f): (usize, usize) = rows
            .iter()
            .filter(|r| r.speed == speed && r.frame > 0)
            .fold((0, 0), |(a, b), r| (a + r.delta_bytes, b + r.full_bytes));
        let n = (frames - 1).max(1) as f64;
        println!(
            "view session, {speed}: {:.1} kB a frame after the first, against {:.1} kB for the whole cut ({:.1}%)",
            d as f64 / n / 1e3,
            f as f64 / n / 1e3,
            100.0 * d as f64 / f.max(1) as f64
        );
    }
    Ok(rows)
}

/// Median bytes a patch takes on the wire, by kind and sample encoding.
fn print_sizes(patches: &[pb::Patch]) {
    let mut by: std::collections::BTreeMap<(i32, i32), Vec<usize>> = Default::default();
    for p in patches {
        by.entry((p.kind, p.encoding))
            .or_default()
            .push(p.encoded_len());
    }
    for ((kind, encoding), mut sizes) in by {
        sizes.sort_unstable();
        println!(
            "patch size, {:?} with {:?} samples: median {} B over {} patches",
            pb::PatchKind::try_from(kind).unwrap_or_default(),
            pb::SampleEncoding::try_from(encoding).unwrap_or_default(),
            sizes[sizes.len() / 2],
            sizes.len()
        );
    }
}

/// Writes the rows to `view_session.csv` under `out`.
pub fn write_csv(out: &Path, rows: &[FlightRow]) -> std::io::Result<()> {
    let mut s = String::from("speed,frame,patches,added,removed,delta_bytes,full_bytes\n");
    for r in rows {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{}",
            r.speed, r.frame, r.patches, r.added, r.removed, r.delta_bytes, r.full_bytes
        );
    }
    std::fs::write(out.join("view_session.csv"), s)
}
