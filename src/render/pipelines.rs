//! Compute pipelines of the illumination passes, created once in `RenderStartup`.

use super::shaders::CloudShaders;
use bevy::{
    prelude::*,
    render::render_resource::{
        BindGroupLayoutDescriptor, BindGroupLayoutEntries, CachedComputePipelineId,
        ComputePipeline, ComputePipelineDescriptor, PipelineCache, ShaderStages,
        binding_types::{
            storage_buffer_read_only_sized, storage_buffer_sized, uniform_buffer_sized,
        },
    },
    shader::Shader,
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
        let pipeline = pipeline_cache.queue_compute_pipeline(ComputePipelineDescriptor {
            label: Some(format!("particle_clouds_{entry_point}").into()),
            layout: vec![layout.clone()],
            shader,
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

/// The pipelines of voxelize, shade, gather, scatter and the per-particle colour.
#[derive(Resource)]
pub struct IlluminationPipelines {
    /// `voxelize.wgsl`, `deposit`.
    pub voxelize: ComputeStage,
    /// `shade.wgsl`, `shade` (incremental).
    pub shade: ComputeStage,
    /// `shade.wgsl`, `shade_brute_force` (benchmarks).
    pub shade_brute_force: ComputeStage,
    /// `gather.wgsl`, `gather`.
    pub gather: ComputeStage,
    /// `scatter.wgsl`, `scatter`.
    pub scatter: ComputeStage,
    /// `particle_colour.wgsl`, `colour`.
    pub colour: ComputeStage,
}

impl IlluminationPipelines {
    /// All compiled, or `None` while any still compiles (work waits for the next frame).
    pub fn ready<'a>(&self, cache: &'a PipelineCache) -> Option<[&'a ComputePipeline; 5]> {
        Some([
            self.voxelize.get(cache)?,
            self.shade.get(cache)?,
            self.gather.get(cache)?,
            self.scatter.get(cache)?,
            self.colour.get(cache)?,
        ])
    }
}

pub(crate) fn init_illumination_pipelines(
    mut commands: Commands,
    shaders: Res<CloudShaders>,
    pipeline_cache: Res<PipelineCache>,
) {
    let uniform = || uniform_buffer_sized(false, None);
    let read = || storage_buffer_read_only_sized(false, None);
    let write = || storage_buffer_sized(false, None);

    let voxelize = BindGroupLayoutDescriptor::new(
        "particle_clouds_voxelize_layout",
        &BindGroupLayoutEntries::sequential(ShaderStages::COMPUTE, (uniform(), read(), write())),
    );
    let shade = BindGroupLayoutDescriptor::new(
        "particle_clouds_shade_layout",
        &BindGroupLayoutEntries::sequential(
            ShaderStages::COMPUTE,
            (uniform(), uniform(), read(), write()),
        ),
    );
    let gather = BindGroupLayoutDescriptor::new(
        "particle_clouds_gather_layout",
        &BindGroupLayoutEntries::sequential(
            ShaderStages::COMPUTE,
            (uniform(), uniform(), read(), write()),
        ),
    );
    let scatter = BindGroupLayoutDescriptor::new(
        "particle_clouds_scatter_layout",
        &BindGroupLayoutEntries::sequential(
            ShaderStages::COMPUTE,
            (uniform(), read(), read(), write(), write()),
        ),
    );
    let colour = BindGroupLayoutDescriptor::new(
        "particle_clouds_colour_layout",
        &BindGroupLayoutEntries::sequential(
            ShaderStages::COMPUTE,
            (uniform(), read(), read(), write()),
        ),
    );
    let cache = pipeline_cache.as_ref();
    let shade_shader = shaders.shade.clone();
    commands.insert_resource(IlluminationPipelines {
        voxelize: ComputeStage::new(cache, shaders.voxelize.clone(), "deposit", voxelize),
        shade: ComputeStage::new(cache, shade_shader.clone(), "shade", shade.clone()),
        shade_brute_force: ComputeStage::new(cache, shade_shader, "shade_brute_force", shade),
        gather: ComputeStage::new(cache, shaders.gather.clone(), "gather", gather),
        scatter: ComputeStage::new(cache, shaders.scatter.clone(), "scatter", scatter),
        colour: ComputeStage::new(cache, shaders.particle_colour.clone(), "colour", colour),
    });
}
