//! Formula 1 and the accurate blend on a GPU through wgpu: the sums of [`cpu::blend`]
//! evaluated by a compute shader
//! (`resample.wgsl`), one workgroup per [`BLOCK`] × [`BLOCK`] block of output samples, each
//! visiting only the patches that meet its block (§7.3).
//!
//! A request is in two parts. [`prepare`] is the CPU's: the patches binned into squares of
//! [`SUPER`] × [`SUPER`] blocks (by bisection along a north-up grid's axes), what the request
//! adds to each patch (its first sample from the request's origin, its rank and weight: 32
//! bytes), and what the positions are made from (for a north-up grid its axes, a column's x
//! and a row's y, not a point a sample: 64 KB for a 2048² tile where points took 64 MB; for
//! a view two points a row; for a grid of another CRS, and for the planes of surveys of other
//! CRSs, the lattices of [`positions`], kept on the device).
//! [`GpuResampler::submit`] is the device's: the patches and lattice nodes not yet on it, then
//! up to three dispatches, the first making the positions that are not axes, the second
//! listing each block's patches from its square's bin (binning on the device, which the paper
//! leaves to future work), the third blending, and 4 bytes a sample read back, through
//! buffers kept from one request to the next. Only the second part needs the device, so a
//! daemon prepares outside its lock.
//!
//! Patches live on the device: their samples in one storage buffer, an append-only arena,
//! and their records (grid axes, window, kernel, base: 144 bytes) in a table beside it, both
//! keyed by [`PatchId`], so a request that shares patches with an earlier one uploads only
//! the new ones, and a warm request uploads 32 bytes a patch and its bin entries. When the
//! arena would grow past its byte budget both are emptied and refilled with the current
//! request's patches: crude, but it never fragments and the next requests refill it.
//!
//! *Positions.* Geographic coordinates near −119° have an f32 spacing of 7.6·10⁻⁶° (≈ 0.8 m),
//! so world positions never reach the GPU as f32. The CPU subtracts a tile origin in f64 and
//! sends the axes (or rows, or lattice nodes) and each patch's first sample, and keeps each
//! patch's axes (divided by the spacing) on the device, as unevaluated sums hi + lo of two
//! f32s, exact to u² relative. The shader forms positions and grid coordinates with
//! error-free sums and products (`two_sum`, and `two_prod` by Dekker's halves, as lavapipe
//! evaluates `fma` unfused), each step behind an integer barrier (`opaque`): a driver that
//! treats float arithmetic as real arithmetic (lavapipe's LLVM does) would otherwise reduce
//! every error term to 0 and leave the coordinates at f32, 10⁻⁷ of the tile, as it did here
//! until the barrier went in (the GPU was then up to 1.6 mm off the CPU; it is 0.24 mm now).
//! So they carry about 48 bits: for a tile L cells across (relative to the tile origin), the
//! error is below ~4u²·L ≈ 10⁻¹³·L cells, under 10⁻⁹ cells for any tile under 10⁴ level cells.
//! The cell, the position inside it and the side of every window, kernel and edge test are
//! then those of the f64 path, and a point within [`SNAP`](patchwork_core::geom::SNAP) = 10⁻⁹ cells of a grid line
//! is put on it by both paths (without that, f64 noise of 10⁻¹⁵ would pick the side of a void
//! edge a pixel-centre grid lands on exactly). The f32 that remains is the fraction f in the
//! cell and the weight argument t, each rounded once: δf, δt ≤ u.
//!
//! *Heights.* f32 holds 8,000 m only to 0.5 mm (its spacing there is 0.98 mm), so absolute
//! heights never reach the GPU either. Each patch's samples are stored relative to the
//! patch's base b (the mid-range of its uploaded samples, an f32); the subtraction rounds by
//! ≤ u·R/2 where R is the patch's relief. The shader blends relative to the base b₀ of the
//! first patch that contributes at the point and adds b₀ back last, in one f32 addition: the
//! sum of two f32s correctly rounded, which is what the CPU's f64 sum rounded to f32 gives, so
//! only 4 bytes a sample come back. Until then every f32 quantity is a height *difference*. With n contributing patches, D the
//! largest |z_k − b₀| among them, Δ the largest difference between two of them at the point,
//! and S the largest height change across one cell:
//!
//! - the bilinear interpolation rounds by ≤ 2u·R plus S·δf ≤ u·S;
//! - rebasing z + (b_k − b₀) by ≤ 2u·D;
//! - the weighted mean by ≤ (n + 2)·u·D, and the weights' δt moves it by ≤ 4n·u·Δ·Σnorm/Σw,
//!   where Σw ≥ Σnorm/64 because a covered point lies in some kernel (|t| ≤ 7/8);
//!
//! so |Δh| ≤ u·[(n + 6)·D + 2R + S + 256·n·Δ] before the final rounding to f32 on each side,
//! which adds at most one f32 spacing of the height: 0.98 mm at 8,192–16,384 m, 0.49 mm below.
//! D, R, S and Δ are local reliefs and disagreements, not altitudes: with n ≤ 8, D, R ≤ 2,000
//! m and Δ ≤ 100 m the rounding term is ≤ 0.03 mm, so heights under 9,000 m agree to within one
//! f32 spacing, ≤ 0.98 mm.
//!
//! *Edge patches* scale their weight by a ramp that falls from 1 to 0 over half a cell at the
//! edge of a survey's pixels: a slope of 2 per cell, 32 times that of a tent 16 cells wide. The
//! rounding of a point's grid position then moves such a weight by up to ~10⁻⁵ of itself, and
//! the blend by that fraction of the spread Δ of the heights blended there. The tests measure
//! ≤ 1 mm where surveys that agree meet (mosaic seams, holes, scattered soundings, nested
//! surveys), and up to 4 mm where a synthetic survey 400 m off the others shares a pixel with
//! them; they hold the GPU to 1 mm (two f32 spacings above 8,192 m) plus 2·10⁻⁵·Δ.
//!
//! *The accurate blend* ramps a weight from 1 to 0 across the 2-cell extension zone (a slope of
//! 8 per unit of t, where the tent's is 1), so the same rounding moves its weights 8 times as
//! much there, still ~10⁻⁶ of the spread blended; the same tests hold it to the same tolerance.
//! Off the kernel its weight is kept below 1 in f32 as in f64: rounded up to 1, a patch would
//! end a point's sum without covering it, and the mask would differ from the CPU's.

mod positions;

use bytemuck::{Pod, Zeroable};
use patchwork_core::geom::Aabb;
use patchwork_core::model::ids::PatchId;
use patchwork_core::model::patch::Blend;
use patchwork_core::resample::{cpu, Backend, PatchSet, ResolvedPatch, SampleGrid, Surface, BLOCK};
use patchwork_core::sync::lock;
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use thiserror::Error;

/// Patch ids are blake3 hashes already: hashing them again for the cache only cost time,
/// a tenth of a warm request's preparation at 16,000 patches.
#[derive(Default)]
struct IdHasher(u64);

impl std::hash::Hasher for IdHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = self.0.rotate_left(8) ^ u64::from(b);
        }
    }
    fn write_u64(&mut self, n: u64) {
        self.0 = n;
    }
}

type Cache = HashMap<PatchId, Held, std::hash::BuildHasherDefault<IdHasher>>;

/// A patch on the device, as the cache knows it: all a warm request looks up, kept small
/// (24 bytes) so that the lookups of 16,000 patches stay in the CPU's caches.
#[derive(Clone, Copy, Debug)]
struct Held {
    /// The patch's record in the device's table of patches.
    slot: u32,
    /// A hash of the window's bounds in the store's plane that the record holds: a patch of
    /// another CRS has other bounds in a store of another, so a resampler that serves two
    /// stores (tests do) keeps a record only for the bounds it was made with. With the
    /// patch's closed sides, which change when another survey raises its survey's claims.
    bounds: u64,
}

