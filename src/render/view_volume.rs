//! The per-view transmittance volume of each cloud composited with
//! [`Compositing::ViewTransmittance`]: its optical depth from the camera, marched through the fine
//! density grid along `m × m` view rays into `m` depth slices (`view_volume.wgsl`,
//! docs/illumination.md §5). It runs only when the view, the cloud's transform or its density
//! changed. The CPU reference is `reference::view_volume`.

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_resource::{
            BindGroup, BindGroupEntries, BindGroupLayoutDescriptor, BindGroupLayoutEntries, Buffer,
            BufferDescriptor, BufferUsages, CachedComputePipelineId, ComputePipelineDescriptor,
            PipelineCache, ShaderStages, ShaderType,
            binding_types::{
                storage_buffer_read_only_sized, storage_buffer_sized, uniform_buffer_sized,
            },
        },
        renderer::{RenderContext, RenderDevice, RenderQueue},
        view::{ExtractedView, RenderVisibleEntities, RetainedViewEntity},
    },
};

use super::{
    extract::ExtractedCloud,
    gpu::{record_stage, storage, uniform_bytes},
    key_of,
    plan::CloudIllumination,
    pools::VolumePools,
    shaders::CloudShaders,
    views_by_cloud,
    volumes::CloudVolumes,
    workgroups,
};
use crate::{
    settings::Compositing,
    stats::{CloudPass, CloudPassCounters},
};

/// Mirror of `ViewVolumeParams` in `types.wgsl`.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct ViewVolumeParams {
    /// Cloud-local from view space.
    pub local_from_view: Mat4,
    /// Tangent rectangle `(u0, u1, v0, v1)` of the rays: `u = x / depth`, `v = y / depth`.
    pub rect: Vec4,
    /// View depths of the first and last slice, metres.
    pub depth: Vec2,
    /// Extinction `K` per world metre at density 1.
    pub extinction: f32,
    /// Rays per side and slices `n` (the fine grid's resolution).
    pub n: u32,
}

/// The march's compute pipeline.
#[derive(Resource)]
pub struct ViewVolumePipeline {
    /// Fine `CloudParams`, `ViewVolumeParams`, fine density, view optical depth.
    pub layout: BindGroupLayoutDescriptor,
    /// `march`.
    pub march: CachedComputePipelineId,
}

pub(crate) fn init_view_volume_pipeline(
    mut commands: Commands,
    shaders: Res<CloudShaders>,
    cache: Res<PipelineCache>,
) {
    let layout = BindGroupLayoutDescriptor::new(
        "particle_clouds_view_volume_layout",
        &BindGroupLayoutEntries::sequential(
            ShaderStages::COMPUTE,
            (
                uniform_buffer_sized(false, None),
                uniform_buffer_sized(false, None),
                storage_buffer_read_only_sized(false, None),
                storage_buffer_sized(false, None),
            ),
        ),
    );
    let march = cache.queue_compute_pipeline(ComputePipelineDescriptor {
        label: Some("particle_clouds_view_volume".into()),
        layout: vec![layout.clone()],
        shader: shaders.view_volume.clone(),
        shader_defs: workgroups::shader_defs(),
        entry_point: Some("march".into()),
        ..default()
    });
    commands.insert_resource(ViewVolumePipeline { layout, march });
}

/// The key of an unlit cloud's volume.
const UNLIT: u64 = u64::MAX;

/// One view's transmittance volume of one cloud.
pub struct ViewVolume {
    /// The `ViewVolumeParams` uniform (the march and the billboards).
    pub params: Buffer,
    /// `n³` f32 optical depth from the camera, index `i + n (j + n k)`.
    pub optical_depth: Buffer,
    n: u32,
    key: u64,
    /// The volume must be marched this frame.
    pub pending: bool,
    /// The volume is valid and may be drawn with.
    pub ready: bool,
    /// The march's bind group, made in `PrepareBindGroups` while the volume is pending.
    group: Option<BindGroup>,
}

/// Every view's transmittance volume of one cloud (render world component on the cloud).
#[derive(Component, Default)]
pub struct CloudViewVolumes(pub HashMap<RetainedViewEntity, ViewVolume>);

