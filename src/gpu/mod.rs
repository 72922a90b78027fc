//! Formula 1 on a GPU through wgpu: the sums of [`cpu::blend`] evaluated by a compute shader
//! (`resample.wgsl`), one workgroup per [`BLOCK`] × [`BLOCK`] block of output samples, each
//! visiting only the patches of its block's bin (§7.3).
//!
//! A request is in two parts. [`prepare`] is the CPU's: binning, and the positions packed
//! (for a north-up grid its axes, a column's x and a row's y, not a point a sample: 32 KB for
//! a 2048² tile where points took 64 MB). [`GpuResampler::resample_prepared`] is the device's:
//! the patches' samples not yet on it, the dispatch, and 4 bytes a sample read back, through
//! buffers kept from one request to the next. Only the second needs the device, so a daemon
//! prepares outside its lock.
//!
//! Patch samples live in one storage buffer, an append-only arena keyed by [`PatchId`], so a
//! request that shares patches with an earlier one uploads only the new ones. When the arena
//! would grow past its byte budget it is emptied and refilled with the current request's
//! patches: crude, but it never fragments and the next requests refill it.
//!
//! # Precision
//!
//! The shader works in f32 and the CPU in f64, so the two differ by rounding. Write
//! u = 2⁻²⁴ for the unit roundoff of f32.
//!
//! *Positions.* Geographic coordinates near −119° have an f32 spacing of 7.6·10⁻⁶° (≈ 0.8 m),
//! so world positions never reach the GPU as f32. The CPU subtracts a tile origin in f64 and
//! sends each sample point, each patch's first sample and each patch's axes (divided by the
//! spacing) as unevaluated sums hi + lo of two f32s, exact to u² relative. The shader forms the
//! grid coordinates with error-free sums and products (`two_sum`, `two_prod` with `fma`), so
//! they carry about 48 bits: for a tile L cells across (relative to the tile origin), the
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

use crate::sync::lock;
use bytemuck::{Pod, Zeroable};
use patchwork_core::model::ids::PatchId;
use patchwork_core::resample::{cpu, Backend, PatchSet, ResolvedPatch, SampleGrid, Surface, BLOCK};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use thiserror::Error;

/// Samples are void at or above this, both in the arena and as a point's x.
const VOID: f32 = f32::MAX;

/// The patch kinds the shader evaluates.
pub const KIND_BILINEAR: u32 = 0;
pub const KIND_EDGE: u32 = 1;
pub const KIND_BICUBIC: u32 = 2;

/// `PATCH_FALLBACK` in the shader.
const PATCH_FALLBACK: u32 = 1;

/// Byte budget of the sample arena before it is emptied and refilled.
pub const DEFAULT_ARENA_BYTES: u64 = 256 << 20;

#[derive(Debug, Error)]
pub enum GpuError {
    #[error("no GPU adapter with compute shaders: {0}")]
    NoAdapter(String),
    #[error("the GPU device could not be created: {0}")]
    Device(String),
    #[error("the GPU device was lost: {0}")]
    Lost(String),
    #[error("the GPU failed: {0}")]
    Failed(String),
    #[error("{0}")]
    TooLarge(String),
}

/// One patch as the shader reads it; see `struct Patch` in `resample.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct GpuPatch {
    origin_hi: [f32; 2],
    origin_lo: [f32; 2],
    col_hi: [f32; 2],
    col_lo: [f32; 2],
    row_hi: [f32; 2],
    row_lo: [f32; 2],
    centre: [f32; 2],
    inv_half: [f32; 2],
    norm: f32,
    base: f32,
    rank: u32,
    flags: u32,
    window: [f32; 4],
    kernel: [f32; 4],
    offset: u32,
    cols: u32,
    rows: u32,
    kind: u32,
    flat: f32,
    /// Where the patch's plane's positions start in the points buffer.
    points: u32,
    _pad: [f32; 2],
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct Params {
    width: u32,
    height: u32,
    blocks_x: u32,
    has_fallback: u32,
    /// 1 where the store plane's positions are a north-up grid's axes (see [`Prepared`]).
    axes: u32,
    _pad: [u32; 3],
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
    /// Binning and packing on the CPU.
    pub prepare: Duration,
    /// Buffer creation and the transfer of samples, points, patches and bins.
    pub upload: Duration,
    /// The dispatch, from submission until the device is idle.
    pub compute: Duration,
    /// Copying the results back and turning them into heights.
    pub readback: Duration,
    pub uploaded_bytes: u64,
    /// Bytes read back: 4 a sample.
    pub read_bytes: u64,
    /// Patches whose samples were uploaded, and those found already on the device.
    pub uploaded_patches: usize,
    pub cached_patches: usize,
}