/// Samples are void at or above this, both in the arena and as a point's x.
const VOID: f32 = f32::MAX;

/// The patch kinds the shader evaluates.
pub const KIND_BILINEAR: u32 = 0;
/// An edge patch: its filled samples, weighted by a ramp that falls to 0 at the edge of its
/// survey's pixels.
pub const KIND_EDGE: u32 = 1;
/// A bicubic patch: the spline fitted to its window's samples, wherever the bilinear surface is
/// defined.
pub const KIND_BICUBIC: u32 = 2;

/// Byte budget of the patches on the device (samples and records) before they are emptied
/// and refilled.
pub const DEFAULT_ARENA_BYTES: u64 = 256 << 20;

/// Why the GPU could not resample: the daemon then resamples on the CPU, unless the request asked
/// for the GPU.
#[non_exhaustive]
#[derive(Debug, Error)]
pub enum GpuError {
    /// No adapter runs compute shaders, or only a software one that is not allowed; the message
    /// says which adapters there are.
    #[error("no GPU adapter with compute shaders: {0}")]
    NoAdapter(String),
    /// The adapter would not give a device.
    #[error("the GPU device could not be created: {0}")]
    Device(String),
    /// The device was lost (a driver reset, a GPU gone); a daemon drops it and resamples on the CPU
    /// from then on.
    #[error("the GPU device was lost: {0}")]
    Lost(String),
    /// The device reported an error, or the heights never came back.
    #[error("the GPU failed: {0}")]
    Failed(String),
    /// The request needs more than the device binds or dispatches at once.
    #[error("{0}")]
    TooLarge(String),
}

/// One patch as the shader reads it, kept on the device beside its samples: written once,
/// when they are uploaded, and read by every request that uses the patch. See `struct Patch`
/// in `resample.wgsl`; what differs from one request to the next is in [`GpuUse`].
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct GpuPatch {
    /// The patch's reach in the store's plane (`ResolvedPatch::reach`: min x, min y, max x,
    /// max y), each as hi + lo: what a block of samples is tested against.
    bounds_hi: [f32; 4],
    bounds_lo: [f32; 4],
    col_hi: [f32; 2],
    col_lo: [f32; 2],
    row_hi: [f32; 2],
    row_lo: [f32; 2],
    centre: [f32; 2],
    inv_half: [f32; 2],
    window: [f32; 4],
    kernel: [f32; 4],
    base: f32,
    flat: f32,
    offset: u32,
    cols: u32,
    rows: u32,
    kind: u32,
    /// `ResolvedPatch::closed`.
    closed: u32,
    _pad: u32,
}

/// What a request adds to a patch kept on the device: where its first sample is from the
/// request's origin, its rank and weight there, and which positions it reads. 32 bytes a
/// patch, the only per-patch bytes a warm request uploads.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct GpuUse {
    origin_hi: [f32; 2],
    origin_lo: [f32; 2],
    /// The patch's record in the device's table.
    slot: u32,
    /// Rank among the fallback patches, with [`FALLBACK`] set for a fallback patch.
    rank: u32,
    norm: f32,
    /// Where the patch's plane's positions start in the points buffer.
    points: u32,
}

/// Set in [`GpuUse::rank`] for a fallback patch.
const FALLBACK: u32 = 1 << 31;

/// Blocks along each side of a bin that the CPU fills: the shader picks each block's patches
/// from its bin, so the CPU bins 64 times fewer boxes and uploads a bin entry where it would
/// have uploaded dozens.
const SUPER: usize = 8;

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct Params {
    width: u32,
    height: u32,
    blocks_x: u32,
    has_fallback: u32,
    /// 1 where the store plane's positions are a north-up grid's axes (see [`Prepared`]).
    axes: u32,
    /// Bins along a row: blocks_x / [`SUPER`], rounded up.
    supers_x: u32,
    /// What the device makes positions from ([`positions::SOURCE_AXES`] or `SOURCE_ROWS`),
    /// and whether a lattice carries them into the store's plane.
    source: u32,
    carry: u32,
    /// The request's origin in the store's plane, as hi + lo.
    origin_hi: [f32; 2],
    origin_lo: [f32; 2],
    /// How far a patch's bounds are widened before a block is tested against them: more
    /// than the error of forming them relative to the origin, so the test keeps every patch
    /// that the CPU's would.
    pad: f32,
    /// Planes whose positions the device makes, and where the first one's start.
    planes: u32,
    plane0: u32,
    /// 1 for the accurate blend ([`PatchSet::with_blend`]), 0 for Formula 1.
    blend: u32,
}

/// Where a patch's samples sit in the arena: its window grown by one cell where the level has
/// one (the edge rule may use the cell beyond the window), first sample at level `(c0, r0)`.
#[derive(Clone, Copy, Debug)]
struct Uploaded {
    offset: u32,
    cols: u32,
    rows: u32,
    c0: u32,
    r0: u32,
    base: f32,
}

/// Where one request's time went.
#[derive(Clone, Debug, Default)]
pub struct GpuTimings {
    /// The CPU's work: binning and packing ([`prepare`]), and placing the patches on the
    /// device (under its lock).
    pub prepare: Duration,
    /// Queuing the uploads and the dispatches and submitting them, under the device's lock.
    pub queue: Duration,
    /// From submission until the heights can be read: the transfer of what was uploaded,
    /// both dispatches and the copy to the readback buffer.
    pub device: Duration,
    /// Copying the heights out of the readback buffer.
    pub readback: Duration,
    /// Bytes uploaded: the new patches' samples and records, lattice nodes, and the request's own
    /// buffers.
    pub uploaded_bytes: u64,
    /// Bytes read back: 4 a sample.
    pub read_bytes: u64,
    /// Patches whose samples were uploaded, and those found already on the device.
    pub uploaded_patches: usize,
    /// Patches whose samples were on the device already.
    pub cached_patches: usize,
}

/// One device and queue, the resampling pipeline, and the patches already on the device.
pub struct GpuResampler {
    device: wgpu::Device,
    queue: wgpu::Queue,
    /// Makes the positions of a grid that is not listed, lists each block's patches from
    /// its bin, then resamples.
    placer: wgpu::ComputePipeline,
    binner: wgpu::ComputePipeline,
    pipeline: wgpu::ComputePipeline,
    info: wgpu::AdapterInfo,
    max_binding: u64,
    budget: u64,
    /// The patches' samples, f32s, and their records ([`GpuPatch`]), one a slot.
    arena: Store,
    table: Store,
    cache: Cache,
    /// Lattice nodes, a block of 16² in a slot of [`positions::BLOCK_BYTES`], and which
    /// block of which lattice each slot holds.
    nodes: Store,
    node_cache: HashMap<(u64, [i64; 2]), u32>,
    /// [0], the shader's `unit`: a word it cannot know at compile time.
    unit: wgpu::Buffer,
    /// The per-request buffers, kept from one request to the next.
    pool: Pool,
    /// Buffers that heights were read back through, for the next requests.
    spare: Spare,
    health: Health,
}

/// Readback buffers free for a request: one a request in flight, kept for the next.
type Spare = Arc<Mutex<Vec<wgpu::Buffer>>>;

/// How many readback buffers are kept free: as many requests in flight as reuse them.
const SPARE: usize = 8;

