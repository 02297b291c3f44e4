//! The billboards in the `Transparent3d` phase: one phase item per cloud and view (per group of
//! view-transmittance clouds that overlap on screen), queued with their specialized pipelines,
//! and the render commands that draw them.

use bevy::{
    core_pipeline::core_3d::{Transparent3d, TransparentSortingInfo3d},
    ecs::{
        query::ROQueryItem,
        system::{
            SystemParamItem,
            lifetimeless::{Read, SQuery, SRes},
        },
    },
    platform::collections::HashMap,
    prelude::*,
    render::{
        diagnostic::{DiagnosticsRecorder, RecordDiagnostics},
        render_asset::RenderAssets,
        render_phase::{
            CachedRenderPipelinePhaseItem, DrawFunctionId, DrawFunctions, PhaseItem,
            PhaseItemExtraIndex, RenderCommand, RenderCommandResult, SetItemPipeline,
            SortedRenderPhase, TrackedRenderPass, ViewSortedRenderPhases,
        },
        render_resource::{
            BindGroup, CachedRenderPipelineId, PipelineCache, RenderPipeline,
            SpecializedRenderPipelines,
        },
        sync_world::MainEntity,
        view::{ExtractedView, Msaa, RenderVisibleEntities, RetainedViewEntity, ViewUniformOffset},
    },
};

use crate::render::{
    draw::fog::{ExtractedCloudFog, FogMode, ViewCloudFogOffset},
    draw::target::{ViewCloudDraws, ViewCloudSplats, ViewCloudTarget},
    extract::ExtractedCloud,
    extract::particles::GpuParticles,
    plan::CloudIllumination,
    view::sort::CloudSorts,
    view::view_atlas::ViewVolumeAtlases,
    view::view_volume::CloudViewVolumes,
};
use crate::{
    cloud::ParticleCloud,
    settings::Compositing,
    stats::{CloudPass, CloudPassCounters},
};

use crate::render::draw::{billboard_groups::*, billboards::*};

/// The `Emit` pipeline drawn after each `Attenuate` pipeline (a view-transmittance cloud's
/// phase item carries the first; its draw function adds the second).
#[derive(Resource, Default)]
pub struct BillboardEmitPipelines(
    pub(crate) HashMap<CachedRenderPipelineId, CachedRenderPipelineId>,
);

/// A view whose clouds are queued: into its phase, or into its cloud target's list.
type ViewToQueue = (
    Entity,
    &'static ExtractedView,
    &'static Msaa,
    &'static RenderVisibleEntities,
    Option<&'static ViewCloudTarget>,
    Option<&'static ExtractedCloudFog>,
);

/// Whether a cloud is ready to draw in a view, and what its phase item needs.
type QueuedCloud = (
    &'static ExtractedCloud,
    &'static CloudIllumination,
    Option<&'static CloudSorts>,
    Option<&'static CloudViewVolumes>,
    &'static MainEntity,
);

