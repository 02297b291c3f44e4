//! The draw without the rasteriser (`DrawMethod::Compute`): into a view's cloud target, a compute
//! shader (`splat` in `billboard.wgsl`) evaluates each view-transmittance cloud's particles over
//! the target texels their screen rectangles cover, exactly as the `accumulate` fragment shader
//! would, and sums each texel's light and optical depth with atomic adds; `resolve_splats` then
//! writes the sums into the target as `accumulate`'s blending would have left it. The image is
//! the rasterised one; the work runs where some GPUs run it many times faster.

use std::sync::atomic::AtomicU64;

use bevy::{
    prelude::*,
    render::{
        render_resource::{
            BindGroup, BindGroupEntries, BindGroupLayoutDescriptor, Buffer, BufferDescriptor,
            BufferInitDescriptor, BufferUsages, CachedComputePipelineId, CommandEncoder,
            ComputePassDescriptor, ComputePipelineDescriptor, PipelineCache, ShaderStages,
            SpecializedComputePipeline, SpecializedComputePipelines, StorageTextureAccess,
            TextureFormat, TextureView, WgpuLimits,
            binding_types::{storage_buffer_sized, texture_storage_2d, uniform_buffer},
        },
        renderer::RenderDevice,
        view::{ExtractedView, ViewUniform},
    },
};

use crate::render::{
    core::gpu::{sequential_layout, storage_buffers_in},
    core::workgroups::{LINEAR, SLICE, linear_groups},
    draw::BillboardPipeline,
    draw::fog::{CloudFogParams, ExtractedCloudFog, FogMode},
    draw::splat_batch::{ViewSplatBatches, prepare_splat_batches, splat_batch_layout},
    draw::target::{
        BLENDED_CLOUD_TARGET_FORMAT, CLOUD_TARGET_FORMAT, CloudTargetParams, ViewCloudTarget,
    },
};

/// Slices of a splat's dispatch (its z dimension): the (particle, texel) pairs of a workgroup's
/// particles are dealt out over them 64 at a time, so that large particles are shaded by several
/// workgroups. Hardly matters on an NVIDIA H200 (computed draw at 1080p with one particle per
/// workgroup, one run each: 2, 8, 32 slices took 18.8, 19.6, 20.6 ms on the paper's scene and
/// 24.9, 23.7, 25.7 ms on the cloudscape).
pub const SPLAT_SLICES: u32 = 8;

/// Workgroups a splat dispatch is given at least, by dealing its pairs over more slices (up to
/// [`MAX_SPLAT_SLICES`]). The dispatches of a view's clouds run one after the other, since each
/// adds into the same sums; a small cloud's few workgroups would leave most of a large GPU idle
/// while each walks its pairs alone (an NVIDIA H200 holds about 4,200 such workgroups at once).
const SPLAT_FILL: u32 = 4096;

/// The most slices a splat dispatch is cut into: each slice reruns its workgroup's scan.
const MAX_SPLAT_SLICES: u32 = 64;

/// Slices of a splat dispatch of `groups` workgroups per slice: [`SPLAT_SLICES`], or more for a
/// small cloud, up to [`MAX_SPLAT_SLICES`], so that the dispatch has [`SPLAT_FILL`] workgroups.
fn splat_slices(groups: u32) -> u32 {
    SPLAT_FILL
        .div_ceil(groups.max(1))
        .clamp(SPLAT_SLICES, MAX_SPLAT_SLICES)
}

/// Bytes per cloud-target texel of the sums: light (r, g, b) and optical depth, f32 each.
const SUM_BYTES: u64 = 16;

/// Why a view cannot splat its clouds into a cloud target of `size` texels on an adapter with
/// `limits`, if it cannot: the sums must fit one storage buffer binding (128 MiB by default: a
/// 4K target just fits), and the splat binds more storage buffers per shader stage than the rest
/// of the plugin, which asks only for eight (WebGPU's default).
pub fn compute_draw_refusal(size: UVec2, limits: &WgpuLimits) -> Option<String> {
    let bytes = size.x as u64 * size.y as u64 * SUM_BYTES;
    let largest = limits
        .max_storage_buffer_binding_size
        .min(limits.max_buffer_size);
    let needed = splat_storage_buffers();
    if bytes > largest {
        Some(format!(
            "a cloud target of {}×{} texels needs {bytes} bytes of sums, more than the adapter's \
             largest storage buffer ({largest} bytes)",
            size.x, size.y
        ))
    } else if limits.max_storage_buffers_per_shader_stage < needed {
        Some(format!(
            "the splat binds {needed} storage buffers, and the adapter allows {} per shader stage",
            limits.max_storage_buffers_per_shader_stage
        ))
    } else {
        None
    }
}