/// Errors the device reported outside any scope, and device loss: shared with the requests
/// in flight, which wait outside the device's lock.
#[derive(Clone, Default)]
struct Health {
    errors: Arc<Mutex<Vec<String>>>,
    lost: Arc<Mutex<Option<String>>>,
}

impl Health {
    /// Fails with what the device reported since the last check.
    fn check(&self) -> Result<(), GpuError> {
        if let Some(l) = lock(&self.lost).clone() {
            return Err(GpuError::Lost(l));
        }
        let mut errors = lock(&self.errors);
        if !errors.is_empty() {
            let msg = errors.join("; ");
            errors.clear();
            return Err(GpuError::Failed(msg));
        }
        Ok(())
    }
}

/// A device buffer that is appended to and grown by doubling, keeping what it holds.
struct Store {
    label: &'static str,
    buffer: wgpu::Buffer,
    /// Size and use, in bytes.
    len: u64,
    used: u64,
}

impl Store {
    fn new(device: &wgpu::Device, label: &'static str, len: u64) -> Self {
        Store {
            label,
            buffer: store_buffer(device, label, len),
            len: len.max(16),
            used: 0,
        }
    }

    /// Room for `len` bytes in all, up to `cap` unless that is less than `len`.
    fn reserve(&mut self, device: &wgpu::Device, queue: &wgpu::Queue, len: u64, cap: u64) {
        if len <= self.len {
            return;
        }
        let mut new_len = self.len.max(16);
        while new_len < len {
            new_len *= 2;
        }
        let new_len = new_len
            .min(cap.max(len) / 4 * 4)
            .max(len.next_multiple_of(4));
        let buffer = store_buffer(device, self.label, new_len);
        if self.used > 0 {
            let mut enc = device.create_command_encoder(&Default::default());
            enc.copy_buffer_to_buffer(&self.buffer, 0, &buffer, 0, self.used);
            queue.submit([enc.finish()]);
        }
        self.buffer = buffer;
        self.len = new_len;
    }

    fn append(&mut self, queue: &wgpu::Queue, bytes: &[u8]) {
        if !bytes.is_empty() {
            queue.write_buffer(&self.buffer, self.used, bytes);
            self.used += bytes.len() as u64;
        }
    }
}

fn store_buffer(device: &wgpu::Device, label: &str, len: u64) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: len.max(16).next_multiple_of(4),
        usage: wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_DST
            | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    })
}

/// Slots of the [`Pool`]: params, points, uses, bin offsets, bins, and what the device makes
/// positions from (the source, the lattices and their blocks) are uploaded in that order
/// (0–7), then the heights the shader writes and the blocks' lists of patches, which never
/// leave the device. Points made on the device are not uploaded. A request in flight holds
/// only its readback buffer: the queue runs requests in order, so the next one's writes to
/// these wait for the last one's dispatch.
const UPLOADS: usize = 8;
const POINTS: usize = 1;
const OUT: usize = 8;
const LISTS: usize = 9;
/// Bytes of lattice nodes kept on the device: 4,096 blocks, each some 16 km or ¼° square.
const NODE_BYTES: u64 = 4096 * positions::BLOCK_BYTES;

/// The buffers a request uses, kept between requests and grown (to powers of two) only when
/// one needs more: creating them afresh cost more than the dispatch on a hardware GPU.
struct Pool {
    buffers: [Option<wgpu::Buffer>; 10],
    /// The largest buffer a binding takes, rounded down to 16 bytes: growth stops there.
    limit: u64,
}

impl Pool {
    /// The buffer of `slot`, at least `size` bytes, grown if it is smaller.
    fn take(
        &mut self,
        device: &wgpu::Device,
        slot: usize,
        size: u64,
        usage: wgpu::BufferUsages,
    ) -> &wgpu::Buffer {
        // Bindings may not be empty, nor smaller than one element (48 bytes for a lattice);
        // storage sizes must be multiples of 4.
        let size = size.max(64).next_multiple_of(16);
        let b = &mut self.buffers[slot];
        if b.as_ref().is_none_or(|b| b.size() < size) {
            *b = Some(device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(POOL_LABELS[slot]),
                size: size.next_power_of_two().min(self.limit.max(size)),
                usage,
                mapped_at_creation: false,
            }));
        }
        b.as_ref().expect("set above")
    }
}

const POOL_LABELS: [&str; 10] = [
    "params",
    "points",
    "uses",
    "bin offsets",
    "bins",
    "position source",
    "lattices",
    "lattice blocks",
    "heights",
    "block lists",
];

/// The CPU's part of a request: the patches binned, what the request adds to each patch,
/// and the sample positions packed for the shader. It needs no device, so it runs before the
/// device is taken.
pub struct Prepared {
    width: usize,
    height: usize,
    /// No valid point or no patch: every height is void, and the device is not needed.
    empty: bool,
    /// The origin the store plane's positions are relative to.
    origin: [f64; 2],
    /// The widening of patch bounds, [`Params::pad`].
    pad: f32,
    /// Whether the store plane's positions are a north-up grid's axes: its columns' x then
    /// its rows' y (width + height entries), not one entry a sample.
    axes: bool,
    /// Positions as (x hi, y hi, x lo, y lo) relative to their plane's origin: the store
    /// plane's, then every other plane's, one a sample; empty where the device makes them.
    points: Vec<[f32; 4]>,
    /// Entries of the device's points buffer: `points.len()`, or what the device makes.
    points_len: usize,
    /// What the device makes the positions from, unless they are listed or axes alone.
    generated: Option<positions::Generated>,
    /// Bins of [`SUPER`]² blocks: patch indices, ascending, whose window meets the bin.
    supers_x: usize,
    offsets: Vec<u32>,
    bins: Vec<u32>,
    /// One a patch of the set, its table slot filled in when the device places it.
    uses: Vec<GpuUse>,
    /// Each patch's id and [`bounds_hash`]: what the device's cache is searched by.
    keys: Vec<(PatchId, u64)>,
    took: Duration,
}

impl Prepared {
    /// How many bins of [`SUPER`]² blocks, and how many entries they hold in all.
    pub fn bins(&self) -> (usize, usize) {
        (
            self.offsets.len().saturating_sub(1),
            *self.offsets.last().unwrap_or(&0) as usize,
        )
    }

    /// Whether the CPU listed a position a sample (and plane) for the device, rather than
    /// the axes, rows and lattices the device makes them from: only a grid of scattered
    /// points, or one whose lattices span more than a device keeps, is listed.
    pub fn listed(&self) -> bool {
        self.generated.is_none() && !(self.axes && self.points.len() == self.width + self.height)
    }

    /// The most patches a bin of [`SUPER`]² blocks holds.
    pub fn largest_bin(&self) -> usize {
        self.offsets
            .windows(2)
            .map(|w| (w[1] - w[0]) as usize)
            .max()
            .unwrap_or(0)
    }

    /// Words of the blocks' lists of patches: each block of a bin has room for all of the
    /// bin's patches and their count (`list_start` in the shader).
    fn lists_len(&self) -> u64 {
        let bins = self.offsets.len().saturating_sub(1) as u64;
        (SUPER * SUPER) as u64 * (bins + *self.offsets.last().unwrap_or(&0) as u64)
    }

    /// Where plane `k`'s positions start in `points`.
    fn plane_start(&self, k: usize) -> u32 {
        let n = self.width * self.height;
        let first = if self.axes {
            self.width + self.height
        } else {
            n
        };
        if k == 0 {
            0
        } else {
            (first + (k - 1) * n) as u32
        }
    }
}