/// One device and queue, the resampling pipeline, and the samples already on the device.
pub struct GpuResampler {
    device: wgpu::Device,
    queue: wgpu::Queue,
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    info: wgpu::AdapterInfo,
    max_binding: u64,
    budget: u64,
    arena: wgpu::Buffer,
    /// Arena size and use, in f32s.
    arena_len: u64,
    arena_used: u64,
    cache: HashMap<PatchId, Uploaded>,
    /// The per-request buffers, kept from one request to the next.
    pool: Pool,
    /// Errors the device reported outside any scope, and device loss.
    errors: Arc<Mutex<Vec<String>>>,
    lost: Arc<Mutex<Option<String>>>,
}

/// Slots of the [`Pool`]: params, points, patches, bin offsets and bins are uploaded in that
/// order (0–4), then the heights the shader writes and the buffer they are read back through.
const OUT: usize = 5;
const READ: usize = 6;

/// The buffers a request uses, kept between requests and grown (to powers of two) only when
/// one needs more: creating them afresh cost more than the dispatch on a hardware GPU.
#[derive(Default)]
struct Pool {
    buffers: [Option<wgpu::Buffer>; 7],
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
        // Bindings may not be empty; storage sizes must be multiples of 4.
        let size = size.max(16).next_multiple_of(16);
        let b = &mut self.buffers[slot];
        if b.as_ref().is_none_or(|b| b.size() < size) {
            *b = Some(device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(POOL_LABELS[slot]),
                size: size.next_power_of_two(),
                usage,
                mapped_at_creation: false,
            }));
        }
        b.as_ref().expect("set above")
    }
}

const POOL_LABELS: [&str; 7] = [
    "params",
    "points",
    "patches",
    "bin offsets",
    "bins",
    "heights",
    "heights readback",
];

/// The CPU's part of a request: the patches binned into blocks and the sample positions
/// packed for the shader. It needs no device, so it runs before the device is taken.
pub struct Prepared {
    width: usize,
    height: usize,
    /// No valid point or no patch: every height is void, and the device is not needed.
    empty: bool,
    /// The origin positions are relative to, of the store plane and then of each other plane.
    origins: Vec<[f64; 2]>,
    /// Whether the store plane's positions are a north-up grid's axes: its columns' x then
    /// its rows' y (width + height entries), not one entry a sample.
    axes: bool,
    /// Positions as (x hi, y hi, x lo, y lo) relative to their plane's origin: the store
    /// plane's, then every other plane's, one a sample.
    points: Vec<[f32; 4]>,
    offsets: Vec<u32>,
    bins: Vec<u32>,
    took: Duration,
}

