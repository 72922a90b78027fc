//! The engine's choice of where a tile is resampled: the GPU device the daemon opened at
//! start-up, when it has one and the request allows it, else the CPU.
//!
//! The device is behind one mutex, since a wgpu queue takes one submission at a time. The
//! mutex guards the device alone: a request gathers its patches' samples (reads from the pack
//! and decodes), bins them and packs its positions before it asks for the device, so that GPU
//! tiles never queue behind each other's disk I/O or CPU work.

use super::{release_free_memory, Engine, EngineError};
use patchwork_core::resample::{Backend, PatchSet, SampleGrid};
#[cfg(feature = "gpu")]
use patchwork_core::sync::lock;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::{Duration, Instant};

#[cfg(feature = "gpu")]
use crate::gpu::{Emulated, GpuError, GpuResampler};

/// The resampler that ran a tile.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Used {
    /// The daemon's GPU device.
    Gpu = 0,
    /// The CPU, in this process's thread pool.
    Cpu = 1,
}

impl Used {
    /// Its name on the wire and in messages: "cpu" or "gpu".
    pub fn as_str(self) -> &'static str {
        match self {
            Used::Cpu => "cpu",
            Used::Gpu => "gpu",
        }
    }
}

/// The GPU device, once opened (empty in a build without the `gpu` feature), and how `auto`
/// chooses between it and the CPU.
#[derive(Default)]
pub(super) struct Device {
    #[cfg(feature = "gpu")]
    resampler: std::sync::Mutex<Option<GpuResampler>>,
    /// The device's adapter while it serves, behind a lock of its own: the device's is held
    /// for a whole dispatch, and asking whether there is a device (every `auto` tile, every
    /// `stats`) must not wait for one.
    adapter: std::sync::Mutex<Option<String>>,
    pub(super) router: Router,
}

/// Where `auto` sends a tile: to the backend expected to finish it first. Each backend keeps
/// the samples in flight on it and its measured cost, in seconds a sample with the work in
/// flight shared out (a moving average over finished tiles); a tile of n samples is expected
/// to finish on a backend after `(in flight + n) × cost`. So a fast device takes the tiles
/// until its queue makes the CPU sooner, and a slow, busy or emulated one takes almost none:
/// the backend not chosen is tried again now and then (every [`RETRY`] at most, and less
/// often the longer it takes), so that its cost follows what it can do now.
#[derive(Default)]
pub(super) struct Router {
    sides: [Side; 2],
}

/// How often, at most, the backend `auto` does not prefer is given a tile to measure it again.
const RETRY: Duration = Duration::from_secs(2);

#[derive(Default)]
struct Side {
    /// Samples of the tiles running on it.
    in_flight: AtomicU64,
    /// Seconds a sample, as f64 bits; 0 until a tile has finished on it.
    cost: AtomicU64,
    /// When it last started a tile, in milliseconds since the router's epoch.
    last_ms: AtomicU64,
}

impl Router {
    /// Whether a tile of `n` samples should go to the device rather than the CPU.
    pub(super) fn prefers_gpu(&self, n: u64) -> bool {
        let [gpu, cpu] = &self.sides;
        let cost = |s: &Side| f64::from_bits(s.cost.load(Relaxed));
        let (cg, cc) = (cost(gpu), cost(cpu));
        // Each side measured once before any comparison: one tile measures the device, and
        // while it runs the others go to the CPU, not into a queue on a device that may turn
        // out to be a hundred times slower (a burst of clients at start-up piled seconds of
        // work on an emulated one).
        if cg == 0.0 {
            return gpu.in_flight.load(Relaxed) == 0;
        }
        if cc == 0.0 {
            return false;
        }
        let finish = |s: &Side, c: f64| (s.in_flight.load(Relaxed) + n) as f64 * c;
        let gpu_first = finish(gpu, cg) <= finish(cpu, cc);
        let (other, c_other) = if gpu_first { (cpu, cc) } else { (gpu, cg) };
        // A retry costs what the tile takes on the slower side (an emulated device takes the
        // CPU's own cores for it): it comes at most every 50 such durations, so that it
        // never costs more than 2% of the time.
        let every = (RETRY.as_secs_f64() * 1e3).max(50.0 * n as f64 * c_other * 1e3) as u64;
        let now = epoch_ms();
        let last = other.last_ms.load(Relaxed);
        if other.in_flight.load(Relaxed) == 0
            && now.saturating_sub(last) >= every
            && other
                .last_ms
                .compare_exchange(last, now, Relaxed, Relaxed)
                .is_ok()
        {
            return !gpu_first;
        }
        gpu_first
    }

