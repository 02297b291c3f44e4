//! The render-world side of the plugin, one file per stage:
//!
//! | file | stage |
//! |---|---|
//! | `extract.rs` | clouds and lights into the render world |
//! | `particles.rs` | the `Particles` asset on the GPU |
//! | `volumes.rs` | per-cloud GPU volumes, sized and filled with uniforms in a prepare system |
//! | `pools.rs` | the volumes of every cloud of one shape packed into shared buffers, one slot per cloud |
//! | `cast.rs` | who casts a shadow on whom: each cloud's light volumes take the other clouds' optical depth |
//! | `shadow_maps.rs` | which cloud shadow maps the cast pass fills this frame |
//! | `sky_map.rs` | the sky map: what the clouds hide of the sky over the ground, marched through their densities |
//! | `overlap.rs` | clouds that overlap: each cloud's multiple scattering goes through the others' media too |
//! | `plan.rs` | which stages rerun this frame: cache keys per stage, a pure planning function |
//! | `pipelines.rs` | compute pipelines of the illumination passes |
//! | `voxelize.rs` | the clouds' particles copied together, deposited on their density grids, batched per pool |
//! | `illumination.rs` | voxelize, then shade, gather, scatter batched per pool (the `RenderGraph` schedule) |
//! | `sort.rs` | per-view GPU radix sort of the particles (`Compositing::Sorted`) |
//! | `view_volume.rs` | per-view optical depth from the camera (`Compositing::ViewTransmittance`) |
//! | `view_atlas.rs` | a view's volumes in shared buffers; which clouds each cloud sees through |
//! | `draw.rs` | the billboard draw in `Transparent3d` |
//! | `fog.rs` | each view's distance fog, applied to every piece of every chord |
//! | `cloud_target.rs` | the paper's §4: billboards into a reduced-resolution target, upsampled by depth |
//! | `after_sky.rs` | the clouds composited after Bevy's sky (`Atmosphere`), not in the schedule's arbitrary order |
//! | `splat.rs` | the draw by compute instead of the rasteriser, into the cloud target |
//! | `workgroups.rs` | workgroup sizes and dispatches, shared with the WGSL as shader defs |
//! | `gpu.rs` | buffers, their encodings, and a recorded stage (compute pass, GPU time span, counter) |
//! | `shaders.rs` | the WGSL beside each stage (`*.wgsl`), embedded |

pub(crate) mod after_sky;
pub mod budget;
pub mod cast;
pub mod cloud_target;
pub mod coarse_grid;
pub mod draw;
pub mod extract;
pub mod fog;
pub mod gpu;
pub mod ground;
pub mod illumination;
pub(crate) mod memory;
pub mod overlap;
pub mod particles;
pub mod pipelines;
pub mod plan;
pub mod pools;
pub(crate) mod redraw;
pub mod shaders;
pub mod shadow_maps;
pub mod sky_map;
pub mod sort;
pub mod splat;
pub mod splat_batch;
pub mod view_atlas;
pub mod view_volume;
pub mod volumes;
pub mod voxelize;
pub mod workgroups;

#[cfg(test)]
mod binding_limits;
#[cfg(test)]
mod layout_tests;

use bevy::{
    core_pipeline::{
        core_3d::Transparent3d,
        schedule::{Core3d, camera_driver},
    },
    platform::collections::HashMap,
    prelude::*,
    render::{
        ExtractSchedule, Render, RenderApp, RenderStartup, RenderSystems,
        extract_resource::ExtractResourcePlugin,
        render_asset::RenderAssetPlugin,
        render_phase::AddRenderCommand,
        render_resource::{DownlevelFlags, SpecializedRenderPipelines},
        renderer::{RenderAdapter, RenderDevice},
        renderer::{RenderGraph, RenderGraphSystems},
        sync_component::{SyncComponent, SyncComponentPlugin},
        view::{ExtractedView, RenderVisibleEntities},
    },
};

use self::{extract::ExtractedCloud, shaders::CloudShaders};
use crate::{
    cloud::ParticleCloud,
    settings::{CloudRedraw, CloudRelightBudget, ShadingMethod, SweepDispatch, SweepMarch},
    shadow_maps::CloudShadowMaps,
    stats::CloudPassCounters,
};

impl SyncComponent for ParticleCloud {
    type Target = (
        ExtractedCloud,
        volumes::CloudVolumes,
        plan::CloudIllumination,
        sort::CloudSorts,
        view_volume::CloudViewVolumes,
        draw::CloudDrawBindGroups,
    );
}

