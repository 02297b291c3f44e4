//! The billboard draw in the `Transparent3d` phase (the paper's Algorithm 3): one phase item per
//! cloud and view (per group of view-transmittance clouds that overlap on screen), instanced
//! draws of a four-vertex strip per particle, depth test on (reverse Z), depth writes off.
//! `Compositing::Sorted`: one draw in the sorted order, premultiplied-alpha blending.
//! `Compositing::ViewTransmittance`: two order-independent draws, one multiplying what is behind
//! by each particle's transmittance, one adding each particle's light, first for every cloud of
//! the group, then for every cloud (one draw into a cloud target, `cloud_target.rs`, which holds
//! only clouds).

use bevy::{
    core_pipeline::core_3d::{CORE_3D_DEPTH_FORMAT, Transparent3d, TransparentSortingInfo3d},
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
            BindGroup, BindGroupEntries, BindGroupLayout, BindGroupLayoutDescriptor,
            BindingResource, BlendComponent, BlendFactor, BlendOperation, BlendState, Buffer,
            BufferInitDescriptor, BufferUsages, CachedRenderPipelineId, ColorTargetState,
            ColorWrites, CompareFunction, DepthBiasState, DepthStencilState, FragmentState,
            MultisampleState, PipelineCache, PrimitiveState, PrimitiveTopology, RenderPipeline,
            RenderPipelineDescriptor, ShaderStages, ShaderType, SpecializedRenderPipeline,
            SpecializedRenderPipelines, StencilState, TextureFormat, VertexState,
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

use crate::beam_phase::BeamPhase;

use crate::render::{
    core::gpu::{sequential_layout, uniform_bytes},
    core::key_of,
    core::shaders::CloudShaders,
    draw::fog::{CloudFogParams, CloudFogUniforms, ExtractedCloudFog, FogMode, ViewCloudFogOffset},
    draw::target::{ViewCloudDraws, ViewCloudSplats, ViewCloudTarget},
    extract::ExtractedCloud,
    extract::particles::GpuParticles,
    plan::CloudIllumination,
    plan::pools::{BufferRange, VolumePools},
    plan::volumes::CloudVolumes,
    view::sort::CloudSorts,
    view::view_atlas::ViewVolumeAtlases,
    view::view_volume::CloudViewVolumes,
};
use crate::{
    cloud::ParticleCloud,
    settings::{BillboardShading, Compositing},
    stats::{CloudPass, CloudPassCounters},
};

/// Mirror of `DrawParams` in `billboard.wgsl`.
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
    /// 1 when the illumination is evaluated once per particle, at its centre
    /// (`BillboardShading::Centre`).
    pub centre_shading: u32,
}

/// A cloud's billboard uniform.
pub(crate) fn draw_params(cloud: &ExtractedCloud) -> DrawParams {
    let world_from_local = Mat4::from(cloud.world_from_local);
    DrawParams {
        world_from_local,
        local_from_world: world_from_local.inverse(),
        scale: cloud.scale(),
        extinction: cloud.extinction,
        segments: cloud.settings.chord_segments,
        centre_shading: (cloud.settings.billboard_shading == BillboardShading::Centre) as u32,
    }
}

/// The billboard render pipeline's layouts and shader (specialized per view target).
#[derive(Resource)]
pub struct BillboardPipeline {
    /// Group 0: the view uniform and the view's fog.
    pub view_layout: BindGroupLayoutDescriptor,
    /// Group 1 when sorted: draw uniform, cloud uniform, particles, sorted order, lights,
    /// optical depths, multiple scattering.
    pub sorted_layout: BindGroupLayoutDescriptor,
    /// Group 1 through the view transmittance: the same with the view volume's uniform in place
    /// of the order, then the view's atlas: optical depths, volumes, neighbour lists.
    pub view_transmittance_layout: BindGroupLayoutDescriptor,
    shader: Handle<Shader>,
}

impl BillboardPipeline {
    /// `billboard.wgsl`.
    pub fn shader(&self) -> Handle<Shader> {
        self.shader.clone()
    }

    fn cloud_layout(&self, compositing: Compositing) -> &BindGroupLayoutDescriptor {
        match compositing {
            Compositing::Sorted => &self.sorted_layout,
            Compositing::ViewTransmittance => &self.view_transmittance_layout,
        }
    }
}

