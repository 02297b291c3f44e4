//! How often each pass ran: the proof that work a scene does not need is skipped.
//!
//! The render world counts every dispatch of each pass into [`CloudPassCounters`], a resource
//! shared (behind an `Arc`) by the main and render worlds. The counts only grow, so any number of
//! readers can each keep their own snapshot and ask for the runs since it
//! ([`CloudPassCounters::since`]). GPU times come from Bevy's render diagnostics
//! (`RenderDiagnosticsPlugin`), under the paths [`CloudPass::diagnostic_paths`].

use std::sync::{
    Arc, Mutex,
    atomic::{AtomicU32, Ordering},
};

use bevy::{diagnostic::DiagnosticPath, prelude::*, render::extract_resource::ExtractResource};

/// Number of [`CloudPass`]es.
pub const PASSES: usize = 7;

/// The stages of the renderer, in the order they run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Reflect)]
pub enum CloudPass {
    /// Particles → density volume, per cloud.
    Voxelize,
    /// Light-aligned transmittance volume, per cloud and light (its time and dispatches include
    /// the cast of other clouds' shadows).
    Shade,
    /// All lights into one single-scattering volume, per cloud.
    Gather,
    /// Multiple-scattering iterations, per cloud (one count per iteration; its time and
    /// dispatches include the overlap of other clouds' media).
    Scatter,
    /// Back-to-front particle sort, per cloud and view (`Compositing::Sorted`).
    Sort,
    /// Optical depth from the camera, per cloud and view (`Compositing::ViewTransmittance`).
    ViewVolume,
    /// Billboard draw, per cloud and view.
    Draw,
}

impl CloudPass {
    /// Every pass, in the order they run.
    pub const ALL: [CloudPass; PASSES] = [
        Self::Voxelize,
        Self::Shade,
        Self::Gather,
        Self::Scatter,
        Self::Sort,
        Self::ViewVolume,
        Self::Draw,
    ];

    /// The lower-case name used in statistics files.
    pub fn name(self) -> &'static str {
        match self {
            Self::Voxelize => "voxelize",
            Self::Shade => "shade",
            Self::Gather => "gather",
            Self::Scatter => "scatter",
            Self::Sort => "sort",
            Self::ViewVolume => "view_volume",
            Self::Draw => "draw",
        }
    }

    /// The name of this pass's GPU time span.
    pub fn span_name(self) -> &'static str {
        match self {
            Self::Voxelize => "particle_clouds_voxelize",
            Self::Shade => "particle_clouds_shade",
            Self::Gather => "particle_clouds_gather",
            Self::Scatter => "particle_clouds_scatter",
            Self::Sort => "particle_clouds_sort",
            Self::ViewVolume => "particle_clouds_view_volume",
            Self::Draw => "particle_clouds_draw",
        }
    }

    /// The diagnostics holding this pass's GPU time in milliseconds (needs `RenderDiagnosticsPlugin`
    /// and an adapter with timestamp queries). The draw has two: its spans nested in Bevy's span of
    /// the transparent pass (at full size), and the span of a view's cloud target (its draw and
    /// composite, `cloud_target_scale` below 1).
    pub fn diagnostic_paths(self) -> Vec<DiagnosticPath> {
        let top_level =
            DiagnosticPath::from_components(["render", self.span_name(), "elapsed_gpu"]);
        match self {
            Self::Draw => vec![
                DiagnosticPath::from_components([
                    "render",
                    "main_transparent_pass_3d",
                    self.span_name(),
                    "elapsed_gpu",
                ]),
                top_level,
            ],
            _ => vec![top_level],
        }
    }
}

/// Run and dispatch counters per pass, shared by the main and the render world.
///
/// A *run* is a unit of a pass's work (a cloud voxelized, a light shaded, a scattering iteration,
/// a cloud drawn in a view); a *dispatch* is one compute dispatch. The illumination passes batch
/// every cloud of a volume shape into one dispatch, so their dispatches grow with the shapes in
/// use, not with the clouds (docs/illumination.md §9).
#[derive(Resource, ExtractResource, Clone, Default, Debug)]
pub struct CloudPassCounters(Arc<PassCounts>);

