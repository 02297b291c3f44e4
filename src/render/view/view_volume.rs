//! The per-view transmittance volume of each cloud composited with
//! [`Compositing::ViewTransmittance`]: its optical depth from the camera, marched through the fine
//! density grid along `m × m` view rays into `m` depth slices (`view_volume.wgsl`,
//! docs/illumination.md §5). It runs only when the view, the cloud's transform or its density
//! changed. The CPU reference is `reference::view_volume`.
//!
//! A view's volumes share one [`ViewVolumeAtlas`] (`view_atlas.rs`), with the lists of which
//! clouds each cloud's billboards see through (the clouds that may lie in front of it) and the
//! groups of clouds that overlap on screen, which `draw.rs` draws as one.

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_resource::{
            BindGroupLayoutDescriptor, Buffer, BufferDescriptor, BufferUsages,
            CachedComputePipelineId, ComputePipelineDescriptor, PipelineCache, ShaderStages,
            ShaderType,
            binding_types::{storage_buffer_read_only_sized, storage_buffer_sized},
        },
        renderer::{RenderDevice, RenderQueue},
        view::{ExtractedView, RenderVisibleEntities, RetainedViewEntity},
    },
};

use crate::render::{
    core::gpu::{indexed_layout, sequential_layout, uniform_bytes},
    core::key_of,
    core::shaders::CloudShaders,
    core::workgroups,
    extract::ExtractedCloud,
    plan::CloudIllumination,
    plan::volumes::CloudVolumes,
    view::view_atlas::{AtlasEntry, UNLIT, ViewVolumeAtlas, ViewVolumeAtlases, link_neighbours},
};
use crate::{cloud::ParticleCloud, settings::Compositing, stats::CloudPassCounters};

// These lived here before the atlas took them; their public paths stay.
pub use crate::render::view::view_atlas::{ViewVolumeParams, view_volume_len};

/// The march's and the front maps' compute pipelines.
#[derive(Resource)]
pub struct ViewVolumePipeline {
    /// A pool's `Slot`s, an atlas's `ViewVolumeParams`, the pool's densities, the atlas's optical
    /// depths, the work list.
    pub layout: BindGroupLayoutDescriptor,
    /// `march`.
    pub march: CachedComputePipelineId,
    /// An atlas's `ViewVolumeParams` (binding 1), its optical depths (3), the work list (4) and
    /// its neighbour lists (5).
    pub front_layout: BindGroupLayoutDescriptor,
    /// `sum_front`.
    pub sum_front: CachedComputePipelineId,
    /// A pool's `Slot`s (binding 0), an atlas's `ViewVolumeParams` (1), the work list (4), the
    /// pool's multiple scattering (6) and the atlas's `seen_multiple` (7).
    pub seen_layout: BindGroupLayoutDescriptor,
    /// `see_multiple`.
    pub see_multiple: CachedComputePipelineId,
}

/// The march's, the front maps' and `see_multiple`'s layouts ([`ViewVolumePipeline`]).
pub(crate) fn view_volume_layouts() -> [BindGroupLayoutDescriptor; 3] {
    let layout = sequential_layout(
        "particle_clouds_view_volume_layout",
        ShaderStages::COMPUTE,
        (
            storage_buffer_read_only_sized(false, None),
            storage_buffer_read_only_sized(false, None),
            storage_buffer_read_only_sized(false, None),
            storage_buffer_sized(false, None),
            storage_buffer_read_only_sized(true, None),
        ),
    );
    let front_layout = indexed_layout(
        "particle_clouds_view_volume_front_layout",
        ShaderStages::COMPUTE,
        (
            (1, storage_buffer_read_only_sized(false, None)),
            (3, storage_buffer_sized(false, None)),
            (4, storage_buffer_read_only_sized(true, None)),
            (5, storage_buffer_read_only_sized(false, None)),
        ),
    );
    let seen_layout = indexed_layout(
        "particle_clouds_view_volume_seen_layout",
        ShaderStages::COMPUTE,
        (
            (0, storage_buffer_read_only_sized(false, None)),
            (1, storage_buffer_read_only_sized(false, None)),
            (4, storage_buffer_read_only_sized(true, None)),
            (6, storage_buffer_read_only_sized(false, None)),
            (7, storage_buffer_sized(false, None)),
        ),
    );
    [layout, front_layout, seen_layout]
}