/// Bins the patches of `set` into bins of [`SUPER`]² blocks, works out what the request adds
/// to each patch, and says how the device finds the samples' positions. A north-up grid sends
/// its axes, one entry a column and one a row, not one a sample: the same f64 positions the
/// CPU blends at, each split into two f32s, so both backends work from the same coordinates.
/// A view sends two points a row, and positions in other CRSs are carried on the device
/// through lattices kept there ([`positions`]); the CPU lists a sample's positions only for a
/// grid of scattered points or one spanning more lattice than a device keeps.
pub fn prepare(set: &PatchSet, grid: &SampleGrid) -> Prepared {
    let t0 = Instant::now();
    // Axes that turn back bound no square by their ends: such a grid goes point by point.
    let pointwise;
    let grid = if grid.axes.is_some() && grid.axis_bounds(BLOCK).is_none() {
        pointwise = grid.clone().pointwise();
        &pointwise
    } else {
        grid
    };
    let mut p = Prepared {
        width: grid.width,
        height: grid.height,
        empty: true,
        origin: [0.0; 2],
        pad: 0.0,
        axes: false,
        points: Vec::new(),
        points_len: 0,
        generated: None,
        supers_x: 0,
        offsets: Vec::new(),
        bins: Vec::new(),
        uses: Vec::new(),
        keys: Vec::new(),
        took: Duration::ZERO,
    };
    if set.patches.is_empty() || grid.width * grid.height == 0 {
        return p;
    }
    let side = BLOCK * SUPER;
    // A north-up grid of the store's plane alone needs nothing made.
    let plan = if grid.axes.is_some() && set.planes.is_empty() {
        None
    } else {
        positions::plan(set, grid, side)
    };
    // Listed: every sample's position in each plane, each relative to an origin of its own.
    let mut listed = Vec::new();
    let (origin, plane_origins) = match &plan {
        Some(plan) => (plan.origin, plan.plane_origins.clone()),
        None => {
            let Some(origin) = grid.points().find(|p| !p[0].is_nan() && !p[1].is_nan()) else {
                return p;
            };
            listed = set.positions(grid);
            let origins = listed
                .iter()
                .map(|ps| {
                    ps.iter()
                        .copied()
                        .find(|p| !p[0].is_nan() && !p[1].is_nan())
                        .unwrap_or([0.0; 2])
                })
                .collect();
            (origin, origins)
        }
    };
    p.origin = origin;
    p.axes = grid.axes.is_some();
    let origins: Vec<[f64; 2]> = std::iter::once(origin).chain(plane_origins).collect();

    // One pass over the patches for all that is needed of them: a ResolvedPatch is several
    // cache lines, and at 16,000 patches each further pass cost a tenth of a millisecond.
    let n = set.patches.len();
    let (mut windows, mut norms) = (Vec::with_capacity(n), Vec::with_capacity(n));
    p.keys.reserve(n);
    p.uses.reserve(n);
    let mut scale = origin[0].abs().max(origin[1].abs());
    let mut max_norm = 0.0f64;
    for q in &set.patches {
        let w = q.reach();
        windows.push(w);
        norms.push(q.norm);
        max_norm = max_norm.max(q.norm);
        scale = scale.max(w.width()).max(w.height());
        // The closed sides follow the survey's claims, which other surveys can raise: a
        // record kept from before a raise is not this patch's any more.
        let h = (bounds_hash(&w) ^ u64::from(q.closed)).wrapping_mul(0x2545_f491_4f6c_dd1d);
        p.keys.push((q.id, h));
        let k = q.plane as usize;
        p.uses.push(use_of(q, origins[k], p.plane_start(k)));
    }
    for (u, norm) in p.uses.iter_mut().zip(norms) {
        // Only ratios of weights matter; scaling keeps them far from f32's range limits.
        u.norm = (norm / max_norm) as f32;
    }

    p.supers_x = grid.width.div_ceil(side);
    let flat = match grid.axis_bounds(side) {
        Some((cols, rows)) => cpu::Flat::of_axes(&windows, &cols, &rows),
        None => None,
    };
    let flat = match flat {
        Some(f) => f,
        // The shader finds each block's bounds from its points; the bins here need only
        // their squares'.
        None => match plan.as_ref().and_then(|p| p.squares.as_ref()) {
            Some(squares) => cpu::Flat::of(&cpu::bin_boxes(&set.patches, squares)),
            None => cpu::Flat::of(&cpu::bin_boxes(&set.patches, &grid.bounds_of(side))),
        },
    };
    (p.offsets, p.bins) = (flat.offsets, flat.entries);
    if p.bins.is_empty() {
        // Bindings cannot be empty; the offsets keep the shader from reading this.
        p.bins.push(0);
    }
    // Forming a patch's bounds relative to the origin from their hi + lo halves errs by a
    // few units of 2⁻⁴⁸ of the coordinates' size; the widening is far above that and far
    // below anything that moves a block's patches.
    p.pad = (2.0 * scale * 2f64.powi(-40)) as f32;

    match (plan, &grid.axes) {
        (Some(plan), _) => {
            p.points_len = p.plane_start(set.planes.len() + 1) as usize;
            p.generated = Some(plan.generated);
        }
        (None, axes) => {
            let pack = |q: [f64; 2], origin: [f64; 2]| {
                if q[0].is_nan() || q[1].is_nan() {
                    [VOID, 0.0, 0.0, 0.0]
                } else {
                    let [xh, xl] = split(q[0] - origin[0]);
                    let [yh, yl] = split(q[1] - origin[1]);
                    [xh, yh, xl, yl]
                }
            };
            match axes {
                Some(axes) => p.points = positions::axes_source(axes, origin),
                None => p.points.extend(grid.points().map(|q| pack(q, origin))),
            }
            p.points.reserve(listed.len() * grid.width * grid.height);
            for (ps, o) in listed.iter().zip(&origins[1..]) {
                p.points.extend(ps.iter().map(|&q| pack(q, *o)));
            }
            p.points_len = p.points.len();
        }
    }
    p.empty = false;
    p.took = t0.elapsed();
    p
}

/// The resampler a backend choice calls for: none for `Cpu`, one if a device opens for
/// `Auto`, and for `Gpu` one or the reason there is none.
pub fn select(backend: Backend, emulated: Emulated) -> Result<Option<GpuResampler>, GpuError> {
    match backend {
        Backend::Cpu => Ok(None),
        Backend::Gpu => GpuResampler::new(emulated).map(Some),
        Backend::Auto => match GpuResampler::new(emulated) {
            Ok(g) => Ok(Some(g)),
            Err(e) => {
                tracing::info!(error = %e, "no GPU; resampling on the CPU");
                Ok(None)
            }
        },
    }
}

fn split(x: f64) -> [f32; 2] {
    let hi = x as f32;
    [hi, (x - hi as f64) as f32]
}

/// Whether a software adapter (Mesa's llvmpipe or lavapipe, WARP) may resample. On a server
/// without a GPU it is several times slower than the CPU path, so by default it may not; tests
/// of the GPU code allow it where it is the only adapter.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Emulated {
    /// Only a real GPU is taken.
    Refuse,
    /// A software adapter is taken where no real GPU is.
    Allow,
}

impl GpuResampler {
    /// A resampler on the best adapter `emulated` allows, keeping at most [`DEFAULT_ARENA_BYTES`]
    /// of patches on the device.
    pub fn new(emulated: Emulated) -> Result<Self, GpuError> {
        Self::with_budget(DEFAULT_ARENA_BYTES, emulated)
    }