    /// Counts a tile of `n` samples as running on `used` until the returned guard is
    /// finished (measured) or dropped (given up: not measured).
    pub(super) fn start(&self, used: Used, n: u64) -> Running<'_> {
        let side = &self.sides[used as usize];
        let ahead = side.in_flight.fetch_add(n, Relaxed);
        side.last_ms.store(epoch_ms(), Relaxed);
        Running {
            side,
            n,
            shared: ahead + n,
            t0: Instant::now(),
            paused: Duration::ZERO,
        }
    }
}

/// A tile running on one backend.
pub(super) struct Running<'a> {
    side: &'a Side,
    n: u64,
    /// Samples in flight on the backend when it started, its own included.
    shared: u64,
    t0: Instant,
    /// Time spent outside the backend (handing bands to the client), not counted.
    paused: Duration,
}

impl Running<'_> {
    /// Leaves `d` out of the measured time.
    pub(super) fn pause(&mut self, d: Duration) {
        self.paused += d;
    }

    /// The tile finished: its time, the work in flight shared out, moves the cost.
    pub(super) fn finish(self) {
        let busy = self.t0.elapsed().saturating_sub(self.paused).as_secs_f64();
        let c = busy / self.shared.max(1) as f64;
        let _ = self.side.cost.fetch_update(Relaxed, Relaxed, |old| {
            let old = f64::from_bits(old);
            Some(if old == 0.0 { c } else { 0.8 * old + 0.2 * c }.to_bits())
        });
    }
}

impl Drop for Running<'_> {
    fn drop(&mut self) {
        self.side.in_flight.fetch_sub(self.n, Relaxed);
    }
}

fn epoch_ms() -> u64 {
    static EPOCH: std::sync::OnceLock<Instant> = std::sync::OnceLock::new();
    // Offset by RETRY so that the first retry is never held back by a zero start.
    EPOCH.get_or_init(Instant::now).elapsed().as_millis() as u64 + RETRY.as_millis() as u64
}

impl Engine {
    /// Opens the GPU device the daemon resamples on, once, at start-up. Without an adapter
    /// (or in a build without the `gpu` feature) the daemon says so and resamples on the CPU.
    pub fn enable_gpu(&self) {
        #[cfg(feature = "gpu")]
        {
            let emulated = if self.cfg.allow_emulated_gpu {
                Emulated::Allow
            } else {
                Emulated::Refuse
            };
            match GpuResampler::new(emulated) {
                Ok(g) => {
                    tracing::info!(adapter = %g.adapter(), "resampling on the GPU");
                    *patchwork_core::sync::lock(&self.gpu.adapter) = Some(g.adapter());
                    *lock(&self.gpu.resampler) = Some(g);
                }
                Err(e) => tracing::info!(reason = %e, "no GPU device: resampling on the CPU"),
            }
            // A refused software driver leaves its libraries' heap behind.
            release_free_memory();
        }
        #[cfg(not(feature = "gpu"))]
        tracing::info!("built without the gpu feature: resampling on the CPU");
    }

    /// Whether a GPU device serves.
    pub(super) fn has_gpu(&self) -> bool {
        patchwork_core::sync::lock(&self.gpu.adapter).is_some()
    }

    /// "cpu", or "gpu (adapter)".
    pub(super) fn backend_name(&self) -> String {
        match patchwork_core::sync::lock(&self.gpu.adapter).as_ref() {
            Some(a) => format!("gpu ({a})"),
            None => "cpu".into(),
        }
    }