/// Adds one `Transparent3d` item per visible, drawable cloud to every view's phase; a view with a
/// cloud target gets its clouds as a back-to-front list instead.
#[allow(clippy::too_many_arguments)] // a render system's resources
pub(crate) fn queue_cloud_billboards(
    mut commands: Commands,
    draw_functions: Res<DrawFunctions<Transparent3d>>,
    pipeline: Option<Res<BillboardPipeline>>,
    mut pipelines: ResMut<SpecializedRenderPipelines<BillboardPipeline>>,
    mut emit_pipelines: ResMut<BillboardEmitPipelines>,
    pipeline_cache: Res<PipelineCache>,
    mut phases: ResMut<ViewSortedRenderPhases<Transparent3d>>,
    views: Query<ViewToQueue>,
    clouds: Query<QueuedCloud>,
    particles: Res<RenderAssets<GpuParticles>>,
    atlases: Res<ViewVolumeAtlases>,
) {
    let Some(pipeline) = pipeline else { return };
    let draw_function = draw_functions.read().id::<DrawCloudBillboards>();
    for (entity, view, msaa, visible, cloud_target, fog) in &views {
        let Some(phase) = phases.get_mut(&view.retained_view_entity) else {
            continue;
        };
        let Some(class) = visible.get::<ParticleCloud>() else {
            continue;
        };
        let target = match cloud_target {
            Some(t) => BillboardTarget::CloudTarget {
                multisampled_depth: t.multisampled,
                format: t.format,
            },
            None => BillboardTarget::View {
                format: view.target_format,
                samples: msaa.samples(),
            },
        };
        let fog = fog.map(|f| FogMode::of(&f.0.falloff));
        let mut specialize = |blend| {
            let key = BillboardPipelineKey { target, blend, fog };
            pipelines.specialize(&pipeline_cache, &pipeline, key)
        };
        let sorted = specialize(BillboardBlend::Sorted);
        // Through the view transmittance: into a cloud target in one draw, into the view in two.
        let view_transmittance = if cloud_target.is_some() {
            specialize(BillboardBlend::Accumulate)
        } else {
            let attenuate = specialize(BillboardBlend::Attenuate);
            emit_pipelines
                .0
                .insert(attenuate, specialize(BillboardBlend::Emit));
            attenuate
        };
        let here = &view.retained_view_entity;
        let view_from_world = view.world_from_view.affine().inverse();
        let mut into_target = Vec::new();
        let mut splats = Vec::new();
        let computed = cloud_target.is_some_and(|t| t.compute);
        let mut groups = CloudGroups::default();
        let group_of = atlases.0.get(here).map(|a| &a.groups);
        for &(render_entity, _) in &class.entities_cpu_culling {
            let Ok((cloud, illumination, sorts, view_volumes, main_entity)) =
                clouds.get(render_entity)
            else {
                continue;
            };
            let (ready, pipeline_id) = match cloud.settings.compositing {
                Compositing::Sorted => (
                    sorts.and_then(|s| s.0.get(here)).is_some_and(|s| s.ready),
                    sorted,
                ),
                Compositing::ViewTransmittance => (
                    view_volumes
                        .and_then(|v| v.0.get(here))
                        .is_some_and(|v| v.ready),
                    view_transmittance,
                ),
            };
            let Some(gpu) = particles.get(cloud.particles) else {
                continue;
            };
            if !(ready && illumination.ready && cloud.extinction > 0.0) || gpu.count == 0 {
                continue;
            }
            let centre = cloud
                .world_from_local
                .transform_point3(gpu.bounds.map_or(Vec3::ZERO, |b| b.centre));
            if computed && cloud.settings.compositing == Compositing::ViewTransmittance {
                splats.push(render_entity);
                continue;
            }
            if cloud_target.is_some() {
                // View space looks down -z: the farthest has the most negative z.
                let z = view_from_world.transform_point3(centre).z;
                into_target.push((z, render_entity, pipeline_id));
                continue;
            }
            let group = group_of.and_then(|g| g.get(&render_entity));
            groups.add(
                group.copied(),
                (render_entity, *main_entity),
                pipeline_id,
                centre,
            );
        }
        if cloud_target.is_some() {
            into_target.sort_by(|a, b| a.0.total_cmp(&b.0));
            let draws = into_target.into_iter().map(|(_, e, p)| (e, p)).collect();
            commands
                .entity(entity)
                .insert((ViewCloudDraws(draws), ViewCloudSplats(splats)));
            continue;
        }
        let members = groups.queue(phase, draw_function);
        commands.entity(entity).insert(members);
    }
}

/// The clouds of one view drawn as one `Transparent3d` item: the view-transmittance clouds that
/// overlap on screen (one group of the view's atlas), or one other cloud.
struct QueuedGroup {
    entities: Vec<(Entity, MainEntity)>,
    pipeline: CachedRenderPipelineId,
    /// Sum of the members' world centres.
    centre: Vec3,
}

/// A view's [`QueuedGroup`]s while they are queued, by atlas group (else alone).
#[derive(Default)]
struct CloudGroups(HashMap<(u32, Option<Entity>), QueuedGroup>);

impl CloudGroups {
    fn add(
        &mut self,
        group: Option<u32>,
        entity: (Entity, MainEntity),
        pipeline: CachedRenderPipelineId,
        centre: Vec3,
    ) {
        let key = group.map_or((0, Some(entity.0)), |g| (g, None));
        let queued = self.0.entry(key).or_insert(QueuedGroup {
            entities: Vec::new(),
            pipeline,
            centre: Vec3::ZERO,
        });
        queued.entities.push(entity);
        queued.centre += centre;
    }

    /// Adds each group to the view's `phase` as one item, sorted at the mean of its clouds'
    /// centres and drawn by `draw_function`; returns the clouds each item draws.
    fn queue(
        self,
        phase: &mut SortedRenderPhase<Transparent3d>,
        draw_function: DrawFunctionId,
    ) -> ViewCloudGroups {
        let mut members = ViewCloudGroups::default();
        for group in self.0.into_values() {
            let (leader, main_entity) = group.entities[0];
            phase.add_transient(Transparent3d {
                sorting_info: TransparentSortingInfo3d::Sorted {
                    mesh_center: group.centre / group.entities.len() as f32,
                    depth_bias: 0.0,
                },
                distance: 0.0,
                pipeline: group.pipeline,
                entity: (leader, main_entity),
                draw_function,
                batch_range: 0..1,
                extra_index: PhaseItemExtraIndex::None,
                indexed: false,
            });
            members
                .0
                .insert(leader, group.entities.into_iter().map(|e| e.0).collect());
        }
        members
    }
}

/// Per view drawn without a cloud target: the clouds each `Transparent3d` item draws, by the
/// item's entity (the first of them).
#[derive(Component, Default)]
pub struct ViewCloudGroups(pub HashMap<Entity, Vec<Entity>>);

