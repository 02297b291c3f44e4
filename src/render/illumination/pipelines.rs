//! Compute pipelines of the illumination passes, created once in `RenderStartup`.

use crate::render::{
    core::gpu::{
        DYNAMIC_UNIFORM_STRIDE, dynamic_uniform, indexed_layout, sequential_layout, uniform_bytes,
    },
    core::shaders::CloudShaders,
    core::types::DensityLevels,
    extract::ExtractedCloudLights,
};
use std::num::NonZeroU64;

use crate::settings::SweepDispatch;
use bevy::{
    prelude::*,
    render::{
        render_resource::{
            BindGroupLayoutDescriptor, Buffer, CachedComputePipelineId, ComputePipeline,
            ComputePipelineDescriptor, PipelineCache, ShaderStages,
            binding_types::{
                storage_buffer_read_only_sized, storage_buffer_sized, uniform_buffer,
                uniform_buffer_sized,
            },
        },
        renderer::{RenderDevice, RenderQueue},
    },
    shader::Shader,
};

use crate::render::illumination::scatter::sweep::sweep_direction_entries;
use crate::render::illumination::voxelize::VOXELIZE_PASSES;

// The sweep's directions lived here before `scatter/sweep.rs`; their public paths stay.
pub use crate::render::illumination::scatter::sweep::{
    MAX_SWEEP_PAIRS, SWEEP_DIRECTIONS_BINDING, SweepDirection, sweep_direction_offset, sweep_lines,
};

/// One compute pipeline with its (single) bind group layout.
pub struct ComputeStage {
    /// Its bind group layout (group 0).
    pub layout: BindGroupLayoutDescriptor,
    /// The queued pipeline.
    pub pipeline: CachedComputePipelineId,
}

impl ComputeStage {
    fn new(
        pipeline_cache: &PipelineCache,
        shader: Handle<Shader>,
        entry_point: &'static str,
        layout: BindGroupLayoutDescriptor,
    ) -> Self {
        Self::specialized(pipeline_cache, shader, entry_point, layout, false, &[])
    }

    /// With `moments`, compiled with the shader def `MOMENTS`: for pools whose scattering
    /// volumes hold angular moments beside their means (docs/illumination.md §4, §9); and with
    /// the shader defs `defs`.
    fn specialized(
        pipeline_cache: &PipelineCache,
        shader: Handle<Shader>,
        entry_point: &'static str,
        layout: BindGroupLayoutDescriptor,
        moments: bool,
        defs: &[&'static str],
    ) -> Self {
        let mut shader_defs = crate::render::core::workgroups::shader_defs();
        if moments {
            shader_defs.push("MOMENTS".into());
        }
        shader_defs.extend(defs.iter().map(|&d| d.into()));
        let variant = if moments { "_moments" } else { "" };
        let extra: String = defs
            .iter()
            .map(|d| format!("_{}", d.to_lowercase()))
            .collect();
        let pipeline = pipeline_cache.queue_compute_pipeline(ComputePipelineDescriptor {
            label: Some(format!("particle_clouds_{entry_point}{variant}{extra}").into()),
            layout: vec![layout.clone()],
            shader,
            shader_defs,
            entry_point: Some(entry_point.into()),
            ..default()
        });
        Self { layout, pipeline }
    }

    /// The compiled pipeline, once ready.
    pub fn get<'a>(&self, pipeline_cache: &'a PipelineCache) -> Option<&'a ComputePipeline> {
        pipeline_cache.get_compute_pipeline(self.pipeline)
    }
}

/// A stage of the scattering volumes, compiled for pools without angular moments (index 0) and
/// with them (index 1, shader def `MOMENTS`): an isotropic cloud runs exactly the isotropic code.
pub struct ByMoments(pub [ComputeStage; 2]);

impl ByMoments {
    fn new(
        cache: &PipelineCache,
        shader: &Handle<Shader>,
        entry: &'static str,
        layout: &BindGroupLayoutDescriptor,
    ) -> Self {
        Self::with_defs(cache, shader, entry, layout, &[])
    }