    /// A resampler whose patches (their samples and records) take at most `budget` bytes of
    /// the device (more only when a single request needs it).
    pub fn with_budget(budget: u64, emulated: Emulated) -> Result<Self, GpuError> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        // Vulkan, Metal and DX12. GL goes through EGL, whose Mesa build writes to stderr on
        // every start of a machine without a display, and a compute-capable GPU has one of
        // the three anyway.
        desc.backends = wgpu::Backends::PRIMARY;
        let instance = wgpu::Instance::new(desc);
        let adapter = pick_adapter(&instance, emulated)?;
        let info = adapter.get_info();
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("patchwork resample"),
            required_features: wgpu::Features::empty(),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device(e.to_string()))?;
        let health = Health::default();
        {
            let errors = health.errors.clone();
            device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
                tracing::error!(error = %e, "GPU error");
                lock(&errors).push(e.to_string());
            }));
            let lost = health.lost.clone();
            device.set_device_lost_callback(move |reason, msg| {
                *lock(&lost) = Some(format!("{reason:?}: {msg}"));
            });
        }
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("resample.wgsl"),
            source: wgpu::ShaderSource::Wgsl(include_str!("resample.wgsl").into()),
        });
        // Each entry point's layout is derived from the bindings it uses.
        let pipeline = |entry| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: None,
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let (placer, binner, pipeline) = (
            pipeline("place_points"),
            pipeline("bin_blocks"),
            pipeline("main"),
        );
        let max_binding = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        let budget = budget.min(max_binding);
        let arena = Store::new(&device, "sample arena", (16u64 << 20).min(budget));
        let table = Store::new(&device, "patch table", 1 << 20);
        let nodes = Store::new(&device, "lattice nodes", 64 * positions::BLOCK_BYTES);
        let unit = store_buffer(&device, "unit", 16);
        queue.write_buffer(&unit, 0, bytemuck::cast_slice(&[0u32; 4]));
        let g = GpuResampler {
            device,
            queue,
            placer,
            binner,
            pipeline,
            info,
            max_binding,
            budget,
            arena,
            table,
            cache: Cache::default(),
            nodes,
            node_cache: HashMap::new(),
            unit,
            pool: Pool {
                buffers: Default::default(),
                limit: max_binding / 16 * 16,
            },
            spare: Spare::default(),
            health,
        };
        g.check()?;
        Ok(g)
    }

    /// The adapter in use, e.g. "llvmpipe (LLVM 15.0.7, 256 bits) on Vulkan".
    pub fn adapter(&self) -> String {
        format!("{} on {:?}", self.info.name, self.info.backend)
    }

    /// Whether the adapter is a software one, emulating a GPU on the CPU.
    pub fn is_emulated(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// Patches whose samples are on the device now.
    pub fn cached_patches(&self) -> usize {
        self.cache.len()
    }

    /// Heights at every point of the grid, NaN where no valid kernel reaches: what
    /// [`cpu::resample`] returns, to f32 rounding.
    pub fn resample(&mut self, set: &PatchSet, grid: &SampleGrid) -> Result<Vec<f32>, GpuError> {
        self.resample_timed(set, grid).map(|(h, _)| h)
    }

    /// [`GpuResampler::resample`], and where the request's time went.
    pub fn resample_timed(
        &mut self,
        set: &PatchSet,
        grid: &SampleGrid,
    ) -> Result<(Vec<f32>, GpuTimings), GpuError> {
        let prepared = prepare(set, grid);
        self.submit(set, prepared)?.wait()
    }

    /// The device's part of a request whose CPU part, [`prepare`], ran already (outside
    /// whatever lock guards this resampler): the patches not on the device yet, the uploads
    /// and both dispatches, queued and submitted. The heights come back through
    /// [`Submitted::wait`], which needs no `&mut self`: a daemon releases the device for the
    /// next request while this one runs and is read back.
    pub fn submit(&mut self, set: &PatchSet, prep: Prepared) -> Result<Submitted, GpuError> {
        // The device's errors from this request's calls are this request's: caught in scopes
        // of this thread, not in the list that every request in flight checks.
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let memory = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let submitted = self.submit_scoped(set, prep);
        let errors = [
            pollster::block_on(memory.pop()),
            pollster::block_on(validation.pop()),
        ];
        let Some(e) = errors.into_iter().flatten().next() else {
            return submitted;
        };
        // What the caches say is on the device may not have got there.
        self.cache.clear();
        self.arena.used = 0;
        self.table.used = 0;
        self.node_cache.clear();
        self.nodes.used = 0;
        Err(match e {
            wgpu::Error::OutOfMemory { .. } => {
                GpuError::TooLarge("the device ran out of memory for this request".into())
            }
            e => GpuError::Failed(e.to_string()),
        })
    }

    fn submit_scoped(&mut self, set: &PatchSet, mut prep: Prepared) -> Result<Submitted, GpuError> {
        self.check()?;
        let mut tm = GpuTimings {
            prepare: prep.took,
            ..Default::default()
        };
        let n = prep.width * prep.height;
        let mut done = Submitted {
            device: self.device.clone(),
            health: self.health.clone(),
            spare: self.spare.clone(),
            index: None,
            read: None,
            n,
            tm: GpuTimings::default(),
            submitted: Instant::now(),
        };
        if prep.empty {
            done.tm = tm;
            return Ok(done);
        }
        let (bx, by) = (prep.width.div_ceil(BLOCK), prep.height.div_ceil(BLOCK));
        let wg_max = self.device.limits().max_compute_workgroups_per_dimension as usize;
        if (prep.points_len * 16) as u64 > self.max_binding
            || (n * 4) as u64 > self.max_binding
            || prep.lists_len() * 4 > self.max_binding
            || (bx * by).div_ceil(64) > wg_max
            || bx > wg_max
            || by > wg_max
        {
            return Err(GpuError::TooLarge(format!(
                "a {}×{} grid is more than this device takes in one dispatch",
                prep.width, prep.height
            )));
        }

        let t0 = Instant::now();
        let placed = self.place(set, &prep.keys)?;
        for (u, slot) in prep.uses.iter_mut().zip(&placed.slots) {
            u.slot = slot.expect("every patch placed");
        }
        let generated = prep.generated.take();
        let nodes = match &generated {
            Some(g) => self.place_nodes(g)?,
            None => (Vec::new(), Vec::new()),
        };
        tm.prepare += t0.elapsed();

        let t1 = Instant::now();
        tm.uploaded_patches = placed.records.len();
        tm.cached_patches = set.patches.len() - tm.uploaded_patches;
        let samples: &[u8] = bytemuck::cast_slice(&placed.samples);
        let records: &[u8] = bytemuck::cast_slice(&placed.records);
        tm.uploaded_bytes += (samples.len() + records.len()) as u64;
        self.arena.append(&self.queue, samples);
        self.table.append(&self.queue, records);
        let node_bytes: &[u8] = bytemuck::cast_slice(&nodes.1);
        tm.uploaded_bytes += node_bytes.len() as u64;
        self.nodes.append(&self.queue, node_bytes);
        let mut refs = generated.as_ref().map_or(Vec::new(), |g| g.refs.clone());
        for (r, slot) in refs.iter_mut().zip(&nodes.0) {
            r.slot = *slot;
        }
        let planes = if generated.is_some() {
            set.planes.len()
        } else {
            0
        };
        let [ox, oy] = prep.origin;
        let ([oxh, oxl], [oyh, oyl]) = (split(ox), split(oy));
        let params = Params {
            width: prep.width as u32,
            height: prep.height as u32,
            blocks_x: bx as u32,
            has_fallback: u32::from(set.has_fallback),
            axes: u32::from(prep.axes),
            supers_x: prep.supers_x as u32,
            source: generated.as_ref().map_or(0, |g| g.kind),
            carry: generated.as_ref().map_or(0, |g| u32::from(g.carry)),
            origin_hi: [oxh, oyh],
            origin_lo: [oxl, oyl],
            pad: prep.pad,
            planes: planes as u32,
            plane0: prep.plane_start(1),
            blend: u32::from(set.blend == Blend::Accurate),
        };
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
        let uniform = wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST;
        let out_usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        let read_usage = wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST;
        let (source, lattices): (&[[f32; 4]], &[positions::GpuLattice]) = match &generated {
            Some(g) => (&g.source, &g.lattices),
            None => (&[], &[]),
        };
        let uploads: [(&[u8], _); UPLOADS] = [
            (bytemuck::bytes_of(&params), uniform),
            (bytemuck::cast_slice(&prep.points), storage),
            (bytemuck::cast_slice(&prep.uses), storage),
            (bytemuck::cast_slice(&prep.offsets), storage),
            (bytemuck::cast_slice(&prep.bins), storage),
            (
                bytemuck::cast_slice(source),
                storage | wgpu::BufferUsages::COPY_SRC,
            ),
            (bytemuck::cast_slice(lattices), storage),
            (bytemuck::cast_slice(&refs), storage),
        ];
        for (slot, (bytes, usage)) in uploads.iter().enumerate() {
            let len = match slot {
                // Made on the device where they are not listed.
                POINTS => (prep.points_len * 16) as u64,
                _ => bytes.len() as u64,
            };
            let b = self.pool.take(&self.device, slot, len, *usage);
            if !bytes.is_empty() {
                self.queue.write_buffer(b, 0, bytes);
            }
            tm.uploaded_bytes += bytes.len() as u64;
        }
        let out_bytes = (n * 4) as u64;
        tm.read_bytes = out_bytes;
        self.pool.take(&self.device, OUT, out_bytes, out_usage);
        self.pool.take(
            &self.device,
            LISTS,
            prep.lists_len() * 4,
            wgpu::BufferUsages::STORAGE,
        );
        let read = {
            let mut spare = lock(&self.spare);
            match spare.iter().position(|b| b.size() >= out_bytes) {
                Some(k) => spare.swap_remove(k),
                None => self.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("heights readback"),
                    size: out_bytes
                        .max(16)
                        .next_power_of_two()
                        .min(self.max_binding.max(out_bytes)),
                    usage: read_usage,
                    mapped_at_creation: false,
                }),
            }
        };
        let bufs = &self.pool.buffers;
        let buf = |slot: usize| bufs[slot].as_ref().expect("taken above");
        let group = |pipeline: &wgpu::ComputePipeline, entries: &[(u32, &wgpu::Buffer)]| {
            let entries: Vec<_> = entries
                .iter()
                .map(|&(binding, b)| wgpu::BindGroupEntry {
                    binding,
                    resource: b.as_entire_binding(),
                })
                .collect();
            self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: &pipeline.get_bind_group_layout(0),
                entries: &entries,
            })
        };
        let (table, arena) = (&self.table.buffer, &self.arena.buffer);
        let place_group = generated.is_some().then(|| {
            group(
                &self.placer,
                &[
                    (0, buf(0)),
                    (11, buf(5)),
                    (12, buf(6)),
                    (13, buf(7)),
                    (14, &self.nodes.buffer),
                    (15, buf(POINTS)),
                    (16, &self.unit),
                ],
            )
        });
        let bin_group = group(
            &self.binner,
            &[
                (0, buf(0)),
                (1, buf(POINTS)),
                (2, table),
                (4, buf(3)),
                (5, buf(4)),
                (7, buf(2)),
                (9, buf(LISTS)),
                (16, &self.unit),
            ],
        );
        let bind = group(
            &self.pipeline,
            &[
                (0, buf(0)),
                (1, buf(POINTS)),
                (2, table),
                (3, arena),
                (4, buf(3)),
                (6, buf(OUT)),
                (7, buf(2)),
                (10, buf(LISTS)),
                (16, &self.unit),
            ],
        );
        let mut enc = self.device.create_command_encoder(&Default::default());
        if place_group.is_some() && prep.axes {
            // The store plane's positions are the axes, as uploaded; the device makes the
            // other planes' after them.
            let axes = ((prep.width + prep.height) * 16) as u64;
            enc.copy_buffer_to_buffer(buf(5), 0, buf(POINTS), 0, Some(axes));
        }
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            if let Some(place) = &place_group {
                pass.set_pipeline(&self.placer);
                pass.set_bind_group(0, place, &[]);
                pass.dispatch_workgroups(bx as u32, by as u32, 1);
            }
            pass.set_pipeline(&self.binner);
            pass.set_bind_group(0, &bin_group, &[]);
            pass.dispatch_workgroups((bx * by).div_ceil(64) as u32, 1, 1);
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(bx as u32, by as u32, 1);
        }
        enc.copy_buffer_to_buffer(buf(OUT), 0, &read, 0, Some(out_bytes));
        done.index = Some(self.queue.submit([enc.finish()]));
        done.submitted = Instant::now();
        tm.queue = t1.elapsed();
        done.read = Some(read);
        done.tm = tm;
        self.check()?;
        Ok(done)
    }

    /// The table slot of every patch of the set, and the samples and records of those not on
    /// the device yet (packed to follow what it holds), with room made for them.
    fn place(&mut self, set: &PatchSet, keys: &[(PatchId, u64)]) -> Result<Placed, GpuError> {
        let held = |cache: &Cache, (id, bounds): &(PatchId, u64)| {
            cache
                .get(id)
                .filter(|u| u.bounds == *bounds)
                .map(|u| u.slot)
        };
        let mut out = Placed {
            slots: keys.iter().map(|k| held(&self.cache, k)).collect(),
            samples: Vec::new(),
            records: Vec::new(),
        };
        if out.slots.iter().all(Option::is_some) {
            return Ok(out);
        }
        let missing = |slots: &[Option<u32>]| {
            let mut seen = std::collections::HashSet::new();
            set.patches
                .iter()
                .zip(slots)
                .zip(keys)
                .filter(|((_, s), k)| s.is_none() && seen.insert(**k))
                .fold((0u64, 0u64), |(f, n), ((p, _), _)| {
                    (f + extent(p).len(p), n + 1)
                })
        };
        let record = std::mem::size_of::<GpuPatch>() as u64;
        let mut need = missing(&out.slots);
        // The records count against the budget with the samples: the patches on the
        // device take at most `budget` bytes in all.
        if self.arena.used + self.table.used + 4 * need.0 + record * need.1 > self.budget
            || self.table.used + record * need.1 > self.max_binding
        {
            // Emptied and refilled with this request's patches: crude, but it never
            // fragments, and the next requests refill it.
            self.cache.clear();
            self.arena.used = 0;
            self.table.used = 0;
            out.slots.fill(None);
            need = missing(&out.slots);
        }
        if 4 * need.0 > self.max_binding || record * need.1 > self.max_binding {
            return Err(GpuError::TooLarge(format!(
                "the patches of this request need {} MiB of samples, more than the device binds",
                (need.0 * 4) >> 20
            )));
        }
        let (used, table_used) = (self.arena.used, self.table.used);
        self.arena
            .reserve(&self.device, &self.queue, used + 4 * need.0, self.budget);
        self.table.reserve(
            &self.device,
            &self.queue,
            table_used + record * need.1,
            self.budget,
        );
        self.check()?;
        out.samples.reserve(need.0 as usize);
        out.records.reserve(need.1 as usize);
        let first_slot = (table_used / record) as u32;
        for ((p, key), slot) in set.patches.iter().zip(keys).zip(out.slots.iter_mut()) {
            if slot.is_some() {
                continue;
            }
            // A patch listed twice is packed once.
            if let Some(s) = held(&self.cache, key) {
                *slot = Some(s);
                continue;
            }
            let offset = (used / 4) as u32 + out.samples.len() as u32;
            let s = first_slot + out.records.len() as u32;
            let u = pack(p, offset, &mut out.samples);
            out.records.push(gpu_patch(p, &u));
            self.cache.insert(
                p.id,
                Held {
                    slot: s,
                    bounds: key.1,
                },
            );
            *slot = Some(s);
        }
        Ok(out)
    }

    /// The node slot of every block a request's lattices read ([`positions::NO_SLOT`] for
    /// one without nodes), and the nodes of those not on the device yet, packed to follow
    /// what it holds, with room made for them. Emptied and refilled when full, as the
    /// patches are.
    fn place_nodes(
        &mut self,
        g: &positions::Generated,
    ) -> Result<(Vec<u32>, Vec<[f32; 4]>), GpuError> {
        let missing = |cache: &HashMap<(u64, [i64; 2]), u32>| {
            let mut seen = std::collections::HashSet::new();
            g.blocks
                .iter()
                .filter(|b| b.anchor[0].is_finite() && !cache.contains_key(&b.key))
                .filter(|b| seen.insert(b.key))
                .count() as u64
        };
        let mut need = missing(&self.node_cache);
        if self.nodes.used + need * positions::BLOCK_BYTES > NODE_BYTES {
            self.node_cache.clear();
            self.nodes.used = 0;
            need = missing(&self.node_cache);
        }
        let bytes = need * positions::BLOCK_BYTES;
        if bytes > self.max_binding {
            return Err(GpuError::TooLarge(
                "this request's lattices need more nodes than the device binds".into(),
            ));
        }
        let used = self.nodes.used;
        self.nodes.reserve(
            &self.device,
            &self.queue,
            used + bytes,
            NODE_BYTES.max(used + bytes),
        );
        self.check()?;
        let mut packed = Vec::with_capacity((bytes / 16) as usize);
        let mut slots = Vec::with_capacity(g.blocks.len());
        for b in &g.blocks {
            if !b.anchor[0].is_finite() {
                slots.push(positions::NO_SLOT);
                continue;
            }
            let slot = match self.node_cache.get(&b.key) {
                Some(&s) => s,
                None => {
                    let s = ((used + packed.len() as u64 * 16) / positions::BLOCK_BYTES) as u32;
                    b.pack(&mut packed);
                    self.node_cache.insert(b.key, s);
                    s
                }
            };
            slots.push(slot);
        }
        Ok((slots, packed))
    }

    fn check(&self) -> Result<(), GpuError> {
        self.health.check()
    }
}