pub(crate) fn init_billboard_pipeline(mut commands: Commands, shaders: Res<CloudShaders>) {
    commands.insert_resource(BillboardPipeline::new(shaders.billboard.clone()));
}

impl BillboardPipeline {
    /// The layouts, drawing with `shader`.
    pub(crate) fn new(shader: Handle<Shader>) -> Self {
        let view_layout = sequential_layout(
            "particle_clouds_view_layout",
            ShaderStages::VERTEX_FRAGMENT,
            (
                uniform_buffer::<ViewUniform>(true),
                uniform_buffer::<CloudFogParams>(true),
            ),
        );
        let read = || storage_buffer_read_only_sized(false, None);
        let uniform = || uniform_buffer_sized(false, None);
        let sorted_layout = sequential_layout(
            "particle_clouds_billboard_sorted_layout",
            ShaderStages::VERTEX_FRAGMENT,
            (
                uniform(),
                uniform(),
                read(),
                read(),
                read(),
                read(),
                read(),
                read(),
            ),
        );
        let view_transmittance_layout = sequential_layout(
            "particle_clouds_billboard_view_transmittance_layout",
            ShaderStages::VERTEX_FRAGMENT,
            (
                uniform(),
                uniform(),
                read(),
                uniform(),
                read(),
                read(),
                read(),
                read(),
                read(),
                read(),
                read(),
            ),
        );
        BillboardPipeline {
            view_layout,
            sorted_layout,
            view_transmittance_layout,
            shader,
        }
    }
}

/// What one billboard draw does to the colour target.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum BillboardBlend {
    /// `Compositing::Sorted`: premultiplied colour and alpha over what is behind.
    Sorted,
    /// `Compositing::ViewTransmittance`, first draw: what is behind times `1 - alpha`.
    Attenuate,
    /// `Compositing::ViewTransmittance`, second draw: plus each particle's light.
    Emit,
    /// `Compositing::ViewTransmittance` into a cloud target, which holds only clouds: one draw
    /// that adds each particle's light and accumulates its opacity in alpha
    /// (`a <- alpha + a (1 - alpha)`, so `1 - a` is the product of the transmittances).
    Accumulate,
}

impl BillboardBlend {
    fn compositing(self) -> Compositing {
        match self {
            Self::Sorted => Compositing::Sorted,
            Self::Attenuate | Self::Emit | Self::Accumulate => Compositing::ViewTransmittance,
        }
    }

    fn entry_point(self) -> &'static str {
        match self {
            Self::Sorted => "fragment",
            Self::Attenuate => "attenuate",
            Self::Emit => "emit",
            Self::Accumulate => "accumulate",
        }
    }

    fn state(self) -> BlendState {
        let component = |src_factor, dst_factor| BlendComponent {
            src_factor,
            dst_factor,
            operation: BlendOperation::Add,
        };
        match self {
            Self::Sorted => BlendState::PREMULTIPLIED_ALPHA_BLENDING,
            Self::Attenuate => BlendState {
                color: component(BlendFactor::Zero, BlendFactor::OneMinusSrcAlpha),
                alpha: component(BlendFactor::One, BlendFactor::OneMinusSrcAlpha),
            },
            Self::Emit => BlendState {
                color: component(BlendFactor::One, BlendFactor::One),
                alpha: component(BlendFactor::Zero, BlendFactor::One),
            },
            Self::Accumulate => BlendState {
                color: component(BlendFactor::One, BlendFactor::One),
                alpha: component(BlendFactor::One, BlendFactor::OneMinusSrcAlpha),
            },
        }
    }
}

/// Where the billboards are drawn.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum BillboardTarget {
    /// Into the view's own colour target, depth-tested by its depth attachment.
    View {
        /// The view's colour target format (HDR or not).
        format: TextureFormat,
        /// MSAA sample count of the view.
        samples: u32,
    },
    /// Into the view's reduced-resolution cloud target (`cloud_target.rs`), depth-tested in the
    /// fragment shader against the view's depth.
    CloudTarget {
        /// Whether the view's depth is multisampled.
        multisampled_depth: bool,
        /// The target's format (`ViewCloudTarget::format`).
        format: TextureFormat,
    },
}