    /// Both variants compiled with the shader defs `defs` too.
    fn with_defs(
        cache: &PipelineCache,
        shader: &Handle<Shader>,
        entry: &'static str,
        layout: &BindGroupLayoutDescriptor,
        defs: &[&'static str],
    ) -> Self {
        Self([false, true].map(|moments| {
            let layout = layout.clone();
            ComputeStage::specialized(cache, shader.clone(), entry, layout, moments, defs)
        }))
    }

    /// The stage for a pool with `moments` or without (both share one bind group layout).
    pub fn stage(&self, moments: bool) -> &ComputeStage {
        &self.0[moments as usize]
    }

    fn get<'a>(&self, cache: &'a PipelineCache) -> Option<[&'a ComputePipeline; 2]> {
        Some([self.0[0].get(cache)?, self.0[1].get(cache)?])
    }
}

/// The pipelines of the illumination passes.
#[derive(Resource)]
pub struct IlluminationPipelines {
    /// `voxelize.wgsl`'s passes, one layout ([`VOXELIZE_PASSES`]).
    pub voxelize: [ComputeStage; VOXELIZE_PASSES.len()],
    /// `shade.wgsl`, `shade` (incremental).
    pub shade: ComputeStage,
    /// `shade.wgsl`, `shade_brute_force` (benchmarks).
    pub shade_brute_force: ComputeStage,
    /// `cast.wgsl`, `cast_shadows`: other clouds' shadows added to the light volumes.
    pub cast: ComputeStage,
    /// `sky_map.wgsl`, `march_sky`: the clouds' optical depths along the sky map's directions.
    pub march_sky: ComputeStage,
    /// `sky_map.wgsl`, `resolve_sky` (same layout): the sky map's occlusion from them.
    pub resolve_sky: ComputeStage,
    /// `gather.wgsl`, `gather`.
    pub gather: ByMoments,
    /// `overlap.wgsl`, `overlap_media`: other clouds' media in a cloud's scattering grid.
    pub overlap: ComputeStage,
    /// `ground.wgsl`, `ground_radiance`: the radiance of the ground under each cloud.
    pub ground: ComputeStage,
    /// `scatter.wgsl`, `sweep` (the discrete-ordinates stencil): its serial march (index 0) and
    /// its march that reads ahead (1, shader def `SWEEP_READ_AHEAD`; [`SweepMarch`](crate::settings::SweepMarch)).
    pub sweep: [ByMoments; 2],
    /// `scatter.wgsl`, `accumulate_order`: an iteration's order added to `multiple` after its
    /// sweeps (same layout).
    pub accumulate_order: ByMoments,
    /// `scatter.wgsl`, `scatter_paper` (the paper's stencil; same layout as `sweep`).
    pub scatter_paper: ComputeStage,
    /// `scatter.wgsl`, `warm_start` (a warm restart's start; same layout).
    pub warm_start: ByMoments,
    /// `scatter.wgsl`, `warm_correction` (a warm restart's first order; same layout).
    pub warm_correction: ByMoments,
    /// `closure.wgsl`, `order_sizes`: the sizes of orders `M - 3` and `M - 2`.
    pub order_sizes: ComputeStage,
    /// `closure.wgsl`, `order_ratio` (same layout as `order_sizes`).
    pub order_ratio: ComputeStage,
    /// `closure.wgsl`, `extrapolate` (same layout as `order_ratio`).
    pub extrapolate: ByMoments,
    /// `coarse_grid.wgsl`, `restrict_media`: the coarse grids' media, before the cycles.
    pub restrict_media: ComputeStage,
    /// `coarse_grid.wgsl`, `restrict_residual`: a coarse-grid cycle's start.
    pub restrict_residual: ByMoments,
    /// `coarse_grid.wgsl`, `prolong_correction`: its correction added.
    pub prolong_correction: ByMoments,
    /// The 62 `SweepDirection`s (13 and 49) in each of the four sets of [`sweep_direction_offset`]
    /// (accumulating or not, bringing the sky in or not), `DYNAMIC_UNIFORM_STRIDE` bytes apart (a
    /// dynamic uniform; `write_sweep_sky` writes the sky into them).
    pub sweep_directions: Buffer,
    /// The sky radiance the sweep directions hold.
    pub sweep_sky: Vec3,
}

