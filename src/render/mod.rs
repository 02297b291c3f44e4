//! The render-world side of the plugin, in one folder per step of the paper (Algorithm 1), each
//! pass's Rust beside its WGSL. Imports run one way, core → extract → plan → illumination → view →
//! draw (a test, `layering`, holds every `use` to it):
//!
//! | folder | what it holds |
//! |---|---|
//! | `core/` | leaves: GPU buffers and recorded stages, workgroup sizes, shader handles, stage keys, the adapter check, the shared WGSL |
//! | `extract/` | clouds, lights and the `Particles` asset into the render world |
//! | `plan/` | which stages rerun this frame, the per-cloud volumes and their pools, the relight budget, who casts on whom, overlapping clouds, the ground frame |
//! | `illumination/` | voxelize, shade, cast, gather, shadow and sky maps; `scatter/`: multiple scattering |
//! | `view/` | per view: the GPU sort, the optical depth from the camera, the view atlas |
//! | `draw/` | billboards in `Transparent3d`, the cloud target, the draw by compute, redraw, fog, compositing after the sky |
//!
//! This file only wires them into Bevy's schedules; `memory.rs` counts what every part holds.

pub mod core;
pub mod draw;
pub mod extract;
pub mod illumination;
pub(crate) mod memory;
pub mod plan;
pub mod view;

#[cfg(test)]
mod binding_limits;
#[cfg(test)]
mod layering;
#[cfg(test)]
mod layout_tests;

// The modules' public paths from before the folders (`render::volumes`, …) stay.
pub use self::core::{adapter::Unsupported, gpu, shaders, workgroups};
pub use self::draw::{cloud_target, fog, splat, splat_batch};
pub use self::extract::particles;
pub use self::illumination::{pipelines, scatter::coarse_grid, shadow_maps, sky_map, voxelize};
pub use self::plan::{budget, casters as cast, ground, overlap, pools, volumes};
pub use self::view::{sort, view_atlas, view_volume};

use bevy::{
    asset::{embedded_asset, load_embedded_asset},
    core_pipeline::{
        core_3d::Transparent3d,
        schedule::{Core3d, camera_driver},
    },
    prelude::*,
    render::{
        ExtractSchedule, Render, RenderApp, RenderStartup, RenderSystems,
        extract_resource::ExtractResourcePlugin,
        render_asset::{RenderAssetPlugin, prepare_assets},
        render_phase::AddRenderCommand,
        render_resource::SpecializedRenderPipelines,
        renderer::{RenderGraph, RenderGraphSystems},
        sync_component::{SyncComponent, SyncComponentPlugin},
    },
};

use self::{core::shaders::CloudShaders, extract::ExtractedCloud};
use crate::{
    cloud::ParticleCloud,
    settings::{CloudRedraw, CloudRelightBudget, ShadingMethod, SweepDispatch, SweepMarch},
    shadow_maps::CloudShadowMaps,
    stats::CloudPassCounters,
};

impl SyncComponent for ParticleCloud {
    type Target = (
        ExtractedCloud,
        plan::volumes::CloudVolumes,
        plan::CloudIllumination,
        view::sort::CloudSorts,
        view::view_volume::CloudViewVolumes,
        draw::billboard_groups::CloudDrawBindGroups,
    );
}

pub(crate) fn build(app: &mut App) {
    let shaders = load_shaders(app);
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
        RenderAssetPlugin::<extract::particles::GpuParticles>::default(),
        ExtractResourcePlugin::<CloudPassCounters>::default(),
        ExtractResourcePlugin::<ShadingMethod>::default(),
        ExtractResourcePlugin::<SweepMarch>::default(),
        ExtractResourcePlugin::<SweepDispatch>::default(),
        ExtractResourcePlugin::<CloudRelightBudget>::default(),
        ExtractResourcePlugin::<CloudRedraw>::default(),
        ExtractResourcePlugin::<CloudShadowMaps>::default(),
    ));
    draw::cloud_target::build(app);
    if let Some(render_app) = app.get_sub_app_mut(RenderApp) {
        render_app.insert_resource(shaders);
    }
}