/// What a billboard pipeline depends on: where it draws, the draw's blend and the view's fog.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub struct BillboardPipelineKey {
    /// The target drawn into.
    pub target: BillboardTarget,
    /// Which of the compositing's draws.
    pub blend: BillboardBlend,
    /// The view's distance fog, if any.
    pub fog: Option<FogMode>,
}

impl SpecializedRenderPipeline for BillboardPipeline {
    type Key = BillboardPipelineKey;

    fn specialize(&self, key: Self::Key) -> RenderPipelineDescriptor {
        let compositing = key.blend.compositing();
        // The shared `types` module uses the workgroup defs too.
        let mut shader_defs = crate::render::core::workgroups::shader_defs();
        if compositing == Compositing::ViewTransmittance {
            shader_defs.push("VIEW_TRANSMITTANCE".into());
        }
        if let Some(fog) = key.fog {
            shader_defs.extend(fog.shader_defs().map(Into::into));
        }
        // The attenuating draw writes alpha only: its vertices need no centre shading.
        if key.blend == BillboardBlend::Attenuate {
            shader_defs.push("ALPHA_ONLY".into());
        }
        let (view_layout, format, samples, depth_stencil) = match key.target {
            BillboardTarget::View { format, samples } => (
                self.view_layout.clone(),
                format,
                samples,
                Some(DepthStencilState {
                    format: CORE_3D_DEPTH_FORMAT,
                    // Read-only depth: opaque geometry hides particles, particles hide nothing.
                    depth_write_enabled: Some(false),
                    depth_compare: Some(CompareFunction::GreaterEqual),
                    stencil: StencilState::default(),
                    bias: DepthBiasState::default(),
                }),
            ),
            BillboardTarget::CloudTarget {
                multisampled_depth,
                format,
            } => {
                shader_defs.push("CLOUD_TARGET".into());
                if multisampled_depth {
                    shader_defs.push("MULTISAMPLED".into());
                }
                (
                    crate::render::draw::target::billboard_view_layout(multisampled_depth),
                    format,
                    1,
                    None,
                )
            }
        };
        RenderPipelineDescriptor {
            label: Some("particle_clouds_billboards".into()),
            layout: vec![view_layout, self.cloud_layout(compositing).clone()],
            vertex: VertexState {
                shader: self.shader.clone(),
                entry_point: Some("vertex".into()),
                shader_defs: shader_defs.clone(),
                buffers: vec![],
            },
            fragment: Some(FragmentState {
                shader: self.shader.clone(),
                entry_point: Some(key.blend.entry_point().into()),
                shader_defs,
                targets: vec![Some(ColorTargetState {
                    format,
                    blend: Some(key.blend.state()),
                    write_mask: ColorWrites::ALL,
                })],
            }),
            primitive: PrimitiveState {
                topology: PrimitiveTopology::TriangleStrip,
                cull_mode: None,
                ..default()
            },
            depth_stencil,
            multisample: MultisampleState {
                count: samples,
                mask: !0,
                alpha_to_coverage_enabled: false,
            },
            ..default()
        }
    }
}

/// Per cloud: the draw uniform and one bind group per view (each view has its own sort order or
/// view volume). Rebuilt only when one of their inputs changes.
#[derive(Component)]
pub struct CloudDrawBindGroups {
    key: u64,
    _params: Buffer,
    /// The cloud's [`BeamPhase`] table (one element for a medium without one).
    beam_phase: Buffer,
    /// Group 1 of the billboard pipeline, per view.
    pub groups: HashMap<RetainedViewEntity, BindGroup>,
}

impl CloudDrawBindGroups {
    /// Its buffers (the memory census).
    pub(crate) fn buffers(&self) -> [&Buffer; 2] {
        [&self._params, &self.beam_phase]
    }

    /// The cloud's [`BeamPhase`] table.
    pub fn beam_phase(&self) -> &Buffer {
        &self.beam_phase
    }
}

/// The view bind group of the billboard pipeline.
#[derive(Resource)]
pub struct BillboardViewBindGroup(BindGroup);