#[derive(Default, Debug)]
struct PassCounts {
    runs: [AtomicU32; PASSES],
    dispatches: [AtomicU32; PASSES],
    /// Writes of what the billboards read made outside a counted dispatch (queue writes, clears).
    writes: AtomicU32,
    /// The render world's last census of the crate's GPU memory.
    gpu_memory: Mutex<CloudGpuMemory>,
}

/// The GPU memory the crate holds, bytes, as the render world counted it at the end of its last
/// frame ([`CloudPassCounters::gpu_memory`]): buffers and textures its resources and components
/// keep between frames, each buffer once. Per-frame transients are left out.
#[derive(Clone, Copy, Default, Debug, PartialEq, Eq, Reflect)]
pub struct CloudGpuMemory {
    /// The volume pools' buffers (every cloud's volumes, by shape) and their sweeps' pair volumes.
    pub volume_pools: u64,
    /// The voxelization's scratch, kept between frames while any cloud exists.
    pub voxelize_scratch: u64,
    /// The particles of every `Particles` asset on the GPU.
    pub particles: u64,
    /// Per cloud: its uniforms, its sorts and view volumes' uniforms, its draw's buffers.
    pub per_cloud: u64,
    /// Per view: its view-volume atlas, its cloud target and sums, its splat batches.
    pub per_view: u64,
}

impl CloudGpuMemory {
    /// All of it, bytes.
    pub fn total(&self) -> u64 {
        self.volume_pools + self.voxelize_scratch + self.particles + self.per_cloud + self.per_view
    }
}

/// The growth of `counts` since `snapshot`, which is then moved to now.
fn counted_since(
    counts: &[AtomicU32; PASSES],
    snapshot: &mut [u32; PASSES],
) -> [(CloudPass, u32); PASSES] {
    CloudPass::ALL.map(|p| {
        let now = counts[p as usize].load(Ordering::Relaxed);
        let runs = now.wrapping_sub(snapshot[p as usize]);
        snapshot[p as usize] = now;
        (p, runs)
    })
}

impl CloudPassCounters {
    /// Adds `n` runs of `pass`.
    pub fn add(&self, pass: CloudPass, n: u32) {
        self.0.runs[pass as usize].fetch_add(n, Ordering::Relaxed);
    }

    /// Adds `n` compute dispatches of `pass`.
    pub fn add_dispatches(&self, pass: CloudPass, n: u32) {
        self.0.dispatches[pass as usize].fetch_add(n, Ordering::Relaxed);
    }

    /// The runs of each pass since the reader's `snapshot`, which is then moved to now. Start
    /// from `[0; PASSES]` to count from the app's start.
    pub fn since(&self, snapshot: &mut [u32; PASSES]) -> [(CloudPass, u32); PASSES] {
        counted_since(&self.0.runs, snapshot)
    }

    /// Notes a write of what the billboards read that no counted dispatch makes (a uniform or a
    /// volume written from the CPU, a volume cleared).
    pub(crate) fn note_write(&self) {
        self.0.writes.fetch_add(1, Ordering::Relaxed);
    }

    /// A number that changes whenever any pass but the draw records work or something the
    /// billboards read is written ([`CloudPassCounters::note_write`]): while it holds, a view's
    /// clouds read what they read when it last drew them (`CloudRedraw`).
    pub(crate) fn illumination_epoch(&self) -> u64 {
        let before_draw = |counts: &[AtomicU32; PASSES]| {
            (CloudPass::ALL.iter())
                .filter(|&&p| p != CloudPass::Draw)
                .map(|&p| counts[p as usize].load(Ordering::Relaxed) as u64)
                .sum::<u64>()
        };
        before_draw(&self.0.runs)
            + before_draw(&self.0.dispatches)
            + self.0.writes.load(Ordering::Relaxed) as u64
    }

    /// The GPU memory the crate held at the end of the render world's last frame.
    pub fn gpu_memory(&self) -> CloudGpuMemory {
        *self.0.gpu_memory.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub(crate) fn set_gpu_memory(&self, memory: CloudGpuMemory) {
        *self.0.gpu_memory.lock().unwrap_or_else(|e| e.into_inner()) = memory;
    }

    /// The compute dispatches of each pass since the reader's `snapshot` (a snapshot of its
    /// own, apart from the runs'), which is then moved to now.
    pub fn dispatches_since(&self, snapshot: &mut [u32; PASSES]) -> [(CloudPass, u32); PASSES] {
        counted_since(&self.0.dispatches, snapshot)
    }
}
