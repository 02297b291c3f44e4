//! The billboard draw in the `Transparent3d` phase (the paper's Algorithm 3): one phase item per
//! cloud and view, one instanced draw of six vertices per particle, depth test on (reverse Z),
//! depth writes off, premultiplied-alpha blending.

use bevy::{
    core_pipeline::core_3d::{CORE_3D_DEPTH_FORMAT, Transparent3d, TransparentSortingInfo3d},
    ecs::{
        query::ROQueryItem,
        system::{
            SystemParamItem,
            lifetimeless::{Read, SRes},
        },
    },
    platform::collections::HashMap,
    prelude::*,
    render::{
        diagnostic::{DiagnosticsRecorder, RecordDiagnostics},
        render_asset::RenderAssets,
        render_phase::{
            DrawFunctions, PhaseItem, PhaseItemExtraIndex, RenderCommand, RenderCommandResult,
            SetItemPipeline, TrackedRenderPass, ViewSortedRenderPhases,
        },
        render_resource::{
            BindGroup, BindGroupEntries, BindGroupLayoutDescriptor, BindGroupLayoutEntries,
            BlendState, Buffer, BufferInitDescriptor, BufferUsages, ColorTargetState, ColorWrites,
            CompareFunction, DepthBiasState, DepthStencilState, FragmentState, MultisampleState,
            PipelineCache, PrimitiveState, RenderPipelineDescriptor, ShaderStages, ShaderType,
            SpecializedRenderPipeline, SpecializedRenderPipelines, StencilState, TextureFormat,
            VertexState,
            binding_types::{storage_buffer_read_only_sized, uniform_buffer, uniform_buffer_sized},
        },
        renderer::RenderDevice,
        sync_world::MainEntity,
        view::{
            ExtractedView, Msaa, RenderVisibleEntities, RetainedViewEntity, ViewUniform,
            ViewUniformOffset, ViewUniforms,
        },
    },
};

use super::{
    extract::ExtractedCloud, key_of, particles::GpuParticles, shaders::CloudShaders,
    sort::CloudSorts, volumes::CloudVolumes, volumes::uniform_bytes,
};
use crate::{
    cloud::ParticleCloud,
    stats::{CloudPass, CloudPassCounters},
};

/// Mirror of `DrawParams` in `shaders/billboard.wgsl`.
#[derive(ShaderType, Clone, Copy, Debug, Default)]
pub struct DrawParams {
    /// World from cloud-local.
    pub world_from_local: Mat4,
    /// Cloud-local from world (the shading points' lookups).
    pub local_from_world: Mat4,
    /// Uniform scale: world metres per local metre.
    pub scale: f32,
    /// Extinction `K` per world metre at density 1.
    pub extinction: f32,
    /// Segments of each chord at which the illumination is evaluated (`chord_segments`).
    pub segments: u32,
    /// Uniform-buffer padding.
    pub _padding: u32,
}

/// The billboard render pipeline's layouts and shader (specialized per view target).
#[derive(Resource)]
pub struct BillboardPipeline {
    /// Group 0: the view uniform.
    pub view_layout: BindGroupLayoutDescriptor,
    /// Group 1: draw uniform, cloud uniform, particles, sorted order, lights, optical depths,
    /// multiple scattering.
    pub cloud_layout: BindGroupLayoutDescriptor,
    shader: Handle<Shader>,
}

pub(crate) fn init_billboard_pipeline(mut commands: Commands, shaders: Res<CloudShaders>) {
    let view_layout = BindGroupLayoutDescriptor::new(
        "particle_clouds_view_layout",
        &BindGroupLayoutEntries::single(
            ShaderStages::VERTEX_FRAGMENT,
            uniform_buffer::<ViewUniform>(true),
        ),
    );
    let read = || storage_buffer_read_only_sized(false, None);
    let cloud_layout = BindGroupLayoutDescriptor::new(
        "particle_clouds_billboard_layout",
        &BindGroupLayoutEntries::sequential(
            ShaderStages::VERTEX_FRAGMENT,
            (
                uniform_buffer_sized(false, None),
                uniform_buffer_sized(false, None),
                read(),
                read(),
                read(),
                read(),
                read(),
            ),
        ),
    );
    commands.insert_resource(BillboardPipeline {
        view_layout,
        cloud_layout,
        shader: shaders.billboard.clone(),
    });
}

/// What a billboard pipeline depends on: the view's target.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub struct BillboardPipelineKey {
    /// The view's colour target format (HDR or not).
    pub target_format: TextureFormat,
    /// MSAA sample count of the view.
    pub samples: u32,
}

impl SpecializedRenderPipeline for BillboardPipeline {
    type Key = BillboardPipelineKey;