/// A request on the device: its heights come back through [`Submitted::wait`].
pub struct Submitted {
    device: wgpu::Device,
    health: Health,
    spare: Spare,
    /// None for a request with nothing to do on the device (every height void).
    index: Option<wgpu::SubmissionIndex>,
    read: Option<wgpu::Buffer>,
    n: usize,
    tm: GpuTimings,
    submitted: Instant,
}

impl Submitted {
    /// Waits for the device to finish this request and reads its heights back: NaN where
    /// no valid kernel reaches, what [`cpu::resample`] returns to f32 rounding.
    pub fn wait(mut self) -> Result<(Vec<f32>, GpuTimings), GpuError> {
        let (Some(index), Some(read)) = (self.index.take(), self.read.take()) else {
            return Ok((vec![f32::NAN; self.n], self.tm));
        };
        let bytes = (self.n * 4) as u64;
        let (tx, rx) = std::sync::mpsc::channel();
        read.map_async(wgpu::MapMode::Read, ..bytes, move |r| {
            let _ = tx.send(r);
        });
        // Waiting for this submission, not the device: later ones may run on. The callback
        // runs on whichever thread's poll finds the submission done, maybe another request's
        // and maybe a moment after that poll returns, so it is waited for in turn.
        let poll = |how| {
            self.device
                .poll(how)
                .map_err(|e| GpuError::Failed(e.to_string()))
        };
        poll(wgpu::PollType::Wait {
            submission_index: Some(index),
            timeout: None,
        })?;
        let deadline = Instant::now() + Duration::from_secs(60);
        let mapped = loop {
            match rx.recv_timeout(Duration::from_millis(1)) {
                Ok(r) => break r,
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) if Instant::now() < deadline => {
                    poll(wgpu::PollType::Poll)?;
                }
                Err(_) => return Err(GpuError::Failed("the results never came back".into())),
            }
        };
        self.health.check()?;
        if let Err(e) = mapped {
            return Err(GpuError::Failed(format!("reading the results back: {e}")));
        }
        self.tm.device = self.submitted.elapsed();
        let t = Instant::now();
        // The shader writes each height whole, as f32 bits (NaN where void): the sum of the
        // blend and its base rounded once, as the CPU rounds its f64 sum.
        let out = {
            let view = read
                .get_mapped_range(..bytes)
                .map_err(|e| GpuError::Failed(e.to_string()))?;
            bytemuck::cast_slice::<u8, f32>(&view).to_vec()
        };
        read.unmap();
        let mut spare = lock(&self.spare);
        if spare.len() < SPARE {
            spare.push(read);
        }
        self.tm.readback = t.elapsed();
        Ok((out, self.tm))
    }
}