pub(crate) fn init_view_volume_pipeline(
    mut commands: Commands,
    shaders: Res<CloudShaders>,
    cache: Res<PipelineCache>,
) {
    let [layout, front_layout, seen_layout] = view_volume_layouts();
    let compute = |label: &'static str, layout: &BindGroupLayoutDescriptor, entry: &'static str| {
        cache.queue_compute_pipeline(ComputePipelineDescriptor {
            label: Some(label.into()),
            layout: vec![layout.clone()],
            shader: shaders.view_volume.clone(),
            shader_defs: workgroups::shader_defs(),
            entry_point: Some(entry.into()),
            ..default()
        })
    };
    let march = compute("particle_clouds_view_volume", &layout, "march");
    let sum_front = compute(
        "particle_clouds_view_volume_front",
        &front_layout,
        "sum_front",
    );
    let see_multiple = compute(
        "particle_clouds_view_volume_seen",
        &seen_layout,
        "see_multiple",
    );
    commands.insert_resource(ViewVolumePipeline {
        layout,
        march,
        front_layout,
        sum_front,
        seen_layout,
        see_multiple,
    });
}

/// One view's transmittance volume of one cloud. Its optical depths live in the view's
/// [`ViewVolumeAtlas`].
pub struct ViewVolume {
    /// The `ViewVolumeParams` uniform (the march and the billboards).
    pub params: Buffer,
    /// What `params` holds.
    written: Option<ViewVolumeParams>,
    /// Key of what the march reads and where it writes.
    key: u64,
    /// The volume must be marched this frame.
    pub pending: bool,
    /// The volume is valid and may be drawn with.
    pub ready: bool,
    /// Its index in its view's atlas (`ViewVolumeAtlas::volumes`).
    pub(super) entry: u32,
    /// Key of where the camera sees the cloud's multiple scattering from and where it is
    /// written (an anisotropic cloud's; 0 for none).
    seen_key: u64,
    /// The multiple scattering seen from the camera must be evaluated again: the camera moved,
    /// or its place in the atlas did.
    pub(super) seen_pending: bool,
    /// The [`CloudIllumination::scattered`] it was last evaluated from.
    pub(super) seen_from: Option<u32>,
}

impl ViewVolume {
    /// The uniform as last written (`None` before the first).
    pub fn uniform(&self) -> Option<ViewVolumeParams> {
        self.written
    }

    /// Its index in its view's atlas (`ViewVolumeAtlas::volumes`).
    pub fn atlas_index(&self) -> u32 {
        self.entry
    }

    /// Whether the billboards read the cloud's multiple scattering seen from the camera from the
    /// view's atlas (an anisotropic cloud), not the pool's.
    pub fn sees_multiple(&self) -> bool {
        self.written.is_some_and(|p| p.seen_n > 0)
    }