    fn specialize(&self, key: Self::Key) -> RenderPipelineDescriptor {
        RenderPipelineDescriptor {
            label: Some("particle_clouds_billboards".into()),
            layout: vec![self.view_layout.clone(), self.cloud_layout.clone()],
            vertex: VertexState {
                shader: self.shader.clone(),
                entry_point: Some("vertex".into()),
                shader_defs: vec![],
                buffers: vec![],
            },
            fragment: Some(FragmentState {
                shader: self.shader.clone(),
                entry_point: Some("fragment".into()),
                shader_defs: vec![],
                targets: vec![Some(ColorTargetState {
                    format: key.target_format,
                    blend: Some(BlendState::PREMULTIPLIED_ALPHA_BLENDING),
                    write_mask: ColorWrites::ALL,
                })],
            }),
            primitive: PrimitiveState {
                cull_mode: None,
                ..default()
            },
            depth_stencil: Some(DepthStencilState {
                format: CORE_3D_DEPTH_FORMAT,
                // Read-only depth: opaque geometry hides particles, particles hide nothing.
                depth_write_enabled: Some(false),
                depth_compare: Some(CompareFunction::GreaterEqual),
                stencil: StencilState::default(),
                bias: DepthBiasState::default(),
            }),
            multisample: MultisampleState {
                count: key.samples,
                mask: !0,
                alpha_to_coverage_enabled: false,
            },
            ..default()
        }
    }
}

/// Per cloud: the draw uniform and one bind group per view (each view has its own sort order).
/// Rebuilt only when one of their inputs changes.
#[derive(Component)]
pub struct CloudDrawBindGroups {
    key: u64,
    _params: Buffer,
    /// Group 1 of the billboard pipeline, per view.
    pub groups: HashMap<RetainedViewEntity, BindGroup>,
}

/// The view bind group of the billboard pipeline.
#[derive(Resource)]
pub struct BillboardViewBindGroup(BindGroup);

pub(crate) fn prepare_billboard_bind_groups(
    mut commands: Commands,
    pipeline: Option<Res<BillboardPipeline>>,
    pipeline_cache: Res<PipelineCache>,
    device: Res<RenderDevice>,
    view_uniforms: Res<ViewUniforms>,
    clouds: Query<(
        Entity,
        &ExtractedCloud,
        &CloudVolumes,
        &CloudSorts,
        Option<&CloudDrawBindGroups>,
    )>,
    particles: Res<RenderAssets<GpuParticles>>,
) {
    let Some(pipeline) = pipeline else { return };
    let Some(view_binding) = view_uniforms.uniforms.binding() else {
        return;
    };
    commands.insert_resource(BillboardViewBindGroup(device.create_bind_group(
        "particle_clouds_view_bind_group",
        &pipeline_cache.get_bind_group_layout(&pipeline.view_layout),
        &BindGroupEntries::single(view_binding),
    )));
    let layout = pipeline_cache.get_bind_group_layout(&pipeline.cloud_layout);
    for (entity, cloud, volumes, sorts, existing) in &clouds {
        let Some(gpu) = particles.get(cloud.particles) else {
            continue;
        };
        let world_from_local = Mat4::from(cloud.world_from_local);
        let params = DrawParams {
            world_from_local,
            local_from_world: world_from_local.inverse(),
            scale: cloud.scale(),
            extinction: cloud.extinction,
            segments: cloud.settings.chord_segments,
            _padding: 0,
        };
        // Order-independent over the views (a hash map's order is arbitrary).
        let views = sorts
            .0
            .iter()
            .map(|(view, sort)| key_of((view, sort.buffers.sorted_values().id())))
            .fold(0, |a, h| a ^ h);
        let key = key_of((
            params.world_from_local.to_cols_array().map(f32::to_bits),
            params.extinction.to_bits(),
            params.segments,
            gpu.buffer.id(),
            [
                &volumes.params_buffer,
                &volumes.light_array,
                &volumes.optical_depth,
                &volumes.multiple,
            ]
            .map(|b| b.id()),
            views,
        ));
        if existing.is_some_and(|e| e.key == key) {
            continue;
        }
        let params = device.create_buffer_with_data(&BufferInitDescriptor {
            label: Some("particle_clouds_draw_params"),
            contents: &uniform_bytes(&params),
            usage: BufferUsages::UNIFORM,
        });
        let groups = sorts
            .0
            .iter()
            .map(|(view, sort)| {
                let group = device.create_bind_group(
                    "particle_clouds_billboard_bind_group",
                    &layout,
                    &BindGroupEntries::sequential((
                        params.as_entire_binding(),
                        volumes.params_buffer.as_entire_binding(),
                        gpu.buffer.as_entire_binding(),
                        sort.buffers.sorted_values().as_entire_binding(),
                        volumes.light_array.as_entire_binding(),
                        volumes.optical_depth.as_entire_binding(),
                        volumes.multiple.as_entire_binding(),
                    )),
                );
                (*view, group)
            })
            .collect();
        commands.entity(entity).insert(CloudDrawBindGroups {
            key,
            _params: params,
            groups,
        });
    }
}