/// Storage buffers the splat and resolve pipelines bind in the compute stage (both groups),
/// counted once from their layouts.
pub fn splat_storage_buffers() -> u32 {
    static COUNT: std::sync::OnceLock<u32> = std::sync::OnceLock::new();
    *COUNT.get_or_init(|| {
        storage_buffers_in(
            &[
                &splat_view_layout(false, CLOUD_TARGET_FORMAT),
                &splat_batch_layout(),
            ],
            ShaderStages::COMPUTE,
        )
    })
}

/// Group 0 of the splat pipelines: the cloud target's billboard view group (view, target
/// parameters, depth, fog), then the sums and the target as storage, and what decides whether the
/// view draws (`still` in `billboard.wgsl`).
pub(crate) fn splat_view_layout(
    multisampled: bool,
    format: TextureFormat,
) -> BindGroupLayoutDescriptor {
    sequential_layout(
        "particle_clouds_splat_view_layout",
        ShaderStages::COMPUTE,
        (
            uniform_buffer::<ViewUniform>(true),
            uniform_buffer::<CloudTargetParams>(false),
            crate::render::draw::target::depth_binding(multisampled),
            uniform_buffer::<CloudFogParams>(true),
            storage_buffer_sized(false, None),
            texture_storage_2d(format, StorageTextureAccess::WriteOnly),
            storage_buffer_sized(false, None),
        ),
    )
}

/// The splat and resolve pipelines: `billboard.wgsl` compiled with `COMPUTE_DRAW`.
#[derive(Resource)]
pub struct SplatPipeline {
    shader: Handle<Shader>,
}

/// The entry points of `billboard.wgsl` that a computing view dispatches, in their order.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum SplatEntry {
    /// `compare_depth`: whether the opaque depth under the target changed.
    CompareDepth,
    /// `splat`: the particles' light and optical depth into the sums.
    Splat,
    /// `resolve_splats`: the sums into the target.
    Resolve,
}

impl SplatEntry {
    fn name(self) -> &'static str {
        match self {
            Self::CompareDepth => "compare_depth",
            Self::Splat => "splat",
            Self::Resolve => "resolve_splats",
        }
    }
}

/// What a splat pipeline depends on.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub struct SplatPipelineKey {
    /// Whether the view's depth is multisampled.
    pub multisampled_depth: bool,
    /// The view's distance fog, if any.
    pub fog: Option<FogMode>,
    /// The entry point.
    pub entry: SplatEntry,
    /// The cloud target's format (`ViewCloudTarget::format`).
    pub target_format: TextureFormat,
}

impl SpecializedComputePipeline for SplatPipeline {
    type Key = SplatPipelineKey;

    fn specialize(&self, key: Self::Key) -> ComputePipelineDescriptor {
        let mut shader_defs = crate::render::core::workgroups::shader_defs();
        shader_defs.extend(["VIEW_TRANSMITTANCE", "CLOUD_TARGET", "COMPUTE_DRAW"].map(Into::into));
        if key.multisampled_depth {
            shader_defs.push("MULTISAMPLED".into());
        }
        if key.target_format == BLENDED_CLOUD_TARGET_FORMAT {
            shader_defs.push("BLENDED_CLOUD_TARGET".into());
        }
        if let Some(fog) = key.fog {
            shader_defs.extend(fog.shader_defs().map(Into::into));
        }
        let entry_point = key.entry.name();
        let view_layout = splat_view_layout(key.multisampled_depth, key.target_format);
        ComputePipelineDescriptor {
            label: Some(format!("particle_clouds_{entry_point}").into()),
            // The depth comparison reads no batch.
            layout: match key.entry {
                SplatEntry::CompareDepth => vec![view_layout],
                _ => vec![view_layout, splat_batch_layout()],
            },
            shader: self.shader.clone(),
            shader_defs,
            entry_point: Some(entry_point.into()),
            ..default()
        }
    }
}

pub(crate) fn init_splat_pipeline(mut commands: Commands, billboards: Res<BillboardPipeline>) {
    commands.insert_resource(SplatPipeline {
        shader: billboards.shader(),
    });
}