    /// Whether the multiple scattering seen from the camera must be evaluated this frame, its
    /// cloud's last scattering being `scattered`.
    pub(super) fn must_see(&self, scattered: u32) -> bool {
        self.sees_multiple() && (self.seen_pending || self.seen_from != Some(scattered))
    }
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

/// What a view's atlas is prepared from, per visible cloud.
type VolumeSources = (
    Entity,
    &'static ExtractedCloud,
    &'static CloudVolumes,
    &'static CloudIllumination,
    Option<&'static mut CloudViewVolumes>,
);

/// Per view: lays out its atlas, links each volume's neighbours and decides which volumes must
/// be marched. A cloud's volumes of views that no longer see it are dropped, and so is the atlas
/// of a view that sees no cloud.
pub(crate) fn prepare_view_volumes(
    mut commands: Commands,
    views: Query<(&ExtractedView, &RenderVisibleEntities)>,
    mut clouds: Query<VolumeSources>,
    mut atlases: ResMut<ViewVolumeAtlases>,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
    counters: Res<CloudPassCounters>,
) {
    let mut fresh: HashMap<Entity, CloudViewVolumes> = HashMap::default();
    let mut seen: HashMap<Entity, Vec<RetainedViewEntity>> = HashMap::default();
    let mut live = Vec::new();
    for (view, visible) in &views {
        let Some(class) = visible.get::<ParticleCloud>() else {
            continue;
        };
        let mut entries: Vec<AtlasEntry> = class
            .entities_cpu_culling
            .iter()
            .filter_map(|&(entity, _)| atlas_entry(entity, clouds.get(entity).ok()?, view))
            .collect();
        // A view without clouds keeps no atlas: its buffers only grow, so a camera that once saw
        // many clouds would hold them at their peak for as long as it lives.
        if entries.is_empty() {
            continue;
        }
        entries.sort_by_key(|e| e.entity);
        let here = view.retained_view_entity;
        live.push(here);
        let atlas = atlases
            .0
            .entry(here)
            .or_insert_with(|| ViewVolumeAtlas::new(&device));
        atlas.lay_out(&device, &mut entries);
        let (lists, groups) = link_neighbours(&mut entries);
        if atlas.write(&device, &queue, &entries, &lists) {
            counters.note_write();
        }
        atlas.groups = entries
            .iter()
            .zip(groups)
            .map(|(e, g)| (e.entity, g))
            .collect();
        for (index, entry) in entries.iter().enumerate() {
            seen.entry(entry.entity).or_default().push(here);
            let Ok((.., existing)) = clouds.get_mut(entry.entity) else {
                continue;
            };
            let all = match existing {
                Some(all) => all.into_inner(),
                None => fresh.entry(entry.entity).or_default(),
            };
            let volume = all.0.entry(here).or_insert_with(|| new_volume(&device));
            if update_volume(volume, index as u32, entry, &queue) {
                counters.note_write();
            }
        }
    }
    atlases.0.retain(|view, _| live.contains(view));
    for (entity, .., existing) in &mut clouds {
        if let Some(mut all) = existing {
            let views = seen.get(&entity);
            all.0
                .retain(|view, _| views.is_some_and(|v| v.contains(view)));
        }
    }
    for (entity, all) in fresh {
        commands.entity(entity).insert(all);
    }
}

/// A view-transmittance cloud's entry in `view`'s atlas, or `None` when it is composited
/// otherwise or not in front of the view.
fn atlas_entry(
    entity: Entity,
    (_, cloud, volumes, illumination, _): (
        Entity,
        &ExtractedCloud,
        &CloudVolumes,
        &CloudIllumination,
        Option<&CloudViewVolumes>,
    ),
    view: &ExtractedView,
) -> Option<AtlasEntry> {
    if cloud.settings.compositing != Compositing::ViewTransmittance {
        return None;
    }
    let (params, key) = view_params(cloud, volumes, illumination.keys.density, view)?;
    // Where the camera is in cloud-local space: what the multiple scattering is seen from.
    let seen_key = (params.seen_n > 0).then(|| {
        let camera = params.local_from_view.w_axis;
        key_of((camera.to_array().map(f32::to_bits), params.seen_n))
    });
    Some(AtlasEntry {
        entity,
        params,
        key,
        seen_key: seen_key.unwrap_or(0),
        // As `queue_cloud_billboards` decides (illumination ready, some extinction).
        drawn: illumination.ready && cloud.extinction > 0.0,
    })
}

/// Writes a volume's uniform when it changed, and marks it pending when what its march reads or
/// where it writes changed. An unlit volume is never marched: it is seen through by no one and
/// lights nothing. Returns whether it wrote the uniform.
fn update_volume(
    volume: &mut ViewVolume,
    index: u32,
    entry: &AtlasEntry,
    queue: &RenderQueue,
) -> bool {
    volume.entry = index;
    let written = volume.written != Some(entry.params);
    if written {
        volume.written = Some(entry.params);
        queue.write_buffer(&volume.params, 0, &uniform_bytes(&entry.params));
    }
    if entry.key == UNLIT {
        volume.key = UNLIT;
        volume.pending = false;
        volume.ready = true;
    } else if entry.key != volume.key {
        volume.key = entry.key;
        volume.pending = true;
    }
    if entry.seen_key != volume.seen_key {
        volume.seen_key = entry.seen_key;
        volume.seen_pending = true;
    }
    written
}

/// The uniform of one view's volume of `cloud` and the key of its inputs, or `None` when the cloud
/// is not in front of the view. An unlit cloud (no light, no sky) scatters nothing, so it needs no optical depth
/// towards the camera (and has no density grid): a volume of 2³ nodes and no neighbours, keyed
/// `UNLIT`.
fn view_params(
    cloud: &ExtractedCloud,
    volumes: &CloudVolumes,
    density_key: u64,
    view: &ExtractedView,
) -> Option<(ViewVolumeParams, u64)> {
    if volumes.params.lit == 0 {
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
        // An anisotropic cloud's billboards see its multiple scattering through the phase
        // function: evaluated once per voxel towards the camera (docs/illumination.md §5).
        seen_n: if volumes.params.moments != 0 {
            volumes.params.n
        } else {
            0
        },
        ..default()
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

fn new_volume(device: &RenderDevice) -> ViewVolume {
    ViewVolume {
        params: device.create_buffer(&BufferDescriptor {
            label: Some("particle_clouds_view_volume_params"),
            size: ViewVolumeParams::min_size().get(),
            usage: BufferUsages::UNIFORM | BufferUsages::COPY_DST,
            mapped_at_creation: false,
        }),
        written: None,
        key: 0,
        pending: false,
        ready: false,
        entry: 0,
        seen_key: 0,
        seen_pending: false,
        seen_from: None,
    }
}