/// Adds one `Transparent3d` item per visible, drawable cloud to every view's phase.
pub(crate) fn queue_cloud_billboards(
    draw_functions: Res<DrawFunctions<Transparent3d>>,
    pipeline: Option<Res<BillboardPipeline>>,
    mut pipelines: ResMut<SpecializedRenderPipelines<BillboardPipeline>>,
    pipeline_cache: Res<PipelineCache>,
    mut phases: ResMut<ViewSortedRenderPhases<Transparent3d>>,
    views: Query<(&ExtractedView, &Msaa, &RenderVisibleEntities)>,
    clouds: Query<(&ExtractedCloud, &CloudVolumes, &CloudSorts, &MainEntity)>,
    particles: Res<RenderAssets<GpuParticles>>,
) {
    let Some(pipeline) = pipeline else { return };
    let draw_function = draw_functions.read().id::<DrawCloudBillboards>();
    for (view, msaa, visible) in &views {
        let Some(phase) = phases.get_mut(&view.retained_view_entity) else {
            continue;
        };
        let Some(class) = visible.get::<ParticleCloud>() else {
            continue;
        };
        let key = BillboardPipelineKey {
            target_format: view.target_format,
            samples: msaa.samples(),
        };
        let pipeline_id = pipelines.specialize(&pipeline_cache, &pipeline, key);
        for &(render_entity, _) in &class.entities_cpu_culling {
            let Ok((cloud, volumes, sorts, main_entity)) = clouds.get(render_entity) else {
                continue;
            };
            let drawable = volumes.ready
                && cloud.extinction > 0.0
                && sorts
                    .0
                    .get(&view.retained_view_entity)
                    .is_some_and(|s| s.ready);
            let Some(gpu) = particles.get(cloud.particles) else {
                continue;
            };
            if !drawable || gpu.count == 0 {
                continue;
            }
            let centre = cloud
                .world_from_local
                .transform_point3(gpu.bounds.map_or(Vec3::ZERO, |b| b.centre));
            phase.add_transient(Transparent3d {
                sorting_info: TransparentSortingInfo3d::Sorted {
                    mesh_center: centre,
                    depth_bias: 0.0,
                },
                distance: 0.0,
                pipeline: pipeline_id,
                entity: (render_entity, *main_entity),
                draw_function,
                batch_range: 0..1,
                extra_index: PhaseItemExtraIndex::None,
                indexed: false,
            });
        }
    }
}

/// The draw function of a cloud's `Transparent3d` item.
pub type DrawCloudBillboards = (
    SetItemPipeline,
    SetBillboardViewBindGroup<0>,
    DrawBillboards<1>,
);

/// Binds the view uniform at group `I`.
pub struct SetBillboardViewBindGroup<const I: usize>;

impl<P: PhaseItem, const I: usize> RenderCommand<P> for SetBillboardViewBindGroup<I> {
    type Param = SRes<BillboardViewBindGroup>;
    type ViewQuery = Read<ViewUniformOffset>;
    type ItemQuery = ();

    fn render<'w>(
        _: &P,
        offset: ROQueryItem<'w, '_, Self::ViewQuery>,
        _: Option<ROQueryItem<'w, '_, Self::ItemQuery>>,
        group: SystemParamItem<'w, '_, Self::Param>,
        pass: &mut TrackedRenderPass<'w>,
    ) -> RenderCommandResult {
        pass.set_bind_group(I, &group.into_inner().0, &[offset.offset]);
        RenderCommandResult::Success
    }
}

/// Binds the cloud's group for this view and draws six vertices per particle.
pub struct DrawBillboards<const I: usize>;

impl<P: PhaseItem, const I: usize> RenderCommand<P> for DrawBillboards<I> {
    type Param = (
        SRes<RenderAssets<GpuParticles>>,
        SRes<CloudPassCounters>,
        Option<SRes<DiagnosticsRecorder>>,
    );
    type ViewQuery = Read<ExtractedView>;
    type ItemQuery = (Read<ExtractedCloud>, Read<CloudDrawBindGroups>);

    fn render<'w>(
        _: &P,
        view: ROQueryItem<'w, '_, Self::ViewQuery>,
        cloud: Option<ROQueryItem<'w, '_, Self::ItemQuery>>,
        (particles, counters, recorder): SystemParamItem<'w, '_, Self::Param>,
        pass: &mut TrackedRenderPass<'w>,
    ) -> RenderCommandResult {
        let Some((cloud, groups)) = cloud else {
            return RenderCommandResult::Skip;
        };
        let Some(group) = groups.groups.get(&view.retained_view_entity) else {
            return RenderCommandResult::Skip;
        };
        let Some(gpu) = particles.into_inner().get(cloud.particles) else {
            return RenderCommandResult::Skip;
        };
        pass.set_bind_group(I, group, &[]);
        // A timestamp span only: Bevy's own span around the transparent pass already holds the
        // pass's pipeline-statistics query, and those cannot nest.
        let recorder = recorder.map(|r| r.into_inner());
        let span = recorder.time_span(pass.wgpu_pass(), CloudPass::Draw.span_name());
        pass.draw(0..6, 0..gpu.count);
        span.end(pass.wgpu_pass());
        counters.add(CloudPass::Draw, 1);
        RenderCommandResult::Success
    }
}