/// Tangent rectangle `(u0, u1, v0, v1)` and depth range of the cube of side `side` centred on
/// `centre` (cloud-local) as seen from `view`, clipped to the view's frustum; `None` when nothing
/// of it is ahead of the near plane and inside the frustum. Perspective views only.
fn view_bounds(
    view_from_local: Mat4,
    clip_from_view: Mat4,
    centre: Vec3,
    side: f32,
) -> Option<(Vec4, Vec2)> {
    // Bevy's infinite reverse-Z perspective: ndc.x = P00 u - P20, near = P32.
    let p = clip_from_view;
    let near = p.w_axis.z;
    let frustum = Vec4::new(
        (-1.0 + p.z_axis.x) / p.x_axis.x,
        (1.0 + p.z_axis.x) / p.x_axis.x,
        (-1.0 + p.z_axis.y) / p.y_axis.y,
        (1.0 + p.z_axis.y) / p.y_axis.y,
    );
    let corners = (0..8).map(|c| {
        let sign = |bit: u32| if c & bit == 0 { -0.5 } else { 0.5 };
        view_from_local.transform_point3(centre + side * Vec3::new(sign(1), sign(2), sign(4)))
    });
    let corners: Vec<Vec3> = corners.collect();
    let nearest = corners.iter().map(|c| -c.z).fold(f32::INFINITY, f32::min);
    let farthest = corners
        .iter()
        .map(|c| -c.z)
        .fold(f32::NEG_INFINITY, f32::max);
    let z0 = nearest.max(near);
    if farthest <= z0 || farthest.is_nan() {
        return None;
    }
    let mut rect = frustum;
    if nearest > near {
        let (mut lo, mut hi) = (Vec2::splat(f32::MAX), Vec2::splat(f32::MIN));
        for c in &corners {
            let uv = c.truncate() / -c.z;
            (lo, hi) = (lo.min(uv), hi.max(uv));
        }
        rect = Vec4::new(
            lo.x.max(frustum.x),
            hi.x.min(frustum.y),
            lo.y.max(frustum.z),
            hi.y.min(frustum.w),
        );
    }
    (rect.x < rect.y && rect.z < rect.w).then_some((rect, Vec2::new(z0, farthest)))
}

/// Decides, per view and visible view-transmittance cloud, whether its volume must be marched.
pub(crate) fn prepare_view_volumes(
    mut commands: Commands,
    views: Query<(&ExtractedView, &RenderVisibleEntities)>,
    mut clouds: Query<(
        &ExtractedCloud,
        &CloudVolumes,
        &CloudIllumination,
        Option<&mut CloudViewVolumes>,
    )>,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
) {
    for (entity, views) in views_by_cloud(views.iter()) {
        let Ok((cloud, volumes, illumination, existing)) = clouds.get_mut(entity) else {
            continue;
        };
        if cloud.settings.compositing != Compositing::ViewTransmittance {
            continue;
        }
        let mut fresh = CloudViewVolumes::default();
        let is_fresh = existing.is_none();
        let all = match existing {
            Some(s) => s.into_inner(),
            None => &mut fresh,
        };
        let retained: Vec<_> = views.iter().map(|v| v.retained_view_entity).collect();
        all.0.retain(|k, _| retained.contains(k));
        for view in views {
            let density_key = illumination.keys.density;
            let Some((params, key)) = view_params(cloud, volumes, density_key, view) else {
                all.0.remove(&view.retained_view_entity);
                continue;
            };
            let volume = all
                .0
                .entry(view.retained_view_entity)
                .or_insert_with(|| new_volume(&device, params.n));
            if volume.n != params.n {
                *volume = new_volume(&device, params.n);
            }
            if key != volume.key {
                volume.key = key;
                queue.write_buffer(&volume.params, 0, &uniform_bytes(&params));
                // An unlit volume stays zero: nothing is scattered to be seen through it.
                volume.pending = key != UNLIT;
                volume.ready |= key == UNLIT;
            }
        }
        if is_fresh {
            commands.entity(entity).insert(fresh);
        }
    }
}