    /// The heights of `grid` from the GPU when `backend` allows it and the device serves:
    /// None to resample on the CPU instead, an error when the GPU was required and cannot.
    /// A device that is lost is dropped, and later requests go to the CPU.
    pub(super) fn gpu_heights(
        &self,
        set: &PatchSet,
        grid: &SampleGrid,
        backend: Backend,
    ) -> Result<Option<Vec<f32>>, EngineError> {
        if backend == Backend::Cpu {
            return Ok(None);
        }
        #[cfg(feature = "gpu")]
        if self.has_gpu() {
            // Binning and packing need no device: done before taking it, so that requests
            // queue on the device only for the device's own work. The device is held only to
            // queue the request's uploads and dispatches; the wait for its heights and their
            // readback are outside, so the next request is queued while this one runs.
            let prepared = crate::gpu::prepare(set, grid);
            let submitted = lock(&self.gpu.resampler)
                .as_mut()
                .map(|g| g.submit(set, prepared));
            if let Some(submitted) = submitted {
                match submitted.and_then(|s| s.wait()) {
                    Ok((heights, _)) => return Ok(Some(heights)),
                    Err(e) => {
                        tracing::warn!(error = %e, "GPU resampling failed; this request and later ones use the CPU");
                        if matches!(e, GpuError::Lost(_) | GpuError::Device(_)) {
                            *lock(&self.gpu.resampler) = None;
                            *patchwork_core::sync::lock(&self.gpu.adapter) = None;
                        }
                        if backend == Backend::Gpu {
                            return Err(EngineError::Gpu(e.to_string()));
                        }
                        return Ok(None);
                    }
                }
            }
        }
        #[cfg(not(feature = "gpu"))]
        let _ = (set, grid, release_free_memory);
        if backend == Backend::Gpu {
            return Err(EngineError::NoGpu);
        }
        Ok(None)
    }

    /// Holds the GPU device's lock, as a request resampling on it does (for tests of what
    /// waits on it).
    #[cfg(all(test, feature = "gpu"))]
    pub(super) fn hold_gpu(&self) -> std::sync::MutexGuard<'_, Option<GpuResampler>> {
        lock(&self.gpu.resampler)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn router(gpu: f64, cpu: f64) -> Router {
        let r = Router::default();
        r.sides[0].cost.store(gpu.to_bits(), Relaxed);
        r.sides[1].cost.store(cpu.to_bits(), Relaxed);
        // Both measured just now: no retry is due.
        for side in &r.sides {
            side.last_ms.store(epoch_ms(), Relaxed);
        }
        r
    }

    #[test]
    fn each_backend_is_measured_before_they_are_compared() {
        let r = Router::default();
        assert!(r.prefers_gpu(1000), "the device first");
        let first = r.start(Used::Gpu, 1000);
        assert!(
            !r.prefers_gpu(1000),
            "the CPU while the device's first tile runs"
        );
        first.finish();
        assert!(!r.prefers_gpu(1000), "then the CPU");
        r.start(Used::Cpu, 1000).finish();
        assert!(f64::from_bits(r.sides[1].cost.load(Relaxed)) > 0.0);
    }

    #[test]
    fn a_slow_device_gets_only_the_tiles_that_measure_it_again() {
        // An emulated device ten times slower than the cores.
        let r = router(1e-6, 1e-7);
        let to_gpu = (0..1000).filter(|_| r.prefers_gpu(262_144)).count();
        assert!(
            to_gpu <= 1,
            "{to_gpu} of 1000 tiles went to the slow device"
        );
    }

    #[test]
    fn a_fast_device_takes_tiles_until_its_queue_makes_the_cpu_sooner() {
        // A device thirty times faster than the cores.
        let r = router(1e-9, 3e-8);
        let n = 262_144;
        assert!(r.prefers_gpu(n));
        let queued: Vec<_> = (0..40).map(|_| r.start(Used::Gpu, n)).collect();
        // 40 tiles ahead on the device finish later than one on the idle CPU.
        assert!(!r.prefers_gpu(n));
        drop(queued);
        assert!(r.prefers_gpu(n));
    }

    #[test]
    fn a_tile_given_up_is_not_measured_but_leaves_the_queue() {
        let r = router(1e-9, 1e-8);
        let run = r.start(Used::Gpu, 5000);
        assert_eq!(r.sides[0].in_flight.load(Relaxed), 5000);
        drop(run);
        assert_eq!(r.sides[0].in_flight.load(Relaxed), 0);
        assert_eq!(f64::from_bits(r.sides[0].cost.load(Relaxed)), 1e-9);
    }
}