impl Prepared {
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

/// Bins the patches of `set` into the grid's blocks and packs the grid's positions for the
/// shader. A north-up grid sends its axes, one entry a column and one a row, not one a
/// sample: the same f64 positions the CPU blends at, each split into two f32s, so both
/// backends work from the same coordinates.
pub fn prepare(set: &PatchSet, grid: &SampleGrid) -> Prepared {
    let t0 = Instant::now();
    let mut p = Prepared {
        width: grid.width,
        height: grid.height,
        empty: true,
        origins: Vec::new(),
        axes: false,
        points: Vec::new(),
        offsets: Vec::new(),
        bins: Vec::new(),
        took: Duration::ZERO,
    };
    let Some(origin) = grid.points().find(|p| !p[0].is_nan() && !p[1].is_nan()) else {
        return p;
    };
    if set.patches.is_empty() {
        return p;
    }
    // The samples' positions in each other plane of the set, each relative to an origin of
    // its own, after the store plane's.
    let planes = set.positions(grid);
    p.origins = std::iter::once(origin)
        .chain(planes.iter().map(|ps| {
            ps.iter()
                .copied()
                .find(|p| !p[0].is_nan() && !p[1].is_nan())
                .unwrap_or([0.0; 2])
        }))
        .collect();
    let bins = cpu::bin(&set.patches, grid);
    p.offsets.reserve(bins.len() + 1);
    p.offsets.push(0u32);
    for b in &bins {
        p.bins.extend_from_slice(b);
        p.offsets.push(p.bins.len() as u32);
    }
    if p.bins.is_empty() {
        // Bindings cannot be empty; the offsets keep the shader from reading this.
        p.bins.push(0);
    }
    let pack = |q: [f64; 2], origin: [f64; 2]| {
        if q[0].is_nan() || q[1].is_nan() {
            [VOID, 0.0, 0.0, 0.0]
        } else {
            let [xh, xl] = split(q[0] - origin[0]);
            let [yh, yl] = split(q[1] - origin[1]);
            [xh, yh, xl, yl]
        }
    };
    match &grid.axes {
        Some(axes) => {
            p.axes = true;
            p.points
                .reserve(grid.width + grid.height + planes.len() * grid.width * grid.height);
            p.points.extend(axes.xs.iter().map(|&x| {
                let [xh, xl] = split(x - origin[0]);
                [xh, 0.0, xl, 0.0]
            }));
            p.points.extend(axes.ys.iter().map(|&y| {
                let [yh, yl] = split(y - origin[1]);
                [0.0, yh, 0.0, yl]
            }));
        }
        None => p.points.extend(grid.points().map(|q| pack(q, origin))),
    }
    for (ps, o) in planes.iter().zip(&p.origins[1..]) {
        p.points.extend(ps.iter().map(|&q| pack(q, *o)));
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
    Refuse,
    Allow,
}

impl GpuResampler {
    pub fn new(emulated: Emulated) -> Result<Self, GpuError> {
        Self::with_budget(DEFAULT_ARENA_BYTES, emulated)
    }

    /// A resampler whose sample arena holds at most `budget` bytes (more only when a single
    /// request needs it).
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
        let errors: Arc<Mutex<Vec<String>>> = Arc::default();
        let lost: Arc<Mutex<Option<String>>> = Arc::default();
        {
            let errors = errors.clone();
            device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
                tracing::error!(error = %e, "GPU error");
                lock(&errors).push(e.to_string());
            }));
            let lost = lost.clone();
            device.set_device_lost_callback(move |reason, msg| {
                *lock(&lost) = Some(format!("{reason:?}: {msg}"));
            });
        }
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("resample.wgsl"),
            source: wgpu::ShaderSource::Wgsl(include_str!("resample.wgsl").into()),
        });
        let entry = |binding, ty| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty,
            count: None,
        };
        let storage = |read_only| wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("resample"),
            entries: &[
                entry(
                    0,
                    wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                ),
                entry(1, storage(true)),
                entry(2, storage(true)),
                entry(3, storage(true)),
                entry(4, storage(true)),
                entry(5, storage(true)),
                entry(6, storage(false)),
            ],
        });
        let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("resample"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("resample"),
            layout: Some(&pl),
            module: &module,
            entry_point: Some("main"),
            compilation_options: Default::default(),
            cache: None,
        });
        let max_binding = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        let budget = budget.min(max_binding);
        let arena_len = (16u64 << 20).min(budget) / 4;
        let arena = arena_buffer(&device, arena_len);
        let g = GpuResampler {
            device,
            queue,
            pipeline,
            layout,
            info,
            max_binding,
            budget,
            arena,
            arena_len,
            arena_used: 0,
            cache: HashMap::new(),
            pool: Pool::default(),
            errors,
            lost,
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

    pub fn resample_timed(
        &mut self,
        set: &PatchSet,
        grid: &SampleGrid,
    ) -> Result<(Vec<f32>, GpuTimings), GpuError> {
        let prepared = prepare(set, grid);
        self.resample_prepared(set, &prepared)
    }

    /// The device's part of a request whose CPU part, [`prepare`], ran already (outside
    /// whatever lock guards this resampler).
    pub fn resample_prepared(
        &mut self,
        set: &PatchSet,
        prep: &Prepared,
    ) -> Result<(Vec<f32>, GpuTimings), GpuError> {
        self.check()?;
        let mut tm = GpuTimings {
            prepare: prep.took,
            ..Default::default()
        };
        let n = prep.width * prep.height;
        if prep.empty {
            return Ok((vec![f32::NAN; n], tm));
        }
        let (bx, by) = (prep.width.div_ceil(BLOCK), prep.height.div_ceil(BLOCK));
        let wg_max = self.device.limits().max_compute_workgroups_per_dimension as usize;
        if (prep.points.len() * 16) as u64 > self.max_binding
            || (n * 4) as u64 > self.max_binding
            || bx > wg_max
            || by > wg_max
        {
            return Err(GpuError::TooLarge(format!(
                "a {}×{} grid is more than this device takes in one dispatch",
                prep.width, prep.height
            )));
        }

        let t0 = Instant::now();
        let (placed, samples) = self.place(set)?;
        let max_norm = set.patches.iter().map(|p| p.norm).fold(0.0f64, f64::max);
        let table: Vec<GpuPatch> = set
            .patches
            .iter()
            .zip(&placed)
            .map(|(p, a)| {
                let k = p.plane as usize;
                gpu_patch(p, a, prep.origins[k], prep.plane_start(k), max_norm)
            })
            .collect();
        tm.prepare += t0.elapsed();

        let t1 = Instant::now();
        tm.uploaded_patches = samples.as_ref().map_or(0, |s| s.1);
        tm.cached_patches = set.patches.len() - tm.uploaded_patches;
        if let Some((data, _)) = &samples {
            tm.uploaded_bytes += (data.len() * 4) as u64;
        }
        self.write_samples(samples.map(|s| s.0))?;
        let params = Params {
            width: prep.width as u32,
            height: prep.height as u32,
            blocks_x: bx as u32,
            has_fallback: u32::from(set.has_fallback),
            axes: u32::from(prep.axes),
            _pad: [0; 3],
        };
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
        let uniform = wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST;
        let out_usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        let read_usage = wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST;
        let uploads: [(&[u8], _); 5] = [
            (bytemuck::bytes_of(&params), uniform),
            (bytemuck::cast_slice(&prep.points), storage),
            (bytemuck::cast_slice(&table), storage),
            (bytemuck::cast_slice(&prep.offsets), storage),
            (bytemuck::cast_slice(&prep.bins), storage),
        ];
        for (slot, (bytes, usage)) in uploads.iter().enumerate() {
            let b = self
                .pool
                .take(&self.device, slot, bytes.len() as u64, *usage);
            self.queue.write_buffer(b, 0, bytes);
            tm.uploaded_bytes += bytes.len() as u64;
        }
        let out_bytes = (n * 4) as u64;
        tm.read_bytes = out_bytes;
        self.pool.take(&self.device, OUT, out_bytes, out_usage);
        self.pool.take(&self.device, READ, out_bytes, read_usage);
        let bufs = &self.pool.buffers;
        let buf = |slot: usize| bufs[slot].as_ref().expect("taken above");
        let bind = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("resample"),
            layout: &self.layout,
            entries: &[
                (0, buf(0)),
                (1, buf(1)),
                (2, buf(2)),
                (3, &self.arena),
                (4, buf(3)),
                (5, buf(4)),
                (6, buf(OUT)),
            ]
            .map(|(binding, b)| wgpu::BindGroupEntry {
                binding,
                resource: b.as_entire_binding(),
            }),
        });
        // Flush the queued writes so that the upload is timed apart from the dispatch.
        self.queue.submit([]);
        self.wait()?;
        tm.upload = t1.elapsed();

        let t2 = Instant::now();
        let mut enc = self.device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(bx as u32, by as u32, 1);
        }
        self.queue.submit([enc.finish()]);
        self.wait()?;
        tm.compute = t2.elapsed();

        let t3 = Instant::now();
        let (out_buf, read_buf) = (buf(OUT), buf(READ));
        let mut enc = self.device.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(out_buf, 0, read_buf, 0, Some(out_bytes));
        self.queue.submit([enc.finish()]);
        let mapped: Arc<Mutex<Option<Result<(), wgpu::BufferAsyncError>>>> = Arc::default();
        {
            let mapped = mapped.clone();
            read_buf.map_async(wgpu::MapMode::Read, ..out_bytes, move |r| {
                *lock(&mapped) = Some(r)
            });
        }
        self.wait()?;
        if let Some(Err(e)) = lock(&mapped).take() {
            return Err(GpuError::Failed(format!("reading the results back: {e}")));
        }
        // The shader writes each height whole, as f32 bits (NaN where void): the sum of the
        // blend and its base rounded once, as the CPU rounds its f64 sum.
        let out = {
            let bytes = read_buf
                .get_mapped_range(..out_bytes)
                .map_err(|e| GpuError::Failed(e.to_string()))?;
            bytemuck::cast_slice::<u8, f32>(&bytes).to_vec()
        };
        read_buf.unmap();
        tm.readback = t3.elapsed();
        Ok((out, tm))
    }

    /// Arena places for every patch of the set, and the samples still to upload (packed to
    /// follow what the arena holds) with how many patches they are.
    #[allow(clippy::type_complexity)]
    fn place(
        &mut self,
        set: &PatchSet,
    ) -> Result<(Vec<Uploaded>, Option<(Vec<f32>, usize)>), GpuError> {
        let missing = |cache: &HashMap<PatchId, Uploaded>| {
            let mut seen = std::collections::HashSet::new();
            set.patches
                .iter()
                .filter(|p| !cache.contains_key(&p.id) && seen.insert(p.id))
                .map(|p| extent(p).len(p))
                .sum::<u64>()
        };
        let mut need = missing(&self.cache);
        if self.arena_used + need > self.budget / 4 {
            self.cache.clear();
            self.arena_used = 0;
            need = missing(&self.cache);
        }
        if need > self.max_binding / 4 {
            return Err(GpuError::TooLarge(format!(
                "the patches of this request need {} MiB of samples, more than the device binds",
                (need * 4) >> 20
            )));
        }
        self.reserve(self.arena_used + need)?;
        let mut data = Vec::with_capacity(need as usize);
        let mut count = 0;
        let placed = set
            .patches
            .iter()
            .map(|p| {
                if let Some(u) = self.cache.get(&p.id) {
                    return *u;
                }
                let u = pack(p, (self.arena_used + data.len() as u64) as u32, &mut data);
                self.cache.insert(p.id, u);
                count += 1;
                u
            })
            .collect();
        Ok((placed, (!data.is_empty()).then_some((data, count))))
    }

    /// Grows the arena to hold `len` f32s, keeping what it holds.
    fn reserve(&mut self, len: u64) -> Result<(), GpuError> {
        if len <= self.arena_len {
            return Ok(());
        }
        let mut new_len = self.arena_len.max(1);
        while new_len < len {
            new_len *= 2;
        }
        let new_len = new_len.min((self.budget / 4).max(len));
        let arena = arena_buffer(&self.device, new_len);
        if self.arena_used > 0 {
            let mut enc = self.device.create_command_encoder(&Default::default());
            enc.copy_buffer_to_buffer(&self.arena, 0, &arena, 0, self.arena_used * 4);
            self.queue.submit([enc.finish()]);
        }
        self.arena = arena;
        self.arena_len = new_len;
        self.check()
    }

    fn write_samples(&mut self, data: Option<Vec<f32>>) -> Result<(), GpuError> {
        if let Some(data) = data {
            self.queue.write_buffer(
                &self.arena,
                self.arena_used * 4,
                bytemuck::cast_slice(&data),
            );
            self.arena_used += data.len() as u64;
        }
        Ok(())
    }

    fn wait(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Failed(e.to_string()))?;
        self.check()
    }

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