impl bevy::render::extract_resource::ExtractResource for CloudPassCounters {
    type Source = CloudPassCounters;
    fn extract_resource(source: &Self::Source) -> Self {
        source.clone()
    }
}

impl bevy::render::extract_resource::ExtractResource for CloudRelightBudget {
    type Source = CloudRelightBudget;
    fn extract_resource(source: &Self::Source) -> Self {
        *source
    }
}

impl bevy::render::extract_resource::ExtractResource for CloudShadowMaps {
    type Source = CloudShadowMaps;
    fn extract_resource(source: &Self::Source) -> Self {
        source.clone()
    }
}

impl bevy::render::extract_resource::ExtractResource for CloudRedraw {
    type Source = CloudRedraw;
    fn extract_resource(source: &Self::Source) -> Self {
        *source
    }
}

impl bevy::render::extract_resource::ExtractResource for SweepMarch {
    type Source = SweepMarch;
    fn extract_resource(source: &Self::Source) -> Self {
        *source
    }
}

impl bevy::render::extract_resource::ExtractResource for SweepDispatch {
    type Source = SweepDispatch;
    fn extract_resource(source: &Self::Source) -> Self {
        *source
    }
}

impl bevy::render::extract_resource::ExtractResource for ShadingMethod {
    type Source = ShadingMethod;
    fn extract_resource(source: &Self::Source) -> Self {
        *source
    }
}

/// Every view each visible cloud is seen in (the per-view passes: sort, view volume).
pub(crate) fn views_by_cloud<'a>(
    views: impl IntoIterator<Item = (&'a ExtractedView, &'a RenderVisibleEntities)>,
) -> HashMap<Entity, Vec<&'a ExtractedView>> {
    let mut by_cloud: HashMap<Entity, Vec<&ExtractedView>> = HashMap::default();
    for (view, visible) in views {
        if let Some(class) = visible.get::<ParticleCloud>() {
            for (entity, _) in &class.entities_cpu_culling {
                by_cloud.entry(*entity).or_default().push(view);
            }
        }
    }
    by_cloud
}

/// A cache key of a stage's inputs: a stage reruns only when its key changes.
pub(crate) fn key_of(value: impl std::hash::Hash) -> u64 {
    use std::hash::{BuildHasher, BuildHasherDefault, DefaultHasher};
    BuildHasherDefault::<DefaultHasher>::default().hash_one(value)
}

pub(crate) fn build(app: &mut App) {
    let shaders = CloudShaders::load(app);
    app.init_resource::<ShadingMethod>()
        .register_type::<ShadingMethod>()
        .init_resource::<SweepMarch>()
        .register_type::<SweepMarch>()
        .init_resource::<SweepDispatch>()
        .register_type::<SweepDispatch>()
        .init_resource::<CloudRelightBudget>()
        .register_type::<CloudRelightBudget>()
        .init_resource::<CloudRedraw>()
        .register_type::<CloudRedraw>();
    app.insert_resource(shaders.clone()).add_plugins((
        SyncComponentPlugin::<ParticleCloud>::default(),
        RenderAssetPlugin::<particles::GpuParticles>::default(),
        ExtractResourcePlugin::<CloudPassCounters>::default(),
        ExtractResourcePlugin::<ShadingMethod>::default(),
        ExtractResourcePlugin::<SweepMarch>::default(),
        ExtractResourcePlugin::<SweepDispatch>::default(),
        ExtractResourcePlugin::<CloudRelightBudget>::default(),
        ExtractResourcePlugin::<CloudRedraw>::default(),
        ExtractResourcePlugin::<CloudShadowMaps>::default(),
    ));
    cloud_target::build(app);
    if let Some(render_app) = app.get_sub_app_mut(RenderApp) {
        render_app.insert_resource(shaders);
    }
}

/// Why an adapter cannot run the plugin: the passes need compute shaders, storage buffers in the
/// vertex stage and eight storage buffers per stage (the sweep's; WebGPU's default limit).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum Unsupported {
    /// No compute shaders (WebGL2, for example).
    #[error("the adapter has no compute shaders")]
    ComputeShaders,
    /// Vertex shaders cannot read storage buffers.
    #[error("the adapter cannot read storage buffers in vertex shaders")]
    VertexStorage,
    /// Too few storage buffers per shader stage.
    #[error("the adapter allows {0} storage buffers per shader stage; 8 are needed")]
    StorageBuffers(u32),
}