/// The draw function of a cloud's `Transparent3d` item.
pub type DrawCloudBillboards = (
    SetItemPipeline,
    SetBillboardViewBindGroup<0>,
    DrawBillboards,
);

/// Binds the view uniform and the view's fog at group `I`.
pub struct SetBillboardViewBindGroup<const I: usize>;

impl<P: PhaseItem, const I: usize> RenderCommand<P> for SetBillboardViewBindGroup<I> {
    type Param = SRes<BillboardViewBindGroup>;
    type ViewQuery = (Read<ViewUniformOffset>, Read<ViewCloudFogOffset>);
    type ItemQuery = ();

    fn render<'w>(
        _: &P,
        (view, fog): ROQueryItem<'w, '_, Self::ViewQuery>,
        _: Option<ROQueryItem<'w, '_, Self::ItemQuery>>,
        group: SystemParamItem<'w, '_, Self::Param>,
        pass: &mut TrackedRenderPass<'w>,
    ) -> RenderCommandResult {
        pass.set_bind_group(I, &group.into_inner().0, &[view.offset, fog.0]);
        RenderCommandResult::Success
    }
}

/// Each drawable cloud of `entities` as the draw binds it in `view`: its group 1 and its
/// particle count (`draw_billboards`).
pub(crate) fn cloud_draws<'a>(
    entities: &[Entity],
    view: &RetainedViewEntity,
    particles: &'a RenderAssets<GpuParticles>,
    cloud: impl Fn(Entity) -> Option<(&'a ExtractedCloud, &'a CloudDrawBindGroups)>,
) -> Vec<(&'a BindGroup, u32)> {
    entities
        .iter()
        .filter_map(|&entity| {
            let (cloud, groups) = cloud(entity)?;
            let group = groups.groups.get(view)?;
            Some((group, particles.get(cloud.particles)?.count))
        })
        .collect()
}

/// Draws clouds' billboards, a four-vertex strip per particle, binding each cloud's group 1 for
/// this view: every cloud once, then, given an `emit` pipeline (through the view transmittance
/// into the view), every cloud again with it. So clouds that overlap on screen first all dim
/// what is behind them, then all add their light, each seen through the others' view volumes.
pub(crate) fn draw_billboards<'w>(
    pass: &mut TrackedRenderPass<'w>,
    clouds: &[(&'w BindGroup, u32)],
    emit: Option<&'w RenderPipeline>,
) {
    let draw_all = |pass: &mut TrackedRenderPass<'w>| {
        for &(group, count) in clouds {
            pass.set_bind_group(1, group, &[]);
            pass.draw(0..4, 0..count);
        }
    };
    draw_all(pass);
    if let Some(emit) = emit {
        pass.set_render_pipeline(emit);
        draw_all(pass);
    }
}

/// Draws the clouds of one `Transparent3d` item ([`ViewCloudGroups`], else the item's own
/// cloud) with `draw_billboards`.
pub struct DrawBillboards;

impl<P: CachedRenderPipelinePhaseItem> RenderCommand<P> for DrawBillboards {
    type Param = (
        SRes<RenderAssets<GpuParticles>>,
        SRes<CloudPassCounters>,
        Option<SRes<DiagnosticsRecorder>>,
        SRes<PipelineCache>,
        SRes<BillboardEmitPipelines>,
        SQuery<(Read<ExtractedCloud>, Read<CloudDrawBindGroups>)>,
    );
    type ViewQuery = (Read<ExtractedView>, Option<Read<ViewCloudGroups>>);
    type ItemQuery = ();

    fn render<'w>(
        item: &P,
        (view, groups): ROQueryItem<'w, '_, Self::ViewQuery>,
        _: Option<ROQueryItem<'w, '_, Self::ItemQuery>>,
        (particles, counters, recorder, cache, emit, clouds): SystemParamItem<'w, '_, Self::Param>,
        pass: &mut TrackedRenderPass<'w>,
    ) -> RenderCommandResult {
        let alone = [item.entity()];
        let members = groups
            .and_then(|g| g.0.get(&item.entity()))
            .map_or(&alone[..], Vec::as_slice);
        let draws = cloud_draws(
            members,
            &view.retained_view_entity,
            particles.into_inner(),
            |entity| clouds.get_inner(entity).ok(),
        );
        if draws.is_empty() {
            return RenderCommandResult::Skip;
        }
        // A timestamp span only: Bevy's own span around the transparent pass already holds the
        // pass's pipeline-statistics query, and those cannot nest.
        let recorder = recorder.map(|r| r.into_inner());
        let span = recorder.time_span(pass.wgpu_pass(), CloudPass::Draw.span_name());
        let emit = emit.into_inner().0.get(&item.cached_pipeline());
        let emit = emit.and_then(|id| cache.into_inner().get_render_pipeline(*id));
        draw_billboards(pass, &draws, emit);
        span.end(pass.wgpu_pass());
        counters.add(CloudPass::Draw, draws.len() as u32);
        RenderCommandResult::Success
    }
}