/// The uniform of one view's volume of `cloud` and the key of its inputs, or `None` when the cloud
/// is not in front of the view. An unlit cloud scatters nothing, so it needs no optical depth
/// towards the camera (and has no density grid): a zero volume of 2³ nodes, keyed `UNLIT`.
fn view_params(
    cloud: &ExtractedCloud,
    volumes: &CloudVolumes,
    density_key: u64,
    view: &ExtractedView,
) -> Option<(ViewVolumeParams, u64)> {
    if volumes.params.light_count == 0 {
        let params = ViewVolumeParams {
            rect: Vec4::new(0.0, 1.0, 0.0, 1.0),
            depth: Vec2::new(0.0, 1.0),
            n: 2,
            ..default()
        };
        return Some((params, UNLIT));
    }
    let fine = &volumes.fine_params;
    let view_from_local =
        view.world_from_view.to_matrix().inverse() * Mat4::from(cloud.world_from_local);
    let side = fine.h * fine.n as f32;
    let (rect, depth) = view_bounds(view_from_local, view.clip_from_view, fine.grid_centre, side)?;
    let params = ViewVolumeParams {
        local_from_view: view_from_local.inverse(),
        rect,
        depth,
        extinction: cloud.extinction,
        n: fine.n.max(2),
    };
    let key = key_of((
        params.local_from_view.to_cols_array().map(f32::to_bits),
        params.rect.to_array().map(f32::to_bits),
        params.depth.to_array().map(f32::to_bits),
        params.extinction.to_bits(),
        density_key,
    ));
    Some((params, key))
}

fn new_volume(device: &RenderDevice, n: u32) -> ViewVolume {
    ViewVolume {
        params: device.create_buffer(&BufferDescriptor {
            label: Some("particle_clouds_view_volume_params"),
            size: ViewVolumeParams::min_size().get(),
            usage: BufferUsages::UNIFORM | BufferUsages::COPY_DST,
            mapped_at_creation: false,
        }),
        optical_depth: storage(
            device,
            "particle_clouds_view_optical_depth",
            n as u64 * n as u64 * n as u64 * 4,
        ),
        n,
        key: 0,
        pending: false,
        ready: false,
        group: None,
    }
}

/// Makes the march's bind group of every pending view volume.
pub(crate) fn prepare_view_volume_bind_groups(
    mut clouds: Query<(&CloudVolumes, &mut CloudViewVolumes)>,
    pipeline: Option<Res<ViewVolumePipeline>>,
    pools: Res<VolumePools>,
    pipeline_cache: Res<PipelineCache>,
    device: Res<RenderDevice>,
) {
    let Some(pipeline) = pipeline else { return };
    let layout = pipeline_cache.get_bind_group_layout(&pipeline.layout);
    for (volumes, mut all) in &mut clouds {
        let fine_density = pools.pool(&volumes.slot).fine_density(volumes.slot.index);
        for volume in all.0.values_mut().filter(|v| v.pending) {
            volume.group = Some(device.create_bind_group(
                "particle_clouds_view_volume_bind_group",
                &layout,
                &BindGroupEntries::sequential((
                    volumes.fine_params_buffer.as_entire_binding(),
                    volume.params.as_entire_binding(),
                    fine_density.binding(),
                    volume.optical_depth.as_entire_binding(),
                )),
            ));
        }
    }
}

/// Marches every pending view volume whose cloud's density is ready (once per frame, after the
/// illumination, before the cameras draw).
pub(crate) fn march_view_volumes(
    mut ctx: RenderContext,
    mut clouds: Query<(&CloudIllumination, &mut CloudViewVolumes)>,
    pipeline: Option<Res<ViewVolumePipeline>>,
    pipeline_cache: Res<PipelineCache>,
    counters: Res<CloudPassCounters>,
) {
    let Some(pipeline) = pipeline else { return };
    let pending = |illumination: &CloudIllumination, all: &CloudViewVolumes| {
        illumination.ready && all.0.values().any(|s| s.pending)
    };
    if !clouds.iter().any(|(i, all)| pending(i, all)) {
        return;
    }
    let Some(march) = pipeline_cache.get_compute_pipeline(pipeline.march) else {
        return;
    };
    let recorder = ctx.diagnostic_recorder();
    record_stage(
        &mut ctx,
        recorder.as_deref(),
        &counters,
        CloudPass::ViewVolume,
        |pass| {
            pass.set_pipeline(march);
            let mut runs = 0;
            for (illumination, mut all) in &mut clouds {
                if !illumination.ready {
                    continue;
                }
                for volume in all.0.values_mut().filter(|s| s.pending) {
                    let Some(group) = volume.group.take() else {
                        continue;
                    };
                    pass.set_bind_group(0, &group, &[]);
                    workgroups::dispatch_columns(pass, volume.n, 1);
                    volume.pending = false;
                    volume.ready = true;
                    runs += 1;
                }
            }
            runs
        },
    );
}