/// Storage buffers per shader stage the plugin's pipelines bind at most (tests hold every
/// pipeline to it), but the computed draw's, which falls back to the rasteriser on an adapter
/// that allows fewer (`splat::compute_draw_refusal`); an adapter with fewer cannot run it.
pub(crate) const REQUIRED_STORAGE_BUFFERS: u32 = 8;

/// Why this adapter cannot run the plugin, if it cannot.
fn check_adapter(render_app: &SubApp) -> Result<(), Unsupported> {
    let adapter = render_app.world().resource::<RenderAdapter>();
    let flags = adapter.get_downlevel_capabilities().flags;
    let limits = render_app.world().resource::<RenderDevice>().limits();
    if !flags.contains(DownlevelFlags::COMPUTE_SHADERS) {
        return Err(Unsupported::ComputeShaders);
    }
    if !flags.contains(DownlevelFlags::VERTEX_STORAGE) {
        return Err(Unsupported::VertexStorage);
    }
    if limits.max_storage_buffers_per_shader_stage < REQUIRED_STORAGE_BUFFERS {
        return Err(Unsupported::StorageBuffers(
            limits.max_storage_buffers_per_shader_stage,
        ));
    }
    Ok(())
}

/// Adds the render-world systems once the adapter is known to support them (like Bevy's
/// atmosphere, which checks its adapter in `Plugin::finish`).
pub(crate) fn finish(app: &mut App) {
    let Some(render_app) = app.get_sub_app_mut(RenderApp) else {
        return;
    };
    if let Err(reason) = check_adapter(render_app) {
        error!("bevy_particle_clouds is disabled: {reason}; particle clouds will not be drawn");
        return;
    }
    render_app
        .init_resource::<extract::ExtractedCloudLights>()
        .init_resource::<pools::VolumePools>()
        .init_resource::<illumination::SweepPairVolumes>()
        .init_resource::<voxelize::VoxelizeScratch>()
        .init_resource::<shadow_maps::ShadowMapKeys>()
        .init_resource::<sky_map::SkyMapKey>()
        .init_resource::<view_atlas::ViewVolumeAtlases>()
        .init_resource::<SpecializedRenderPipelines<draw::BillboardPipeline>>()
        .init_resource::<draw::BillboardEmitPipelines>()
        .init_resource::<fog::CloudFogUniforms>()
        .add_render_command::<Transparent3d, draw::DrawCloudBillboards>()
        .add_systems(
            RenderStartup,
            (
                pipelines::init_illumination_pipelines,
                sort::init_sort_pipelines,
                view_volume::init_view_volume_pipeline,
                draw::init_billboard_pipeline,
            ),
        )
        .add_systems(
            ExtractSchedule,
            (extract::extract_clouds, extract::extract_cloud_lights),
        )
        .add_systems(
            Render,
            (
                (
                    volumes::prepare_cloud_volumes,
                    (sort::prepare_cloud_sorts, view_volume::prepare_view_volumes),
                )
                    .chain()
                    .in_set(RenderSystems::PrepareResources),
                (pipelines::write_sweep_sky, pipelines::queue_per_order_sweep)
                    .in_set(RenderSystems::PrepareResources),
                fog::prepare_cloud_fog.in_set(RenderSystems::PrepareResources),
                (
                    illumination::prepare_illumination_bind_groups,
                    // Disjoint fields of `CloudSorts`, but unordered they read as ambiguous.
                    (
                        sort::prepare_sort_bind_groups,
                        draw::prepare_billboard_bind_groups,
                    )
                        .chain(),
                )
                    .in_set(RenderSystems::PrepareBindGroups),
                draw::queue_cloud_billboards.in_set(RenderSystems::Queue),
                (memory::release_idle_scratch, memory::census_gpu_memory)
                    .chain()
                    .in_set(RenderSystems::Cleanup),
            ),
        )
        .add_systems(
            RenderGraph,
            (
                illumination::illuminate_clouds,
                sort::sort_cloud_particles,
                view_volume::march_view_volumes,
            )
                .chain()
                .in_set(RenderGraphSystems::Render)
                .before(camera_driver),
        );
    #[cfg(feature = "distance_fog")]
    render_app.add_systems(ExtractSchedule, fog::extract_cloud_fog);
    cloud_target::finish(render_app);
    render_app.edit_schedule(Core3d, |schedule| {
        schedule.add_build_pass(after_sky::LastBetween::cloud_composite());
    });
    splat::finish(render_app);
}