fn arena_buffer(device: &wgpu::Device, len: u64) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("sample arena"),
        size: len.max(1) * 4,
        usage: wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_DST
            | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    })
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
    // Where the surface's samples start in its level: a window of a level may begin inside it.
    let (heights, cols, flags, at): (&[f32], usize, Option<&[u8]>, [usize; 2]) = match &p.surface {
        Surface::Bilinear(w) | Surface::Bicubic(w, _) => {
            (&w.grid.samples, w.grid.cols, None, [w.c0, w.r0])
        }
        Surface::Edge(g) => (&g.heights, g.cols, Some(&g.flags), [0, 0]),
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

/// The shader's record of a patch, its first sample relative to `origin`, the origin of its
/// plane's positions, which start at `points` in the points buffer.
fn gpu_patch(
    p: &ResolvedPatch,
    a: &Uploaded,
    origin: [f64; 2],
    points: u32,
    max_norm: f64,
) -> GpuPatch {
    let (c0, r0) = (a.c0 as f64, a.r0 as f64);
    // The first uploaded sample, from the same origin and axes `to_grid` uses.
    let [u, v] = p.axes;
    let o = [
        p.origin[0] + c0 * u[0] / p.inv_step[0] + r0 * v[0] / p.inv_step[1],
        p.origin[1] + c0 * u[1] / p.inv_step[0] + r0 * v[1] / p.inv_step[1],
    ];
    let [xh, xl] = split(o[0] - origin[0]);
    let [yh, yl] = split(o[1] - origin[1]);
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
    GpuPatch {
        origin_hi: [xh, yh],
        origin_lo: [xl, yl],
        col_hi,
        col_lo,
        row_hi,
        row_lo,
        centre: [(p.centre[0] - c0) as f32, (p.centre[1] - r0) as f32],
        inv_half: f2(p.inv_half),
        rank: p.rank,
        flags: if p.fallback { PATCH_FALLBACK } else { 0 },
        // Only ratios of weights matter; scaling keeps them far from f32's range limits.
        norm: (p.norm / max_norm) as f32,
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
        points,
        _pad: [0.0; 2],
    }
}
