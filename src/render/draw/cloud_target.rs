//! The paper's §4 fill-rate optimisation: a view whose cloud target scale is below 1 draws its
//! clouds' billboards into a target of that fraction of its size (per axis), then enlarges the
//! target onto the view with a depth-aware upsample (`cloud_target.wgsl`). The draw happens
//! between the opaque and the transparent passes, and reads the view's depth without writing it.
//!
//! The billboards are depth-tested in their fragment shader against one view pixel per target
//! texel (the one under the texel's centre). The upsample weighs the four texels around each view
//! pixel bilinearly and by how close that pixel's depth is to each texel's, so an edge between
//! near and far geometry takes its cloud from the texels on its own side.

use bevy::{
    camera::Camera3d,
    core_pipeline::{
        FullscreenShader,
        core_3d::{main_opaque_pass_3d, main_transparent_pass_3d},
        schedule::{Core3d, Core3dSystems},
    },
    prelude::*,
    render::{
        Render, RenderSystems,
        camera::{ExtractedCamera, TemporalJitter},
        diagnostic::RecordDiagnostics,
        extract_component::ExtractComponentPlugin,
        render_asset::RenderAssets,
        render_resource::{
            BindGroupEntries, BlendState, BufferInitDescriptor, BufferUsages,
            CachedRenderPipelineId, ColorTargetState, ColorWrites, FragmentState, LoadOp,
            Operations, PipelineCache, RenderPassColorAttachment, RenderPassDescriptor,
            RenderPipelineDescriptor, SpecializedRenderPipeline, SpecializedRenderPipelines,
            StoreOp, TextureDescriptor, TextureDimension, TextureFormat, TextureUsages,
        },
        renderer::{RenderContext, RenderDevice, ViewQuery},
        texture::CachedTexture,
        view::{
            ExtractedView, Msaa, RenderVisibleEntities, ViewDepthTexture, ViewTarget,
            ViewUniformOffset, ViewUniforms,
        },
    },
};

use bevy::render::render_resource::BindGroup;

use crate::render::{
    core::gpu::uniform_bytes,
    core::key_of,
    core::shaders::CloudShaders,
    draw::fog::{CloudFogParams, CloudFogUniforms, ExtractedCloudFog, ViewCloudFogOffset},
    draw::redraw::{DrawInputs, must_redraw},
    draw::splat::SplatResources,
    draw::splat::{ViewSplatPipelines, compute_draw_refusal, record_splats, splat_resources},
    draw::splat_batch::ViewSplatBatches,
    draw::{CloudDrawBindGroups, draw_billboards},
    extract::particles::GpuParticles,
    extract::{ExtractedCloud, ExtractedCloudLights},
};
use crate::{
    cloud::ParticleCloud,
    settings::{CloudRedraw, CloudTargetScale, Compositing, DrawMethod},
    stats::{CloudPass, CloudPassCounters},
};

// The target's types lived here before `target.rs`; their public paths stay.
pub use crate::render::draw::target::*;

/// A view's cloud target texture and its bind groups.
#[derive(Component)]
pub struct ViewCloudTargetResources {
    /// The key of what the bind groups bind.
    key: u64,
    /// Texels per side of the texture.
    size: UVec2,
    /// The target: `ViewCloudTarget::format`, the target's size; the view's own.
    pub texture: CachedTexture,
    /// Group 0 of the billboards drawn into the target: view, target parameters, depth.
    pub billboard_view: BindGroup,
    /// The composite's group: target parameters, target, depth.
    pub composite: BindGroup,
    /// A computing view's sums and splat group.
    pub splat: Option<SplatResources>,
}

/// The composite pipeline: the fullscreen triangle and `cloud_target.wgsl`.
#[derive(Resource)]
pub struct CompositePipeline {
    fullscreen: FullscreenShader,
    shader: Handle<Shader>,
}

/// What a composite pipeline depends on: the view's colour target and depth.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub struct CompositePipelineKey {
    /// The view's colour target format.
    pub target_format: TextureFormat,
    /// MSAA samples of the view (its depth is multisampled when above 1).
    pub samples: u32,
}

impl SpecializedRenderPipeline for CompositePipeline {
    type Key = CompositePipelineKey;