/// A computing view's splat pipelines, specialized in `Queue`.
#[derive(Component, Clone, Copy)]
pub struct ViewSplatPipelines {
    /// `compare_depth`.
    pub compare_depth: CachedComputePipelineId,
    /// `splat`.
    pub splat: CachedComputePipelineId,
    /// `resolve_splats`.
    pub resolve: CachedComputePipelineId,
}

pub(crate) fn queue_splat_pipelines(
    mut commands: Commands,
    pipeline: Option<Res<SplatPipeline>>,
    mut pipelines: ResMut<SpecializedComputePipelines<SplatPipeline>>,
    cache: Res<PipelineCache>,
    views: Query<(Entity, &ViewCloudTarget, Option<&ExtractedCloudFog>), With<ExtractedView>>,
) {
    let Some(pipeline) = pipeline else { return };
    for (entity, target, fog) in &views {
        if !target.compute {
            commands.entity(entity).remove::<ViewSplatPipelines>();
            continue;
        }
        let mut specialize = |entry| {
            let key = SplatPipelineKey {
                multisampled_depth: target.multisampled,
                fog: fog.map(|f| FogMode::of(&f.0.falloff)),
                entry,
                target_format: target.format,
            };
            pipelines.specialize(&cache, &pipeline, key)
        };
        let pipelines = ViewSplatPipelines {
            compare_depth: specialize(SplatEntry::CompareDepth),
            splat: specialize(SplatEntry::Splat),
            resolve: specialize(SplatEntry::Resolve),
        };
        commands.entity(entity).insert(pipelines);
    }
}

/// A computing view's sums and the splat pipelines' group 0.
pub struct SplatResources {
    /// Per target texel, `SUM_BYTES` (light and optical depth); zero before each splat (the
    /// resolve leaves them so).
    pub sums: Buffer,
    /// Whether this frame draws, then the depth per target texel (`still` in `billboard.wgsl`).
    pub still: Buffer,
    /// One u32 of 1: copied into `still` when the view must draw.
    redraw: Buffer,
    /// The key of what the target last showed (0: nothing yet), written by the draw.
    pub drawn: AtomicU64,
    /// Texels per side of the target the sums stand for.
    pub target_size: UVec2,
    /// Group 0 of the splat pipelines.
    pub group: BindGroup,
}

impl SplatResources {
    /// Its buffers (the memory census).
    pub(crate) fn buffers(&self) -> [&Buffer; 3] {
        [&self.sums, &self.still, &self.redraw]
    }
}