/// Per view, the buffers that make a cloud's group 1 differ between views: the sorted order, or
/// the view volume's uniform and the view's atlas (optical depths, volumes, neighbour lists,
/// and for an anisotropic cloud its multiple scattering seen from the camera).
struct PerView<'a> {
    view: RetainedViewEntity,
    buffers: [&'a Buffer; 4],
    seen_multiple: Option<&'a Buffer>,
}

fn per_view_buffers<'a>(
    sorts: Option<&'a CloudSorts>,
    view_volumes: Option<&'a CloudViewVolumes>,
    atlases: &'a ViewVolumeAtlases,
    compositing: Compositing,
) -> Vec<PerView<'a>> {
    match compositing {
        Compositing::Sorted => sorts
            .into_iter()
            .flat_map(|s| &s.0)
            .map(|(view, sort)| PerView {
                view: *view,
                buffers: [sort.buffers.sorted_values(); 4],
                seen_multiple: None,
            })
            .collect(),
        Compositing::ViewTransmittance => view_volumes
            .into_iter()
            .flat_map(|v| &v.0)
            .filter_map(|(view, volume)| {
                let atlas = atlases.0.get(view)?;
                let buffers = [&atlas.optical_depth, &atlas.volumes, &atlas.neighbours];
                Some(PerView {
                    view: *view,
                    buffers: [&volume.params, buffers[0], buffers[1], buffers[2]],
                    seen_multiple: volume.sees_multiple().then_some(&atlas.seen_multiple),
                })
            })
            .collect(),
    }
}

/// Each anisotropy's [`BeamPhase`] table on the GPU, built once while some cloud has that
/// medium (building one sums a Legendre series per entry).
#[derive(Default)]
pub(crate) struct BeamPhaseBuffers(HashMap<u32, Buffer>);

impl BeamPhaseBuffers {
    /// Drops the tables no cloud of `anisotropies` uses.
    fn keep_only(&mut self, anisotropies: impl Iterator<Item = f32>) {
        let used: Vec<u32> = anisotropies.map(f32::to_bits).collect();
        self.0.retain(|g, _| used.contains(g));
    }

    /// The table of anisotropy `g` (one element where the medium has none).
    fn get(&mut self, device: &RenderDevice, g: f32) -> Buffer {
        let buffer = self.0.entry(g.to_bits()).or_insert_with(|| {
            let ratios = BeamPhase::new(g as f64).map_or(vec![1.0], |t| t.ratios);
            device.create_buffer_with_data(&BufferInitDescriptor {
                label: Some("particle_clouds_beam_phase"),
                contents: bytemuck::cast_slice(&ratios),
                usage: BufferUsages::STORAGE,
            })
        });
        buffer.clone()
    }
}

/// What the billboards of one cloud bind: its volumes and its per-view sorts or view volumes.
type BillboardSources = (
    Entity,
    &'static ExtractedCloud,
    &'static CloudVolumes,
    Option<&'static CloudSorts>,
    Option<&'static CloudViewVolumes>,
    Option<&'static CloudDrawBindGroups>,
);