    fn specialize(&self, key: Self::Key) -> RenderPipelineDescriptor {
        let multisampled = key.samples > 1;
        let mut shader_defs = crate::render::core::workgroups::shader_defs();
        if multisampled {
            shader_defs.push("MULTISAMPLED".into());
        }
        RenderPipelineDescriptor {
            label: Some("particle_clouds_cloud_target_composite".into()),
            layout: vec![composite_layout(multisampled)],
            vertex: self.fullscreen.to_vertex_state(),
            fragment: Some(FragmentState {
                shader: self.shader.clone(),
                entry_point: Some("composite".into()),
                shader_defs,
                targets: vec![Some(ColorTargetState {
                    format: key.target_format,
                    // The target holds premultiplied radiance and opacity: over what is behind.
                    blend: Some(BlendState::PREMULTIPLIED_ALPHA_BLENDING),
                    write_mask: ColorWrites::ALL,
                })],
            }),
            multisample: bevy::render::render_resource::MultisampleState {
                count: key.samples,
                ..default()
            },
            ..default()
        }
    }
}

/// A view's composite pipeline, specialized in `Queue`.
#[derive(Component, Clone, Copy)]
pub struct ViewCompositePipeline(pub CachedRenderPipelineId);

pub(crate) fn build(app: &mut App) {
    app.add_plugins(ExtractComponentPlugin::<CloudTargetScale>::default());
}

pub(crate) fn finish(render_app: &mut SubApp) {
    render_app
        .init_resource::<SpecializedRenderPipelines<CompositePipeline>>()
        .add_systems(bevy::render::RenderStartup, init_composite_pipeline)
        .add_systems(
            Render,
            (
                choose_cloud_targets.in_set(RenderSystems::PrepareViews),
                queue_composites.in_set(RenderSystems::Queue),
                prepare_cloud_targets
                    .in_set(RenderSystems::PrepareBindGroups)
                    .after(crate::render::draw::prepare_billboard_bind_groups),
            ),
        )
        .add_systems(
            Core3d,
            draw_cloud_target
                .in_set(Core3dSystems::MainPass)
                .after(main_opaque_pass_3d)
                .before(main_transparent_pass_3d),
        );
}

fn init_composite_pipeline(
    mut commands: Commands,
    fullscreen: Res<FullscreenShader>,
    shaders: Res<CloudShaders>,
) {
    commands.insert_resource(CompositePipeline {
        fullscreen: fullscreen.clone(),
        shader: shaders.cloud_target.clone(),
    });
}

/// The scale a view draws its clouds at: its camera's [`CloudTargetScale`], else the largest
/// `cloud_target_scale` of the clouds it sees (1 without clouds).
pub fn view_scale<'a>(
    camera: Option<&CloudTargetScale>,
    clouds: impl IntoIterator<Item = &'a ExtractedCloud>,
) -> f32 {
    match camera {
        Some(scale) => scale.effective(),
        None => clouds
            .into_iter()
            .map(|c| c.settings.cloud_target_scale)
            .reduce(f32::max)
            .unwrap_or(1.0),
    }
}

/// A view whose cloud target is decided: what it sees, its camera's scale, its depth's usages.
type ViewToTarget = (
    Entity,
    &'static ExtractedView,
    &'static RenderVisibleEntities,
    &'static Msaa,
    Option<&'static CloudTargetScale>,
    &'static mut Camera3d,
);

/// Decides each view's cloud target and asks for its depth to be readable.
fn choose_cloud_targets(
    mut commands: Commands,
    mut views: Query<ViewToTarget>,
    clouds: Query<&ExtractedCloud>,
    device: Res<RenderDevice>,
    mut warned: Local<bool>,
) {
    let limits = device.limits();
    for (entity, view, visible, msaa, camera_scale, mut camera) in &mut views {
        let seen: Vec<&ExtractedCloud> = visible
            .get::<ParticleCloud>()
            .into_iter()
            .flat_map(|class| &class.entities_cpu_culling)
            .filter_map(|(e, _)| clouds.get(*e).ok())
            .collect();
        let scale = view_scale(camera_scale, seen.iter().copied());
        let viewport = view.viewport;
        let params = CloudTargetParams::new(viewport.xy(), viewport.zw(), scale.min(1.0));
        let asked = seen
            .iter()
            .any(|c| c.settings.draw_method == DrawMethod::Compute);
        let refusal = asked
            .then(|| compute_draw_refusal(params.target_size, &limits))
            .flatten();
        let compute = asked && refusal.is_none();
        if let Some(reason) = refusal
            && !*warned
        {
            *warned = true;
            warn!(
                "the clouds' draw cannot be computed on this adapter ({reason}): they are \
                 rasterised (`draw_method: Raster` asks for that and silences this)"
            );
        }
        // No cloud in view: no target (and no texture kept alive), nor splat batches, whose
        // bind groups would keep the despawned clouds' volume pools alive.
        if (scale >= 1.0 && !compute) || seen.is_empty() {
            commands.entity(entity).remove::<(
                ViewCloudTarget,
                ViewCloudDraws,
                ViewCloudSplats,
                ViewCloudTargetResources,
                ViewSplatBatches,
            )>();
            continue;
        }
        camera.depth_texture_usages.0 |= TextureUsages::TEXTURE_BINDING.bits();
        let rasterised_into = !compute
            || seen
                .iter()
                .any(|c| c.settings.compositing == Compositing::Sorted);
        commands.entity(entity).insert(ViewCloudTarget {
            params,
            multisampled: msaa.samples() > 1,
            compute,
            format: cloud_target_format(rasterised_into, device.features()),
        });
    }
}