/// Makes a computing view's sums for a target of `params.target_size` and binds them with the
/// target's other inputs.
#[allow(clippy::too_many_arguments)] // the group's entries
pub(crate) fn splat_resources(
    device: &RenderDevice,
    cache: &PipelineCache,
    target: &ViewCloudTarget,
    view: bevy::render::render_resource::BindingResource<'_>,
    params: &Buffer,
    depth: &TextureView,
    fog: bevy::render::render_resource::BindingResource<'_>,
    texture: &TextureView,
) -> SplatResources {
    let size = target.params.target_size;
    let texels = size.x as u64 * size.y as u64;
    let storage = |label, size| {
        device.create_buffer(&BufferDescriptor {
            label: Some(label),
            size,
            usage: BufferUsages::STORAGE | BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    };
    let sums = storage("particle_clouds_splat_sums", texels * SUM_BYTES);
    let still = storage("particle_clouds_splat_still", (1 + texels) * 4);
    let redraw = device.create_buffer_with_data(&BufferInitDescriptor {
        label: Some("particle_clouds_splat_redraw"),
        contents: &1u32.to_le_bytes(),
        usage: BufferUsages::COPY_SRC,
    });
    let group = device.create_bind_group(
        "particle_clouds_splat_view_bind_group",
        &cache.get_bind_group_layout(&splat_view_layout(target.multisampled, target.format)),
        &BindGroupEntries::sequential((
            view,
            params.as_entire_binding(),
            depth,
            fog,
            sums.as_entire_binding(),
            texture,
            still.as_entire_binding(),
        )),
    );
    SplatResources {
        sums,
        still,
        redraw,
        drawn: AtomicU64::new(0),
        target_size: size,
        group,
    }
}

/// Records a computing view's draw: the depth comparison, its splats into its sums, one dispatch
/// per batch, then their resolve into its cloud target. Where `redraw` is false (nothing the CPU
/// knows of changed), the splats and the resolve do their work only if the depth under the
/// target changed; else the target keeps its texels. `offsets` are the view's and the fog's
/// dynamic offsets. Returns the dispatches recorded, or `None` (nothing recorded) while the
/// pipelines compile.
pub(crate) fn record_splats(
    encoder: &mut CommandEncoder,
    cache: &PipelineCache,
    pipelines: &ViewSplatPipelines,
    splat: &SplatResources,
    (offsets, redraw): ([u32; 2], bool),
    batches: &ViewSplatBatches,
) -> Option<u32> {
    let compare_depth = cache.get_compute_pipeline(pipelines.compare_depth)?;
    let splat_pipeline = cache.get_compute_pipeline(pipelines.splat)?;
    let resolve = cache.get_compute_pipeline(pipelines.resolve)?;
    if redraw {
        encoder.copy_buffer_to_buffer(&splat.redraw, 0, &splat.still, 0, 4);
    } else {
        encoder.clear_buffer(&splat.still, 0, Some(4));
    }
    let mut pass = encoder.begin_compute_pass(&ComputePassDescriptor {
        label: Some("particle_clouds_splat"),
        ..default()
    });
    let size = splat.target_size;
    let texel_groups = [size.x.div_ceil(SLICE), size.y.div_ceil(SLICE), 1];
    pass.set_bind_group(0, &splat.group, &offsets);
    pass.set_pipeline(compare_depth);
    pass.dispatch_workgroups(texel_groups[0], texel_groups[1], 1);
    pass.set_pipeline(splat_pipeline);
    let mut dispatches = 1;
    for batch in batches.0.values() {
        pass.set_bind_group(1, &batch.group, &[]);
        // A workgroup per `LINEAR` particles of a cloud and slice.
        let [x, y, _] = linear_groups(batch.groups * LINEAR);
        pass.dispatch_workgroups(x, y, splat_slices(x * y));
        dispatches += 1;
    }
    pass.set_pipeline(resolve);
    pass.dispatch_workgroups(texel_groups[0], texel_groups[1], 1);
    Some(dispatches + 1)
}

pub(crate) fn finish(render_app: &mut SubApp) {
    use bevy::render::{Render, RenderSystems};
    render_app
        .init_resource::<SpecializedComputePipelines<SplatPipeline>>()
        .add_systems(
            bevy::render::RenderStartup,
            init_splat_pipeline.after(crate::render::draw::init_billboard_pipeline),
        )
        .add_systems(
            Render,
            (
                queue_splat_pipelines.in_set(RenderSystems::Queue),
                prepare_splat_batches
                    .in_set(RenderSystems::PrepareBindGroups)
                    .after(crate::render::draw::prepare_billboard_bind_groups),
            ),
        );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_adapter_splats_when_its_sums_and_storage_buffers_fit() {
        let needed = splat_storage_buffers();
        assert!(needed > crate::render::core::adapter::REQUIRED_STORAGE_BUFFERS);
        let limits = WgpuLimits {
            max_storage_buffers_per_shader_stage: needed,
            ..default()
        };
        let uhd = UVec2::new(3840, 2160);
        assert_eq!(compute_draw_refusal(uhd, &limits), None);
        let refusal = compute_draw_refusal(UVec2::new(7680, 4320), &limits).unwrap();
        assert!(refusal.contains("7680×4320"), "{refusal}");
        // WebGPU's default limits allow 8 storage buffers per stage: rasterise there.
        let fewer = WgpuLimits {
            max_storage_buffers_per_shader_stage: needed - 1,
            ..default()
        };
        let refusal = compute_draw_refusal(uhd, &fewer).unwrap();
        assert!(
            refusal.contains(&format!("binds {needed} storage")),
            "{refusal}"
        );
    }

    #[test]
    fn small_clouds_are_cut_into_more_slices_and_large_ones_keep_the_default() {
        // The paper's 38,000 particles: 594 workgroups of 64, 8 slices already fill the GPU.
        assert_eq!(splat_slices(594), SPLAT_SLICES);
        // One of the scale benchmark's 100 puffs, 384 particles: 6 workgroups.
        assert_eq!(splat_slices(6), MAX_SPLAT_SLICES);
        assert_eq!(splat_slices(0), MAX_SPLAT_SLICES);
        assert_eq!(splat_slices(128), 32);
        for groups in 1..2000 {
            let slices = splat_slices(groups);
            assert!((SPLAT_SLICES..=MAX_SPLAT_SLICES).contains(&slices));
            assert!(slices <= splat_slices(groups - 1));
            assert!(groups * slices >= SPLAT_FILL || slices == MAX_SPLAT_SLICES);
        }
    }
}