/// The adapters with compute shaders that the probe sees, as "software" or "gpu", a tab, and
/// the adapter's name and API, one to a line: what `patchwork probe-gpu` prints for a daemon
/// to read before it loads any driver itself.
pub fn list_adapters() -> Vec<String> {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::PRIMARY;
    let instance = wgpu::Instance::new(desc);
    pollster::block_on(instance.enumerate_adapters(wgpu::Backends::PRIMARY))
        .iter()
        .filter(|a| {
            a.get_downlevel_capabilities()
                .flags
                .contains(wgpu::DownlevelFlags::COMPUTE_SHADERS)
        })
        .map(|a| {
            let i = a.get_info();
            let kind = if i.device_type == wgpu::DeviceType::Cpu {
                "software"
            } else {
                "gpu"
            };
            format!("{kind}\t{} ({:?})", i.name, i.backend)
        })
        .collect()
}

/// Why the software adapters `names` are not taken.
pub fn software_refused(names: &str) -> String {
    format!(
        "only the software adapter {names}, slower than the CPU path; set allow_emulated_gpu = \
         true to resample on it anyway"
    )
}

/// The best adapter that runs compute shaders: a real GPU before a software one, which is
/// taken only if `emulated` allows it.
fn pick_adapter(instance: &wgpu::Instance, emulated: Emulated) -> Result<wgpu::Adapter, GpuError> {
    let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::PRIMARY));
    let seen: Vec<String> = adapters
        .iter()
        .map(|a| {
            let i = a.get_info();
            format!("{} ({:?})", i.name, i.backend)
        })
        .collect();
    let software = |a: &wgpu::Adapter| a.get_info().device_type == wgpu::DeviceType::Cpu;
    let rank = |a: &wgpu::Adapter| match a.get_info().device_type {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Cpu => 3,
        wgpu::DeviceType::Other => 4,
    };
    let capable: Vec<wgpu::Adapter> = adapters
        .into_iter()
        .filter(|a| {
            a.get_downlevel_capabilities()
                .flags
                .contains(wgpu::DownlevelFlags::COMPUTE_SHADERS)
        })
        .collect();
    let only_software = !capable.is_empty() && capable.iter().all(software);
    capable
        .into_iter()
        .filter(|a| emulated == Emulated::Allow || !software(a))
        .min_by_key(rank)
        .ok_or_else(|| {
            GpuError::NoAdapter(if seen.is_empty() {
                "no adapters at all (no Vulkan, Metal or DX12 driver)".into()
            } else if only_software {
                software_refused(&seen.join(", "))
            } else {
                format!("none of {} runs compute shaders", seen.join(", "))
            })
        })
}