#[allow(clippy::too_many_arguments)]
pub(crate) fn prepare_billboard_bind_groups(
    mut commands: Commands,
    pipeline: Option<Res<BillboardPipeline>>,
    pipeline_cache: Res<PipelineCache>,
    device: Res<RenderDevice>,
    view_uniforms: Res<ViewUniforms>,
    fog_uniforms: Res<CloudFogUniforms>,
    clouds: Query<BillboardSources>,
    particles: Res<RenderAssets<GpuParticles>>,
    pools: Res<VolumePools>,
    atlases: Res<ViewVolumeAtlases>,
    mut beam_phases: Local<BeamPhaseBuffers>,
) {
    let Some(pipeline) = pipeline else { return };
    beam_phases.keep_only(clouds.iter().map(|c| c.1.anisotropy));
    let (Some(view_binding), Some(fog_binding)) =
        (view_uniforms.uniforms.binding(), fog_uniforms.0.binding())
    else {
        return;
    };
    commands.insert_resource(BillboardViewBindGroup(device.create_bind_group(
        "particle_clouds_view_bind_group",
        &pipeline_cache.get_bind_group_layout(&pipeline.view_layout),
        &BindGroupEntries::sequential((view_binding, fog_binding)),
    )));
    for (entity, cloud, volumes, sorts, view_volumes, existing) in &clouds {
        let Some(gpu) = particles.get(cloud.particles) else {
            continue;
        };
        let compositing = cloud.settings.compositing;
        let pool = pools.pool(&volumes.slot);
        let optical_depth = pool.optical_depth(volumes.slot.index);
        let multiple = pool.multiple(volumes.slot.index);
        let lights = pool.lights(volumes.slot.index);
        let layout = pipeline_cache.get_bind_group_layout(pipeline.cloud_layout(compositing));
        let params = draw_params(cloud);
        let per_view = per_view_buffers(sorts, view_volumes, &atlases, compositing);
        // Order-independent over the views (a hash map's order is arbitrary).
        let views = per_view
            .iter()
            .map(|p| {
                let seen = p.seen_multiple.map(|b| b.id());
                key_of((p.view, p.buffers.map(|b| b.id()), seen))
            })
            .fold(0, |a, h| a ^ h);
        // The whole uniform, so that no field of it can be left out of the key.
        let params_bytes = uniform_bytes(&params);
        let key = key_of((
            &params_bytes,
            gpu.buffer.id(),
            volumes.params_buffer.id(),
            [&lights, &optical_depth, &multiple].map(|r| (r.buffer.id(), r.offset)),
            views,
            compositing,
            cloud.anisotropy.to_bits(),
        ));
        if existing.is_some_and(|e| e.key == key) {
            continue;
        }
        let beam_phase = beam_phases.get(&device, cloud.anisotropy);
        let params = device.create_buffer_with_data(&BufferInitDescriptor {
            label: Some("particle_clouds_draw_params"),
            contents: &params_bytes,
            usage: BufferUsages::UNIFORM,
        });
        let shared = SharedBindings {
            params: &params,
            cloud_params: &volumes.params_buffer,
            particles: &gpu.buffer,
            lights: &lights,
            optical_depth: &optical_depth,
            multiple: &multiple,
            beam_phase: &beam_phase,
        };
        let groups = per_view
            .into_iter()
            .map(|p| {
                (
                    p.view,
                    billboard_group(&device, &layout, compositing, &shared, &p),
                )
            })
            .collect();
        commands.entity(entity).insert(CloudDrawBindGroups {
            key,
            _params: params,
            beam_phase,
            groups,
        });
    }
}

/// What a cloud's billboard bind group binds whatever the view.
struct SharedBindings<'a> {
    params: &'a Buffer,
    cloud_params: &'a Buffer,
    particles: &'a Buffer,
    lights: &'a BufferRange,
    optical_depth: &'a BufferRange,
    multiple: &'a BufferRange,
    beam_phase: &'a Buffer,
}

/// A cloud's billboard bind group for one view (group 1 of `billboard.wgsl`): its buffers, the
/// view's sorted order or view volume, and through the view transmittance the view's atlas.
fn billboard_group(
    device: &RenderDevice,
    layout: &BindGroupLayout,
    compositing: Compositing,
    shared: &SharedBindings,
    view: &PerView,
) -> BindGroup {
    let [a, atlas_depth, atlas_volumes, atlas_neighbours] = view.buffers;
    let multiple = match view.seen_multiple {
        Some(seen) => seen.as_entire_binding(),
        None => BindingResource::Buffer(shared.multiple.binding()),
    };
    let (p, c, g, a, l, o) = (
        shared.params.as_entire_binding(),
        shared.cloud_params.as_entire_binding(),
        shared.particles.as_entire_binding(),
        a.as_entire_binding(),
        shared.lights.binding(),
        shared.optical_depth.binding(),
    );
    let b = shared.beam_phase.as_entire_binding();
    let label = "particle_clouds_billboard_bind_group";
    match compositing {
        Compositing::Sorted => device.create_bind_group(
            label,
            layout,
            &BindGroupEntries::sequential((p, c, g, a, l, o, multiple, b)),
        ),
        Compositing::ViewTransmittance => device.create_bind_group(
            label,
            layout,
            &BindGroupEntries::sequential((
                p,
                c,
                g,
                a,
                l,
                o,
                multiple,
                atlas_depth.as_entire_binding(),
                atlas_volumes.as_entire_binding(),
                atlas_neighbours.as_entire_binding(),
                b,
            )),
        ),
    }
}

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
