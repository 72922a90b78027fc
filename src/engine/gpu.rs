//! The engine's choice of where a tile is resampled: the GPU device the daemon opened at
//! start-up, when it has one and the request allows it, else the CPU.
//!
//! The device is behind one mutex, since a wgpu queue takes one submission at a time. The
//! mutex guards the device alone: a request gathers its patches' samples (reads from the pack
//! and decodes), bins them and packs its positions before it asks for the device, so that GPU
//! tiles never queue behind each other's disk I/O or CPU work.

use super::{release_free_memory, Engine, EngineError};
#[cfg(feature = "gpu")]
use crate::sync::lock;
use patchwork_core::resample::{Backend, PatchSet, SampleGrid};

#[cfg(feature = "gpu")]
use crate::gpu::{Emulated, GpuError, GpuResampler};

/// The resampler that ran a tile.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Used {
    /// The CPU, in this process's thread pool.
    Cpu,
    /// The daemon's GPU device.
    Gpu,
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

/// The GPU device, once opened; empty in a build without the `gpu` feature.
#[derive(Default)]
pub(super) struct Device {
    #[cfg(feature = "gpu")]
    resampler: std::sync::Mutex<Option<GpuResampler>>,
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

    /// "cpu", or "gpu (adapter)".
    pub(super) fn backend_name(&self) -> String {
        #[cfg(feature = "gpu")]
        if let Some(g) = lock(&self.gpu.resampler).as_ref() {
            return format!("gpu ({})", g.adapter());
        }
        "cpu".into()
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
        if lock(&self.gpu.resampler).is_some() {
            // Binning and packing need no device: done before taking it, so that requests
            // queue on the device only for the device's own work.
            let prepared = crate::gpu::prepare(set, grid);
            let mut gpu = lock(&self.gpu.resampler);
            if let Some(g) = gpu.as_mut() {
                match g.resample_prepared(set, &prepared) {
                    Ok((heights, _)) => return Ok(Some(heights)),
                    Err(e) => {
                        tracing::warn!(error = %e, "GPU resampling failed; this request and later ones use the CPU");
                        if matches!(e, GpuError::Lost(_) | GpuError::Device(_)) {
                            *gpu = None;
                        }
                        if backend == Backend::Gpu {
                            return Err(EngineError::Unavailable(format!(
                                "GPU resampling failed: {e}"
                            )));
                        }
                        return Ok(None);
                    }
                }
            }
        }
        #[cfg(not(feature = "gpu"))]
        let _ = (set, grid, release_free_memory);
        if backend == Backend::Gpu {
            return Err(EngineError::Unavailable(
                "backend gpu was asked for, but this daemon has no GPU device; use auto or cpu"
                    .into(),
            ));
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