fn queue_composites(
    mut commands: Commands,
    pipeline: Option<Res<CompositePipeline>>,
    mut pipelines: ResMut<SpecializedRenderPipelines<CompositePipeline>>,
    cache: Res<PipelineCache>,
    views: Query<(Entity, &ExtractedView, &Msaa), With<ViewCloudTarget>>,
) {
    let Some(pipeline) = pipeline else { return };
    for (entity, view, msaa) in &views {
        let key = CompositePipelineKey {
            target_format: view.target_format,
            samples: msaa.samples(),
        };
        let id = pipelines.specialize(&cache, &pipeline, key);
        commands.entity(entity).insert(ViewCompositePipeline(id));
    }
}

/// A new cloud target of `size` texels in `format`. Each view owns its own: a computing view
/// keeps its texels from frame to frame ([`CloudRedraw`]), which a texture shared through Bevy's
/// texture cache would not guarantee.
fn cloud_target_texture(
    device: &RenderDevice,
    size: UVec2,
    format: TextureFormat,
) -> CachedTexture {
    let texture = device.create_texture(&TextureDescriptor {
        label: Some("particle_clouds_cloud_target"),
        size: bevy::render::render_resource::Extent3d {
            width: size.x,
            height: size.y,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: TextureDimension::D2,
        format,
        // Copied out by the tests that check the upsample against its CPU reference; written
        // as storage by the splats' resolve.
        usage: TextureUsages::RENDER_ATTACHMENT
            | TextureUsages::TEXTURE_BINDING
            | TextureUsages::STORAGE_BINDING
            | TextureUsages::COPY_SRC,
        view_formats: &[],
    });
    let default_view = texture.create_view(&default());
    CachedTexture {
        texture,
        default_view,
    }
}

/// Gives each cloud target its texture (a new one when its size changes) and makes its bind
/// groups when what they bind changed.
fn prepare_cloud_targets(
    mut commands: Commands,
    device: Res<RenderDevice>,
    cache: Res<PipelineCache>,
    view_uniforms: Res<ViewUniforms>,
    fog_uniforms: Res<CloudFogUniforms>,
    views: Query<(
        Entity,
        &ViewCloudTarget,
        &ViewDepthTexture,
        Option<&ViewCloudTargetResources>,
    )>,
) {
    let (Some(view_binding), Some(view_buffer), Some(fog_binding), Some(fog_buffer)) = (
        view_uniforms.uniforms.binding(),
        view_uniforms.uniforms.buffer(),
        fog_uniforms.0.binding(),
        fog_uniforms.0.buffer(),
    ) else {
        return;
    };
    for (entity, target, depth, existing) in &views {
        // The bind groups are remade only when what they bind changes.
        let p = &target.params;
        let key = key_of((
            [p.viewport_origin, p.viewport_size, p.target_size],
            [p.scale, p.depth_tolerance].map(f32::to_bits),
            target.multisampled,
            target.compute,
            target.format,
            depth.view().id(),
            view_buffer.id(),
            fog_buffer.id(),
        ));
        if existing.is_some_and(|e| e.key == key) {
            continue;
        }
        let texture = match existing {
            Some(e) if e.size == p.target_size && e.texture.texture.format() == target.format => {
                e.texture.clone()
            }
            _ => cloud_target_texture(&device, p.target_size, target.format),
        };
        let params = device.create_buffer_with_data(&BufferInitDescriptor {
            label: Some("particle_clouds_cloud_target_params"),
            contents: &uniform_bytes(&target.params),
            usage: BufferUsages::UNIFORM,
        });
        let billboard_view = device.create_bind_group(
            "particle_clouds_cloud_target_view_bind_group",
            &cache.get_bind_group_layout(&billboard_view_layout(target.multisampled)),
            &BindGroupEntries::sequential((
                view_binding.clone(),
                params.as_entire_binding(),
                depth.view(),
                fog_binding.clone(),
            )),
        );
        let composite = device.create_bind_group(
            "particle_clouds_cloud_target_composite_bind_group",
            &cache.get_bind_group_layout(&composite_layout(target.multisampled)),
            &BindGroupEntries::sequential((
                params.as_entire_binding(),
                &texture.default_view,
                depth.view(),
            )),
        );
        let splat = target.compute.then(|| {
            splat_resources(
                &device,
                &cache,
                target,
                view_binding.clone(),
                &params,
                depth.view(),
                fog_binding.clone(),
                &texture.default_view,
            )
        });
        commands.entity(entity).insert(ViewCloudTargetResources {
            key,
            size: p.target_size,
            texture,
            billboard_view,
            composite,
            splat,
        });
    }
}

/// What the cloud target's draw reads of a view.
type CloudTargetView = (
    &'static ExtractedCamera,
    &'static ExtractedView,
    &'static ViewTarget,
    (&'static ViewUniformOffset, &'static ViewCloudFogOffset),
    &'static ViewCloudDraws,
    &'static ViewCloudTargetResources,
    &'static ViewCompositePipeline,
    Option<(&'static ViewSplatBatches, &'static ViewSplatPipelines)>,
    (
        Option<&'static ExtractedCloudFog>,
        Option<&'static TemporalJitter>,
    ),
);

/// Draws the view's clouds into its cloud target (cleared to no cloud), then composites the
/// target over the view. A computing view whose target cannot have changed keeps it
/// ([`CloudRedraw`]).
#[allow(clippy::too_many_arguments)] // a render pass's inputs
pub fn draw_cloud_target(
    view: ViewQuery<CloudTargetView>,
    clouds: Query<(&ExtractedCloud, &CloudDrawBindGroups)>,
    particles: Res<RenderAssets<GpuParticles>>,
    emit: Res<crate::render::draw::BillboardEmitPipelines>,
    cache: Res<PipelineCache>,
    counters: Res<CloudPassCounters>,
    (lights, redraw): (Res<ExtractedCloudLights>, Option<Res<CloudRedraw>>),
    mut ctx: RenderContext,
) {
    let (camera, extracted, target, offsets, draws, resources, composite, splats, view_fog) =
        view.into_inner();
    let (offset, fog) = offsets;
    let Some(composite) = cache.get_render_pipeline(composite.0) else {
        return;
    };
    let splatting = splats.filter(|(batches, _)| !batches.0.is_empty());
    if draws.0.is_empty() && splatting.is_none() {
        return;
    }
    let recorder = ctx.diagnostic_recorder();
    let recorder = recorder.as_deref();
    // The draw's span (`CloudPass::Draw`), here around the cloud target's draw and composite.
    let span = recorder.time_span(ctx.command_encoder(), CloudPass::Draw.span_name());
    let splatted = match (splatting, &resources.splat) {
        (Some((batches, pipelines)), Some(splat)) => {
            let inputs = DrawInputs {
                view: extracted,
                exposure: camera.exposure,
                jitter: view_fog.1.map(|j| j.offset),
                fog: view_fog.0.map(|f| CloudFogParams::new(&f.0, &lights)),
                batches: batches.0.values().map(|b| b.key()).collect(),
                target: resources.key,
                epoch: counters.illumination_epoch(),
            };
            let mode = redraw.map_or(CloudRedraw::default(), |r| *r);
            let forced = must_redraw(mode, !draws.0.is_empty(), &splat.drawn, inputs.key());
            let encoder = ctx.command_encoder();
            let offsets = ([offset.offset, fog.0], forced);
            let recorded = record_splats(encoder, &cache, pipelines, splat, offsets, batches);
            let Some(dispatches) = recorded else {
                // Still compiling: nothing is drawn this frame (nor counted as shown).
                splat.drawn.store(0, std::sync::atomic::Ordering::Relaxed);
                span.end(ctx.command_encoder());
                return;
            };
            counters.add_dispatches(CloudPass::Draw, dispatches);
            // A kept target is no run; one the depth comparison redraws is not counted either
            // (the CPU cannot know it).
            if forced {
                counters.add(CloudPass::Draw, batches.0.values().map(|b| b.clouds).sum());
            }
            true
        }
        _ => false,
    };
    let mut pass = ctx.begin_tracked_render_pass(RenderPassDescriptor {
        label: Some("particle_clouds_cloud_target_draw"),
        color_attachments: &[Some(RenderPassColorAttachment {
            view: &resources.texture.default_view,
            depth_slice: None,
            resolve_target: None,
            ops: Operations {
                // Over the splats, else from no cloud.
                load: if splatted {
                    LoadOp::Load
                } else {
                    LoadOp::Clear(Default::default())
                },
                store: StoreOp::Store,
            },
        })],
        ..default()
    });
    pass.set_bind_group(0, &resources.billboard_view, &[offset.offset, fog.0]);
    let mut drawn = 0;
    for &(entity, pipeline_id) in &draws.0 {
        let Ok((cloud, groups)) = clouds.get(entity) else {
            continue;
        };
        let (Some(pipeline), Some(group), Some(gpu)) = (
            cache.get_render_pipeline(pipeline_id),
            groups.groups.get(&extracted.retained_view_entity),
            particles.get(cloud.particles),
        ) else {
            continue;
        };
        pass.set_render_pipeline(pipeline);
        let emit = emit.0.get(&pipeline_id);
        let emit = emit.and_then(|id| cache.get_render_pipeline(*id));
        draw_billboards(&mut pass, &[(group, gpu.count)], emit);
        drawn += 1;
    }
    drop(pass);
    let mut pass = ctx.begin_tracked_render_pass(RenderPassDescriptor {
        label: Some("particle_clouds_cloud_target_composite"),
        color_attachments: &[Some(target.get_color_attachment())],
        ..default()
    });
    if let Some(viewport) = camera.viewport.as_ref() {
        pass.set_camera_viewport(viewport);
    }
    pass.set_render_pipeline(composite);
    pass.set_bind_group(0, &resources.composite, &[]);
    pass.draw(0..3, 0..1);
    drop(pass);
    span.end(ctx.command_encoder());
    counters.add(CloudPass::Draw, drawn);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::settings::CloudQualitySettings;
    use bevy::render::render_resource::WgpuFeatures;

    fn cloud(scale: f32) -> ExtractedCloud {
        ExtractedCloud::for_test(CloudQualitySettings {
            cloud_target_scale: scale,
            ..default()
        })
    }

    #[test]
    fn a_view_draws_at_its_camera_scale_else_at_the_finest_its_clouds_ask() {
        let clouds = [cloud(0.5), cloud(0.25)];
        assert_eq!(view_scale(None, &clouds), 0.5);
        assert_eq!(view_scale(Some(&CloudTargetScale(0.25)), &clouds), 0.25);
        assert_eq!(view_scale(Some(&CloudTargetScale(0.01)), &clouds), 0.125);
        assert_eq!(view_scale(Some(&CloudTargetScale(f32::NAN)), &clouds), 1.0);
        assert_eq!(view_scale(None, &[]), 1.0);
    }

    #[test]
    fn a_target_the_rasteriser_blends_into_is_f32_where_the_adapter_blends_it() {
        let blendable = WgpuFeatures::FLOAT32_BLENDABLE;
        assert_eq!(
            cloud_target_format(true, blendable),
            BLENDED_CLOUD_TARGET_FORMAT
        );
        assert_eq!(
            cloud_target_format(true, WgpuFeatures::empty()),
            CLOUD_TARGET_FORMAT
        );
        assert_eq!(cloud_target_format(false, blendable), CLOUD_TARGET_FORMAT);
        assert_eq!(CLOUD_TARGET_FORMAT, TextureFormat::Rgba16Float);
    }

    #[test]
    fn the_target_covers_the_viewport_and_each_texel_stands_for_the_pixel_under_its_centre() {
        let p = CloudTargetParams::new(UVec2::new(10, 20), UVec2::new(641, 480), 0.5);
        assert_eq!(p.target_size, UVec2::new(321, 240));
        assert_eq!(p.depth_pixel(UVec2::ZERO), UVec2::new(11, 21));
        // The last texel overhangs the odd width: clamped into the viewport.
        assert_eq!(p.depth_pixel(UVec2::new(320, 239)), UVec2::new(650, 499));
        let tiny = CloudTargetParams::new(UVec2::ZERO, UVec2::new(3, 1), 0.125);
        assert_eq!(tiny.target_size, UVec2::ONE);
    }
}