/// What [`GpuResampler::place`] found and made: a table slot a patch of the set, and the
/// samples and records to append.
struct Placed {
    /// Every one is Some once placed.
    slots: Vec<Option<u32>>,
    samples: Vec<f32>,
    records: Vec<GpuPatch>,
}

/// The samples a patch uploads: a survey patch's window plus one cell on every side its level
/// has (the edge rule may look at the cell beyond the window), or an edge patch's whole grid.
struct Extent {
    c0: u32,
    r0: u32,
    cols: u32,
    rows: u32,
}

impl Extent {
    /// f32 slots in the arena: edge patches add a flag word per sample, bicubic ones their
    /// spline's coefficients.
    fn len(&self, p: &ResolvedPatch) -> u64 {
        let n = self.cols as u64 * self.rows as u64;
        match &p.surface {
            Surface::Bilinear(_) => n,
            Surface::Bicubic(_, s) => n + s.coef.len() as u64,
            Surface::Edge(_) => 2 * n,
        }
    }
}

fn extent(p: &ResolvedPatch) -> Extent {
    let [cw, ch] = p.surface.cells();
    if let Surface::Edge(_) = p.surface {
        return Extent {
            c0: 0,
            r0: 0,
            cols: cw as u32 + 1,
            rows: ch as u32 + 1,
        };
    }
    let w = p.window;
    let c0 = w.c0.saturating_sub(1);
    let r0 = w.r0.saturating_sub(1);
    let c1 = (w.c1 + 1).min(cw as u32);
    let r1 = (w.r1 + 1).min(ch as u32);
    Extent {
        c0,
        r0,
        cols: c1 - c0 + 1,
        rows: r1 - r0 + 1,
    }
}

/// Appends a patch's samples relative to its base, voids as [`VOID`], and after them an edge
/// patch's flags or a bicubic patch's spline coefficients (relative to the same base).
fn pack(p: &ResolvedPatch, offset: u32, data: &mut Vec<f32>) -> Uploaded {
    let e = extent(p);
    // An edge grid keeps only its edge cells' corners; the shader reads its whole window,
    // the samples it never evaluates void.
    let whole;
    // Where the surface's samples start in its level: a window of a level may begin inside it.
    let (heights, cols, flags, at): (&[f32], usize, Option<&[u8]>, [usize; 2]) = match &p.surface {
        Surface::Bilinear(w) | Surface::Bicubic(w, _) => {
            (&w.grid.samples, w.grid.cols, None, [w.c0, w.r0])
        }
        Surface::Edge(g) => {
            whole = g.dense();
            (&whole.0, g.cols, Some(&whole.1), [0, 0])
        }
    };
    let rows = || (e.r0..e.r0 + e.rows).map(|r| r as usize - at[1]);
    let c0 = e.c0 as usize - at[0];
    let row = |r: usize| &heights[r * cols + c0..][..e.cols as usize];
    let (lo, hi) = rows()
        .flat_map(row)
        .filter(|z| !z.is_nan())
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &z| {
            (lo.min(z), hi.max(z))
        });
    let base = if lo <= hi {
        (0.5 * (lo as f64 + hi as f64)) as f32
    } else {
        0.0
    };
    for r in rows() {
        data.extend(row(r).iter().map(|&z| {
            if z.is_nan() {
                VOID
            } else {
                (z as f64 - base as f64) as f32
            }
        }));
    }
    if let Surface::Bicubic(_, spline) = &p.surface {
        data.extend(spline.coef.iter().map(|&c| (c - base as f64) as f32));
    }
    if let Some(flags) = flags {
        for r in rows() {
            data.extend(
                flags[r * cols + c0..][..e.cols as usize]
                    .iter()
                    .map(|&f| f32::from(f)),
            );
        }
    }
    Uploaded {
        offset,
        cols: e.cols,
        rows: e.rows,
        c0: e.c0,
        r0: e.r0,
        base,
    }
}

/// A patch's reach ([`ResolvedPatch::reach`]) as (min x, min y, max x, max y).
fn bounds(b: &Aabb) -> [f64; 4] {
    [b.min[0], b.min[1], b.max[0], b.max[1]]
}

/// [`bounds`] hashed for [`Held`].
fn bounds_hash(b: &Aabb) -> u64 {
    bounds(b).iter().fold(0x9e37_79b9_7f4a_7c15u64, |h, v| {
        (h.rotate_left(23) ^ v.to_bits()).wrapping_mul(0x2545_f491_4f6c_dd1d)
    })
}

/// The shader's record of a patch whose samples were packed as `a` says.
fn gpu_patch(p: &ResolvedPatch, a: &Uploaded) -> GpuPatch {
    let (c0, r0) = (a.c0 as f64, a.r0 as f64);
    let rect = |r: &patchwork_core::model::patch::CellRect| {
        [
            (r.c0 as f64 - c0) as f32,
            (r.r0 as f64 - r0) as f32,
            (r.c1 as f64 - c0) as f32,
            (r.r1 as f64 - r0) as f32,
        ]
    };
    let f2 = |v: [f64; 2]| [v[0] as f32, v[1] as f32];
    let axis = |a: [f64; 2], s: f64| {
        let [xh, xl] = split(a[0] * s);
        let [yh, yl] = split(a[1] * s);
        ([xh, yh], [xl, yl])
    };
    let (col_hi, col_lo) = axis(p.u, p.inv_step[0]);
    let (row_hi, row_lo) = axis(p.v, p.inv_step[1]);
    let halves = bounds(&p.reach()).map(split);
    GpuPatch {
        bounds_hi: halves.map(|h| h[0]),
        bounds_lo: halves.map(|h| h[1]),
        col_hi,
        col_lo,
        row_hi,
        row_lo,
        centre: [(p.centre[0] - c0) as f32, (p.centre[1] - r0) as f32],
        inv_half: f2(p.inv_half),
        base: a.base,
        window: rect(&p.window),
        kernel: rect(&p.kernel),
        offset: a.offset,
        cols: a.cols,
        rows: a.rows,
        kind: match p.surface {
            Surface::Bilinear(_) => KIND_BILINEAR,
            Surface::Bicubic(..) => KIND_BICUBIC,
            Surface::Edge(_) => KIND_EDGE,
        },
        flat: p.flat as f32,
        closed: p.closed as u32,
        _pad: 0,
    }
}

/// What a request adds to patch `p`: its first uploaded sample relative to `origin`, the
/// origin of its plane's positions, which start at `points` in the points buffer.
fn use_of(p: &ResolvedPatch, origin: [f64; 2], points: u32) -> GpuUse {
    let e = extent(p);
    let (c0, r0) = (e.c0 as f64, e.r0 as f64);
    // The first uploaded sample, from the same origin and axes `to_grid` uses.
    let [u, v] = p.axes;
    let o = [
        p.origin[0] + c0 * u[0] / p.inv_step[0] + r0 * v[0] / p.inv_step[1],
        p.origin[1] + c0 * u[1] / p.inv_step[0] + r0 * v[1] / p.inv_step[1],
    ];
    let [xh, xl] = split(o[0] - origin[0]);
    let [yh, yl] = split(o[1] - origin[1]);
    GpuUse {
        origin_hi: [xh, yh],
        origin_lo: [xl, yl],
        slot: 0,
        rank: p.rank | if p.fallback { FALLBACK } else { 0 },
        // Set once the set's largest is known.
        norm: 0.0,
        points,
    }
}
