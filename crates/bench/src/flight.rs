//! A flight through a view session (§6.4, Fig. 7): bytes per frame of the delta that the
//! server sends beside the whole cut that a stateless client would fetch, at two speeds.

use patchwork_core::geom::Aabb;
use patchwork_engine::{Camera, Cut, Engine};
use patchwork_server::api::{ViewClient, ViewSession};
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
            let v = camera(along(over, f), along(over, f + 0.3));
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

/// The point a fraction `g` along the diagonal of `over`.
fn along(over: &Aabb, g: f64) -> [f64; 2] {
    [
        over.min[0] + g * over.width(),
        over.min[1] + g * over.height(),
    ]
}

/// A camera at `e`, 1,500 m up, looking at `l` at 300 m (60°, 1024 px, 1 px of screen error).
fn camera(e: [f64; 2], l: [f64; 2]) -> pb::ViewCut {
    pb::ViewCut {
        eye_x: e[0],
        eye_y: e[1],
        eye_z: 1500.0,
        look_x: l[0],
        look_y: l[1],
        look_z: 300.0,
        fov_deg: 60.0,
        viewport_px: 1024,
        pixel_error: 1.0,
        ..Default::default()
    }
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

/// A client's cache and the server's prefetch (issue: view sessions that prefetch and
/// remember), for each flight: what a frame costs and how many frames were whole before they
/// were asked for.
#[derive(Clone, Debug)]
pub struct PrefetchRow {
    /// `slow`, `fast` or `turn` (on the spot, 3° a frame).
    pub flight: &'static str,
    /// The client's cache, bytes (0: none).
    pub cache_bytes: u64,
    /// The prefetch budget a frame, bytes (0: none).
    pub prefetch_bytes: u64,
    /// Bytes a frame after the first: median and mean.
    pub median_bytes: f64,
    /// See `median_bytes`.
    pub mean_bytes: f64,
    /// Frames after the first whose cut's patches the client all held, by id, before asking.
    pub complete: f64,
    /// Frames after the first whose step added no patch.
    pub quiet: f64,
}

/// A flight: the camera of each frame.
type Flight<'a> = Box<dyn Fn(usize) -> pb::ViewCut + 'a>;

/// The modes flown: none, a cache, a cache and prefetch.
const MODES: [(u64, u64); 3] = [(0, 0), (8 << 20, 0), (8 << 20, 128 << 10)];

/// Flies each flight in each mode of [`MODES`] through a session and a [`ViewClient`], as
/// [`fly`] does, checking each frame's cut against the client's.
pub fn fly_prefetch(
    engine: &Engine,
    over: &Aabb,
    frames: usize,
) -> Result<Vec<PrefetchRow>, String> {
    let at = |g: f64| along(over, g);
    let flights: [(&'static str, Flight<'_>); 3] = [
        (
            "slow",
            Box::new(|k| {
                let f = 0.15 + SPEEDS[0].1 * k as f64;
                camera(at(f), at(f + 0.3))
            }),
        ),
        (
            "fast",
            Box::new(|k| {
                let f = 0.15 + SPEEDS[1].1 * k as f64;
                camera(at(f), at(f + 0.3))
            }),
        ),
        (
            "turn",
            Box::new(|k| {
                let e = at(0.5);
                let a = (k as f64 * 3.0).to_radians();
                let r = 0.3 * over.width().min(over.height());
                camera(e, [e[0] + r * a.cos(), e[1] + r * a.sin()])
            }),
        ),
    ];
    let mut rows = Vec::new();
    for (flight, cam) in &flights {
        for (cache, prefetch) in MODES {
            let mut session = ViewSession::default();
            let mut client = ViewClient::new(cache);
            let (mut sizes, mut complete, mut quiet) = (Vec::new(), 0usize, 0usize);
            for k in 0..frames {
                let v = pb::ViewCut {
                    cache_bytes: cache,
                    prefetch_bytes: prefetch,
                    ..cam(k)
                };
                let cut = Cut::View(Camera::try_from(&v).map_err(|e| e.to_string())?);
                let (_, ps) = engine.query(&cut).map_err(|e| e.to_string())?;
                // Whole before asked: every patch of the cut already at the client, by id (its
                // samples and geometry); quiet: the step added nothing at all, not even a
                // patch held whose box in LOD space or fallback flag changed.
                if k > 0 && ps.iter().all(|x| client.has(x.id.0)) {
                    complete += 1;
                }
                let deltas = session.step(engine, &v).map_err(|e| e.to_string())?;
                if k > 0 && deltas.iter().all(|d| d.added.is_empty()) {
                    quiet += 1;
                }
                for (i, d) in deltas.iter().enumerate() {
                    client.apply(d, i == 0)?;
                }
                if client.cut.len() != ps.len()
                    || ps.iter().any(|x| !client.cut.contains_key(&x.id.0))
                {
                    return Err(format!(
                        "{flight} frame {k}: the client's cut is not the view cut"
                    ));
                }
                if k > 0 {
                    sizes.push(deltas.iter().map(|d| d.encoded_len()).sum::<usize>() as f64);
                }
            }
            let n = sizes.len().max(1) as f64;
            let mean = sizes.iter().sum::<f64>() / n;
            sizes.sort_by(f64::total_cmp);
            let row = PrefetchRow {
                flight,
                cache_bytes: cache,
                prefetch_bytes: prefetch,
                median_bytes: sizes.get(sizes.len() / 2).copied().unwrap_or(0.0),
                mean_bytes: mean,
                complete: complete as f64 / n,
                quiet: quiet as f64 / n,
            };
            println!(
                "view session, {flight}, cache {} kB, prefetch {} kB a frame: median {:.1} kB, mean {:.1} kB a frame, {:.0}% of frames whole before asked, {:.0}% adding nothing",
                cache >> 10,
                prefetch >> 10,
                row.median_bytes / 1e3,
                row.mean_bytes / 1e3,
                100.0 * row.complete,
                100.0 * row.quiet
            );
            rows.push(row);
        }
    }
    Ok(rows)
}

/// Writes the rows to `view_prefetch.csv` under `out`.
pub fn write_prefetch_csv(out: &Path, rows: &[PrefetchRow]) -> std::io::Result<()> {
    let mut s =
        String::from("flight,cache_bytes,prefetch_bytes,median_bytes,mean_bytes,complete,quiet\n");
    for r in rows {
        let _ = writeln!(
            s,
            "{},{},{},{:.0},{:.0},{:.4},{:.4}",
            r.flight,
            r.cache_bytes,
            r.prefetch_bytes,
            r.median_bytes,
            r.mean_bytes,
            r.complete,
            r.quiet
        );
    }
    std::fs::write(out.join("view_prefetch.csv"), s)
}