/// Embeds every shader into the app's asset sources and loads it. Here, not in `core/`, because
/// `embedded_asset!` takes paths relative to the calling file, and this file sits above every folder.
fn load_shaders(app: &mut App) -> CloudShaders {
    embedded_asset!(app, "core/types.wgsl");
    embedded_asset!(app, "illumination/voxelize.wgsl");
    embedded_asset!(app, "core/density.wgsl");
    embedded_asset!(app, "illumination/shade.wgsl");
    embedded_asset!(app, "illumination/cast.wgsl");
    embedded_asset!(app, "illumination/sky_map.wgsl");
    embedded_asset!(app, "illumination/gather.wgsl");
    embedded_asset!(app, "illumination/scatter/overlap.wgsl");
    embedded_asset!(app, "illumination/ground.wgsl");
    embedded_asset!(app, "illumination/scatter/sweep.wgsl");
    embedded_asset!(app, "illumination/scatter/closure.wgsl");
    embedded_asset!(app, "illumination/scatter/coarse_grid.wgsl");
    embedded_asset!(app, "view/sort.wgsl");
    embedded_asset!(app, "view/view_volume.wgsl");
    embedded_asset!(app, "draw/fog.wgsl");
    embedded_asset!(app, "draw/billboard.wgsl");
    embedded_asset!(app, "draw/cloud_target.wgsl");
    CloudShaders {
        types: load_embedded_asset!(&*app, "core/types.wgsl"),
        voxelize: load_embedded_asset!(&*app, "illumination/voxelize.wgsl"),
        density: load_embedded_asset!(&*app, "core/density.wgsl"),
        shade: load_embedded_asset!(&*app, "illumination/shade.wgsl"),
        cast: load_embedded_asset!(&*app, "illumination/cast.wgsl"),
        sky_map: load_embedded_asset!(&*app, "illumination/sky_map.wgsl"),
        gather: load_embedded_asset!(&*app, "illumination/gather.wgsl"),
        overlap: load_embedded_asset!(&*app, "illumination/scatter/overlap.wgsl"),
        ground: load_embedded_asset!(&*app, "illumination/ground.wgsl"),
        scatter: load_embedded_asset!(&*app, "illumination/scatter/sweep.wgsl"),
        closure: load_embedded_asset!(&*app, "illumination/scatter/closure.wgsl"),
        coarse_grid: load_embedded_asset!(&*app, "illumination/scatter/coarse_grid.wgsl"),
        sort: load_embedded_asset!(&*app, "view/sort.wgsl"),
        view_volume: load_embedded_asset!(&*app, "view/view_volume.wgsl"),
        fog: load_embedded_asset!(&*app, "draw/fog.wgsl"),
        billboard: load_embedded_asset!(&*app, "draw/billboard.wgsl"),
        cloud_target: load_embedded_asset!(&*app, "draw/cloud_target.wgsl"),
    }
}

/// Adds the render-world systems once the adapter is known to support them (like Bevy's
/// atmosphere, which checks its adapter in `Plugin::finish`).
pub(crate) fn finish(app: &mut App) {
    let Some(render_app) = app.get_sub_app_mut(RenderApp) else {
        return;
    };
    if let Err(reason) = self::core::adapter::check_adapter(render_app) {
        error!("bevy_particle_clouds is disabled: {reason}; particle clouds will not be drawn");
        return;
    }
    render_app
        .init_resource::<extract::ExtractedCloudLights>()
        .init_resource::<plan::pools::VolumePools>()
        .init_resource::<illumination::batches::SweepPairVolumes>()
        .init_resource::<illumination::voxelize::VoxelizeScratch>()
        .init_resource::<illumination::shadow_maps::ShadowMapKeys>()
        .init_resource::<illumination::sky_map::SkyMapKey>()
        .init_resource::<view::view_atlas::ViewVolumeAtlases>()
        .init_resource::<SpecializedRenderPipelines<draw::billboards::BillboardPipeline>>()
        .init_resource::<draw::billboard_queue::BillboardEmitPipelines>()
        .init_resource::<draw::fog::CloudFogUniforms>()
        .add_render_command::<Transparent3d, draw::billboard_queue::DrawCloudBillboards>()
        .add_systems(
            RenderStartup,
            (
                illumination::pipelines::init_illumination_pipelines,
                view::sort::init_sort_pipelines,
                view::view_volume::init_view_volume_pipeline,
                draw::billboards::init_billboard_pipeline,
            ),
        )
        .add_systems(
            ExtractSchedule,
            (extract::extract_clouds, extract::extract_cloud_lights),
        )
        .add_systems(
            Render,
            (
                extract::particles::clamp_opaque_extinctions
                    .in_set(RenderSystems::PrepareAssets)
                    .after(prepare_assets::<extract::particles::GpuParticles>),
                (
                    plan::volumes::prepare_cloud_volumes,
                    (
                        view::sort::prepare_cloud_sorts,
                        view::view_volume::prepare_view_volumes,
                    ),
                )
                    .chain()
                    .in_set(RenderSystems::PrepareResources),
                (
                    illumination::pipelines::write_sweep_sky,
                    illumination::pipelines::queue_per_order_sweep,
                )
                    .in_set(RenderSystems::PrepareResources),
                draw::fog::prepare_cloud_fog.in_set(RenderSystems::PrepareResources),
                (
                    illumination::batches::prepare_illumination_bind_groups,
                    // Disjoint fields of `CloudSorts`, but unordered they read as ambiguous.
                    (
                        view::sort::prepare_sort_bind_groups,
                        draw::billboard_groups::prepare_billboard_bind_groups,
                    )
                        .chain(),
                )
                    .in_set(RenderSystems::PrepareBindGroups),
                draw::billboard_queue::queue_cloud_billboards.in_set(RenderSystems::Queue),
                (memory::release_idle_scratch, memory::census_gpu_memory)
                    .chain()
                    .in_set(RenderSystems::Cleanup),
            ),
        )
        .add_systems(
            RenderGraph,
            (
                illumination::node::illuminate_clouds,
                view::sort::sort_cloud_particles,
                view::view_volume_node::march_view_volumes,
            )
                .chain()
                .in_set(RenderGraphSystems::Render)
                .before(camera_driver),
        );
    #[cfg(feature = "distance_fog")]
    render_app.add_systems(ExtractSchedule, draw::fog::extract_cloud_fog);
    draw::cloud_target::finish(render_app);
    render_app.edit_schedule(Core3d, |schedule| {
        schedule.add_build_pass(draw::after_sky::LastBetween::cloud_composite());
    });
    draw::splat::finish(render_app);
}