/// The compiled pipelines of every illumination pass (brute-force shading aside); those of the
/// scattering volumes for pools without angular moments and with them ([`ByMoments`]).
pub struct ReadyPipelines<'a> {
    /// Voxelize's passes ([`VOXELIZE_PASSES`]).
    pub voxelize: [&'a ComputePipeline; VOXELIZE_PASSES.len()],
    /// Cast.
    pub cast: &'a ComputePipeline,
    /// The sky map's march.
    pub march_sky: &'a ComputePipeline,
    /// The sky map's resolve.
    pub resolve_sky: &'a ComputePipeline,
    /// Gather.
    pub gather: [&'a ComputePipeline; 2],
    /// Overlap.
    pub overlap: &'a ComputePipeline,
    /// The ground's radiance.
    pub ground: &'a ComputePipeline,
    /// Sweep, with the march in use.
    pub sweep: [&'a ComputePipeline; 2],
    /// The sweeps' accumulation into `multiple`.
    pub accumulate_order: [&'a ComputePipeline; 2],
    /// The paper's stencil.
    pub scatter_paper: &'a ComputePipeline,
    /// A warm restart's start.
    pub warm_start: [&'a ComputePipeline; 2],
    /// A warm restart's first order.
    pub warm_correction: [&'a ComputePipeline; 2],
    /// The closure's early order sizes.
    pub order_sizes: &'a ComputePipeline,
    /// The closure's ratio.
    pub order_ratio: &'a ComputePipeline,
    /// The closure's extrapolation.
    pub extrapolate: [&'a ComputePipeline; 2],
    /// The coarse grids' media.
    pub restrict_media: &'a ComputePipeline,
    /// The coarse-grid cycles' restriction.
    pub restrict_residual: [&'a ComputePipeline; 2],
    /// The coarse-grid cycles' prolongation.
    pub prolong_correction: [&'a ComputePipeline; 2],
    /// The sweep of one dispatch per order and its sum, where asked for
    /// ([`SweepDispatch::PerOrder`]).
    pub per_order: Option<PerOrderReady<'a>>,
}

/// The compiled pipelines of one dispatch per order.
#[derive(Clone, Copy)]
pub struct PerOrderReady<'a> {
    /// Every pair's sweep, with the march in use.
    pub sweep: [&'a ComputePipeline; 2],
    /// Their sum into the next order.
    pub sum_pairs: [&'a ComputePipeline; 2],
}

/// The pipelines of one dispatch per order ([`SweepDispatch::PerOrder`]): queued the first time
/// it is asked for, so that apps that never ask compile none of them.
#[derive(Resource)]
pub struct PerOrderSweepPipelines {
    /// `scatter.wgsl`, `sweep` with `SWEEP_PER_ORDER`: the serial march (0), reading ahead (1).
    pub sweep: [ByMoments; 2],
    /// `scatter.wgsl`, `sum_pairs` (the sweep's layout).
    pub sum_pairs: ByMoments,
}

impl PerOrderSweepPipelines {
    fn ready<'a>(&self, cache: &'a PipelineCache, read_ahead: bool) -> Option<PerOrderReady<'a>> {
        Some(PerOrderReady {
            sweep: self.sweep[read_ahead as usize].get(cache)?,
            sum_pairs: self.sum_pairs.get(cache)?,
        })
    }
}

/// Queues [`PerOrderSweepPipelines`] once [`SweepDispatch::PerOrder`] is asked for.
pub(crate) fn queue_per_order_sweep(
    mut commands: Commands,
    dispatch: Option<Res<SweepDispatch>>,
    queued: Option<Res<PerOrderSweepPipelines>>,
    shaders: Res<CloudShaders>,
    pipeline_cache: Res<PipelineCache>,
) {
    if queued.is_some() || dispatch.is_none_or(|d| *d != SweepDispatch::PerOrder) {
        return;
    }
    let cache = pipeline_cache.as_ref();
    let layout = IlluminationLayouts::new().scatter;
    let stage = |entry, defs: &[&'static str]| {
        ByMoments::with_defs(cache, &shaders.scatter, entry, &layout, defs)
    };
    commands.insert_resource(PerOrderSweepPipelines {
        sweep: [
            stage("sweep", &["SWEEP_PER_ORDER"]),
            stage("sweep", &["SWEEP_PER_ORDER", "SWEEP_READ_AHEAD"]),
        ],
        sum_pairs: stage("sum_pairs", &["SWEEP_PER_ORDER"]),
    });
}

impl IlluminationPipelines {
    /// All compiled, or `None` while any still compiles (work waits for the next frame); the
    /// sweep's march that reads ahead, or its serial one.
    /// With `per_order` (the pipelines of one dispatch per order, where asked for), those too.
    pub fn ready<'a>(
        &self,
        cache: &'a PipelineCache,
        read_ahead: bool,
        per_order: Option<&PerOrderSweepPipelines>,
    ) -> Option<ReadyPipelines<'a>> {
        let per_order = match per_order {
            Some(p) => Some(p.ready(cache, read_ahead)?),
            None => None,
        };
        Some(ReadyPipelines {
            per_order,
            voxelize: every_ready(&self.voxelize, cache)?,
            cast: self.cast.get(cache)?,
            march_sky: self.march_sky.get(cache)?,
            resolve_sky: self.resolve_sky.get(cache)?,
            gather: self.gather.get(cache)?,
            overlap: self.overlap.get(cache)?,
            ground: self.ground.get(cache)?,
            sweep: self.sweep[read_ahead as usize].get(cache)?,
            accumulate_order: self.accumulate_order.get(cache)?,
            scatter_paper: self.scatter_paper.get(cache)?,
            warm_start: self.warm_start.get(cache)?,
            warm_correction: self.warm_correction.get(cache)?,
            order_sizes: self.order_sizes.get(cache)?,
            order_ratio: self.order_ratio.get(cache)?,
            extrapolate: self.extrapolate.get(cache)?,
            restrict_media: self.restrict_media.get(cache)?,
            restrict_residual: self.restrict_residual.get(cache)?,
            prolong_correction: self.prolong_correction.get(cache)?,
        })
    }
}

/// Writes the sky's radiance into the sweep directions when it changed.
pub(crate) fn write_sweep_sky(
    mut pipelines: ResMut<IlluminationPipelines>,
    lights: Res<ExtractedCloudLights>,
    queue: Res<RenderQueue>,
) {
    if pipelines.sweep_sky == lights.sky {
        return;
    }
    pipelines.sweep_sky = lights.sky;
    for (i, entry) in sweep_direction_entries(lights.sky).enumerate() {
        queue.write_buffer(
            &pipelines.sweep_directions,
            i as u64 * DYNAMIC_UNIFORM_STRIDE as u64,
            &uniform_bytes(&entry),
        );
    }
}

/// Every stage's pipeline, once all are compiled.
fn every_ready<'a, const N: usize>(
    stages: &[ComputeStage; N],
    cache: &'a PipelineCache,
) -> Option<[&'a ComputePipeline; N]> {
    let ready: Vec<_> = stages.iter().map(|s| s.get(cache)).collect::<Option<_>>()?;
    ready.try_into().ok()
}

/// The bind group layouts of the illumination passes, one per shader (its entry points share it),
/// but for the coarse grids', whose entry points bind a subset each.
struct IlluminationLayouts {
    voxelize: BindGroupLayoutDescriptor,
    shade: BindGroupLayoutDescriptor,
    cast: BindGroupLayoutDescriptor,
    sky_map: BindGroupLayoutDescriptor,
    gather: BindGroupLayoutDescriptor,
    scatter: BindGroupLayoutDescriptor,
    ground: BindGroupLayoutDescriptor,
    overlap: BindGroupLayoutDescriptor,
    closure: BindGroupLayoutDescriptor,
    coarse_media: BindGroupLayoutDescriptor,
    coarse_residual: BindGroupLayoutDescriptor,
    coarse_prolongation: BindGroupLayoutDescriptor,
}

impl IlluminationLayouts {
    fn new() -> Self {
        let read = || storage_buffer_read_only_sized(false, None);
        let write = || storage_buffer_sized(false, None);
        // The batched passes' work list, a chunk of it per dispatch (illumination.rs, `WorkList`).
        let work = || storage_buffer_read_only_sized(true, None);
        Self {
            voxelize: sequential_layout(
                "particle_clouds_voxelize_layout",
                ShaderStages::COMPUTE,
                (
                    read(),
                    read(),
                    write(),
                    write(),
                    uniform_buffer::<DensityLevels>(true),
                    work(),
                    write(),
                    write(),
                    write(),
                ),
            ),
            shade: sequential_layout(
                "particle_clouds_shade_layout",
                ShaderStages::COMPUTE,
                (read(), read(), read(), write(), write(), work()),
            ),
            cast: sequential_layout(
                "particle_clouds_cast_layout",
                ShaderStages::COMPUTE,
                (read(), write(), read(), read(), work()),
            ),
            sky_map: sequential_layout(
                "particle_clouds_sky_map_layout",
                ShaderStages::COMPUTE,
                (read(), read(), read(), write(), read(), write(), read()),
            ),
            gather: sequential_layout(
                "particle_clouds_gather_layout",
                ShaderStages::COMPUTE,
                (read(), read(), read(), write(), write(), work()),
            ),
            scatter: sequential_layout(
                "particle_clouds_scatter_layout",
                ShaderStages::COMPUTE,
                (
                    read(),
                    uniform_buffer_sized(true, NonZeroU64::new(SWEEP_DIRECTIONS_BINDING)),
                    read(),
                    read(),
                    write(),
                    write(),
                    work(),
                    read(),
                    read(),
                ),
            ),
            ground: sequential_layout(
                "particle_clouds_ground_layout",
                ShaderStages::COMPUTE,
                (read(), read(), read(), write(), work()),
            ),
            overlap: sequential_layout(
                "particle_clouds_overlap_layout",
                ShaderStages::COMPUTE,
                (read(), read(), read(), write(), work()),
            ),
            closure: sequential_layout(
                "particle_clouds_closure_layout",
                ShaderStages::COMPUTE,
                (read(), read(), read(), read(), write(), write(), work()),
            ),
            coarse_media: indexed_layout(
                "particle_clouds_coarse_media_layout",
                ShaderStages::COMPUTE,
                (
                    (0, read()),
                    (1, read()),
                    (2, read()),
                    (3, read()),
                    (7, work()),
                    (8, write()),
                ),
            ),
            coarse_residual: sequential_layout(
                "particle_clouds_coarse_residual_layout",
                ShaderStages::COMPUTE,
                (
                    read(),
                    read(),
                    read(),
                    read(),
                    read(),
                    write(),
                    write(),
                    work(),
                ),
            ),
            coarse_prolongation: indexed_layout(
                "particle_clouds_coarse_prolongation_layout",
                ShaderStages::COMPUTE,
                (
                    (0, read()),
                    (1, read()),
                    (6, write()),
                    (7, work()),
                    (9, write()),
                ),
            ),
        }
    }
}

/// Queues the illumination passes' compute pipelines (those of the scattering volumes with and
/// without moments) and makes the sweep's direction uniforms.
pub(crate) fn init_illumination_pipelines(
    mut commands: Commands,
    shaders: Res<CloudShaders>,
    pipeline_cache: Res<PipelineCache>,
    device: Res<RenderDevice>,
) {
    let IlluminationLayouts {
        voxelize,
        shade,
        cast,
        sky_map,
        gather,
        scatter,
        ground,
        overlap,
        closure,
        coarse_media,
        coarse_residual,
        coarse_prolongation,
    } = IlluminationLayouts::new();
    let cache = pipeline_cache.as_ref();
    let stage =
        |shader: &Handle<Shader>, entry: &'static str, layout: &BindGroupLayoutDescriptor| {
            ComputeStage::new(cache, shader.clone(), entry, layout.clone())
        };
    commands.insert_resource(IlluminationPipelines {
        voxelize: VOXELIZE_PASSES.map(|entry| stage(&shaders.voxelize, entry, &voxelize)),
        shade: stage(&shaders.shade, "shade", &shade),
        shade_brute_force: stage(&shaders.shade, "shade_brute_force", &shade),
        cast: stage(&shaders.cast, "cast_shadows", &cast),
        march_sky: stage(&shaders.sky_map, "march_sky", &sky_map),
        resolve_sky: stage(&shaders.sky_map, "resolve_sky", &sky_map),
        gather: ByMoments::new(cache, &shaders.gather, "gather", &gather),
        overlap: stage(&shaders.overlap, "overlap_media", &overlap),
        ground: stage(&shaders.ground, "ground_radiance", &ground),
        sweep: [&[][..], &["SWEEP_READ_AHEAD"]]
            .map(|defs| ByMoments::with_defs(cache, &shaders.scatter, "sweep", &scatter, defs)),
        accumulate_order: ByMoments::new(cache, &shaders.scatter, "accumulate_order", &scatter),
        scatter_paper: stage(&shaders.scatter, "scatter_paper", &scatter),
        warm_start: ByMoments::new(cache, &shaders.scatter, "warm_start", &scatter),
        warm_correction: ByMoments::new(cache, &shaders.scatter, "warm_correction", &scatter),
        order_sizes: stage(&shaders.closure, "order_sizes", &closure),
        order_ratio: stage(&shaders.closure, "order_ratio", &closure),
        extrapolate: ByMoments::new(cache, &shaders.closure, "extrapolate", &closure),
        restrict_media: stage(&shaders.coarse_grid, "restrict_media", &coarse_media),
        restrict_residual: ByMoments::new(
            cache,
            &shaders.coarse_grid,
            "restrict_residual",
            &coarse_residual,
        ),
        prolong_correction: ByMoments::new(
            cache,
            &shaders.coarse_grid,
            "prolong_correction",
            &coarse_prolongation,
        ),
        // Padded so that the last set's binding of MAX_SWEEP_PAIRS entries fits.
        sweep_directions: dynamic_uniform(
            &device,
            "particle_clouds_sweep_directions",
            sweep_direction_entries(Vec3::ZERO)
                .chain(std::iter::repeat_n(default(), MAX_SWEEP_PAIRS - 1)),
        ),
        sweep_sky: Vec3::ZERO,
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::core::gpu::storage_buffers_in;

    #[test]
    fn every_illumination_layout_fits_the_storage_buffers_the_adapter_check_asks_for() {
        let l = IlluminationLayouts::new();
        let layouts = [
            &l.voxelize,
            &l.shade,
            &l.cast,
            &l.sky_map,
            &l.gather,
            &l.scatter,
            &l.ground,
            &l.overlap,
            &l.closure,
            &l.coarse_media,
            &l.coarse_residual,
            &l.coarse_prolongation,
        ];
        for layout in layouts {
            let storage = storage_buffers_in(&[layout], ShaderStages::COMPUTE);
            assert!(
                storage <= crate::render::core::adapter::REQUIRED_STORAGE_BUFFERS,
                "{}: {storage} storage buffers",
                layout.label
            );
        }
    }
}
