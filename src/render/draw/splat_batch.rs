//! The splat's batches (`DrawMethod::Compute`): every cloud a view splats whose volumes share a
//! pool and whose medium is the same is splatted by one dispatch, so that the draw's dispatches
//! grow with the volume shapes and media in use, not with the clouds (issue #11; the illumination
//! passes batch the same way, docs/illumination.md §9). A batch binds its pool's buffers whole,
//! the view's atlas, and its clouds' particles copied end to end, each cloud's from a workgroup
//! boundary; a `SplatCloud` per cloud holds its uniforms and where its elements start.

use std::collections::BTreeMap;

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_asset::RenderAssets,
        render_resource::{
            BindGroup, BindGroupEntries, BindGroupLayout, BindGroupLayoutDescriptor, Buffer,
            BufferDescriptor, BufferUsages, CommandEncoderDescriptor, PipelineCache, ShaderStages,
            ShaderType, binding_types::storage_buffer_read_only_sized,
        },
        renderer::{RenderDevice, RenderQueue},
        view::{ExtractedView, RetainedViewEntity},
    },
};

use crate::render::{
    core::gpu::{indexed_layout, storage_init},
    core::key_of,
    core::workgroups::LINEAR,
    draw::target::ViewCloudSplats,
    draw::{CloudDrawBindGroups, DrawParams, draw_params},
    extract::ExtractedCloud,
    extract::particles::{GpuParticle, GpuParticles},
    plan::pools::{PoolId, VolumePool, VolumePools},
    plan::volumes::{CloudParams, CloudVolumes, LightParams},
    view::view_atlas::{ViewVolumeAtlas, ViewVolumeAtlases},
    view::view_volume::CloudViewVolumes,
};

/// Mirror of `CloudBases` in `billboard.wgsl`: where a cloud's elements start in its pool's
/// buffers.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq, Hash)]
pub struct CloudBases {
    /// First `LightParams` of its lights.
    pub lights: u32,
    /// First f32 of its light volumes.
    pub optical_depth: u32,
    /// First vec4 of its multiple scattering (unread where the view's atlas holds it).
    pub multiple: u32,
}

/// Mirror of `SplatCloud` in `billboard.wgsl`: one cloud of a batch.
#[derive(ShaderType, Clone, Copy, Debug, Default)]
pub struct SplatCloud {
    /// The billboards' uniform.
    pub draw: DrawParams,
    /// The scattering grid's uniform.
    pub cloud: CloudParams,
    /// Its first workgroup: its particles start at particle `first_group * LINEAR`.
    pub first_group: u32,
    /// Its particles.
    pub particle_count: u32,
    /// Its view volume's element of the atlas's `volumes`.
    pub view_volume: u32,
    /// Where its elements start in the pool's buffers.
    pub bases: CloudBases,
}

/// Group 1 of the splat pipeline: the batch's clouds (0), their particles (2), the pool's lights
/// (4), light volumes (5), multiple scattering or the atlas's seen from the camera (6), the
/// atlas's optical depths, volumes and neighbour lists (7–9), the medium's beam table (10). The
/// numbers are the billboards' group 1 numbers for the same arrays.
pub(crate) fn splat_batch_layout() -> BindGroupLayoutDescriptor {
    let read = || storage_buffer_read_only_sized(false, None);
    indexed_layout(
        "particle_clouds_splat_batch_layout",
        ShaderStages::COMPUTE,
        (
            (0, read()),
            (2, read()),
            (4, read()),
            (5, read()),
            (6, read()),
            (7, read()),
            (8, read()),
            (9, read()),
            (10, read()),
        ),
    )
}

/// What makes clouds splat together: their pool, their medium's anisotropy (its beam table), and
/// whether the view's atlas holds their multiple scattering (anisotropic media) or their pool.
/// Clouds of one kind whose particles exceed one storage binding together are split into parts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BatchKey {
    pool: PoolId,
    anisotropy: u32,
    seen_from_camera: bool,
    part: u32,
}

/// The part of its kind a batch's next cloud goes into: the current one while the particles fit
/// in one storage binding of `max_bytes`, else a new one.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct PartFill {
    part: u32,
    bytes: u64,
}

impl PartFill {
    /// Takes `bytes` of particles into the current part, or into a new one when they would not fit
    /// (a cloud larger than a binding has a part of its own); returns the part.
    fn take(&mut self, bytes: u64, max_bytes: u64) -> u32 {
        if self.bytes > 0 && self.bytes + bytes > max_bytes {
            *self = Self {
                part: self.part + 1,
                bytes: 0,
            };
        }
        self.bytes += bytes;
        self.part
    }
}

/// Bytes of `count` particles in a batch's copy: whole workgroups of them.
fn padded_bytes(count: u32) -> u64 {
    (count.div_ceil(LINEAR) * LINEAR) as u64 * size_of::<GpuParticle>() as u64
}

/// One batch's buffers and group 1.
pub struct SplatBatch {
    /// Key of everything the group binds.
    key: u64,
    /// Key of the particles copied into `particles`.
    particles_key: u64,
    particles: Buffer,
    _clouds: Buffer,
    /// Group 1 of the splat pipeline.
    pub group: BindGroup,
    /// Workgroups per slice: one per [`LINEAR`] particles of each cloud.
    pub groups: u32,
    /// Clouds in the batch.
    pub clouds: u32,
}

impl SplatBatch {
    /// Its buffers (the memory census).
    pub(crate) fn buffers(&self) -> [&Buffer; 2] {
        [&self.particles, &self._clouds]
    }

    /// The key of everything its group binds: its clouds' uniforms, its particles and the
    /// buffers it reads.
    pub(crate) fn key(&self) -> u64 {
        self.key
    }
}

/// A computing view's batches, dispatched in the order of their keys.
#[derive(Component, Default)]
pub struct ViewSplatBatches(pub BTreeMap<BatchKey, SplatBatch>);

/// One cloud a view splats, with what its batch needs of it.
struct Member<'a> {
    cloud: SplatCloud,
    particles: &'a GpuParticles,
    beam_phase: &'a Buffer,
}

/// Each cloud's first workgroup when `counts` particles are laid end to end, each from a
/// workgroup boundary; and the workgroups in all.
pub(crate) fn first_groups(counts: &[u32]) -> (Vec<u32>, u32) {
    let mut total = 0;
    let firsts = counts
        .iter()
        .map(|&count| {
            let first = total;
            total += count.div_ceil(LINEAR);
            first
        })
        .collect();
    (firsts, total)
}

/// The clouds of `entities` a view can splat, grouped into batches (in the order they come).
fn batch_members<'a>(
    entities: &[Entity],
    view: &RetainedViewEntity,
    pools: &VolumePools,
    particles: &'a RenderAssets<GpuParticles>,
    max_bytes: u64,
    cloud: impl Fn(Entity) -> Option<SplatSource<'a>>,
) -> Vec<(BatchKey, Vec<Member<'a>>)> {
    let mut batches: Vec<(BatchKey, Vec<Member<'a>>)> = Vec::new();
    let mut fills: HashMap<BatchKey, PartFill> = HashMap::default();
    for &entity in entities {
        let Some((extracted, volumes, view_volumes, draws)) = cloud(entity) else {
            continue;
        };
        let (Some(gpu), Some(volume), Some(_)) = (
            particles.get(extracted.particles),
            view_volumes.0.get(view),
            draws.groups.get(view),
        ) else {
            continue;
        };
        if gpu.count == 0 || volume.uniform().is_none() {
            continue;
        }
        let pool = pools.pool(&volumes.slot);
        let index = volumes.slot.index;
        let kind = BatchKey {
            pool: volumes.slot.pool,
            anisotropy: extracted.anisotropy.to_bits(),
            seen_from_camera: volume.sees_multiple(),
            part: 0,
        };
        let part = (fills.entry(kind).or_default()).take(padded_bytes(gpu.count), max_bytes);
        let key = BatchKey { part, ..kind };
        let member = Member {
            cloud: SplatCloud {
                draw: draw_params(extracted),
                cloud: volumes.params,
                first_group: 0,
                particle_count: gpu.count,
                view_volume: volume.atlas_index(),
                bases: CloudBases {
                    lights: (pool.lights(index).offset / LightParams::min_size().get()) as u32,
                    optical_depth: (pool.optical_depth(index).offset / 4) as u32,
                    multiple: (pool.multiple(index).offset / 16) as u32,
                },
            },
            particles: gpu,
            beam_phase: draws.beam_phase(),
        };
        match batches.iter_mut().find(|(k, _)| *k == key) {
            Some((_, members)) => members.push(member),
            None => batches.push((key, vec![member])),
        }
    }
    batches
}

/// What a batch reads of one cloud.
type SplatSource<'a> = (
    &'a ExtractedCloud,
    &'a CloudVolumes,
    &'a CloudViewVolumes,
    &'a CloudDrawBindGroups,
);

/// Copies the members' particles end to end into a new buffer, each from its first workgroup.
fn copy_particles(
    device: &RenderDevice,
    queue: &RenderQueue,
    members: &[Member],
    groups: u32,
) -> Buffer {
    let stride = size_of::<GpuParticle>() as u64;
    let buffer = device.create_buffer(&BufferDescriptor {
        label: Some("particle_clouds_splat_particles"),
        size: (groups as u64 * LINEAR as u64 * stride).max(16),
        usage: BufferUsages::STORAGE | BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = device.create_command_encoder(&CommandEncoderDescriptor {
        label: Some("particle_clouds_splat_particles_copy"),
    });
    for m in members {
        let at = m.cloud.first_group as u64 * LINEAR as u64 * stride;
        let bytes = m.particles.count as u64 * stride;
        encoder.copy_buffer_to_buffer(&m.particles.buffer, 0, &buffer, at, bytes);
    }
    queue.submit([encoder.finish()]);
    buffer
}

/// The atlas's or the pool's multiple scattering, as the batch reads it.
fn multiple_source<'a>(
    key: &BatchKey,
    atlas: &'a ViewVolumeAtlas,
    pools: &'a VolumePools,
) -> &'a Buffer {
    if key.seen_from_camera {
        &atlas.seen_multiple
    } else {
        &pools.0[&key.pool].multiple
    }
}

/// Gives every computing view its splat batches, remaking a batch's buffers only when what it
/// holds changed (a static frame remakes nothing; a moving cloud rewrites its batch's clouds but
/// copies no particles).
#[allow(clippy::too_many_arguments)] // a render system's resources
pub(crate) fn prepare_splat_batches(
    mut commands: Commands,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
    cache: Res<PipelineCache>,
    pools: Res<VolumePools>,
    atlases: Res<ViewVolumeAtlases>,
    particles: Res<RenderAssets<GpuParticles>>,
    mut views: Query<(
        Entity,
        &ExtractedView,
        &ViewCloudSplats,
        Option<&mut ViewSplatBatches>,
    )>,
    clouds: Query<(
        &ExtractedCloud,
        &CloudVolumes,
        &CloudViewVolumes,
        &CloudDrawBindGroups,
    )>,
) {
    let layout = cache.get_bind_group_layout(&splat_batch_layout());
    let limits = device.limits();
    let max_bytes = limits
        .max_storage_buffer_binding_size
        .min(limits.max_buffer_size);
    for (entity, view, splats, existing) in &mut views {
        let retained = &view.retained_view_entity;
        let Some(atlas) = atlases.0.get(retained) else {
            // No view volumes, so no cloud to splat: none of last frame's batches either.
            commands.entity(entity).remove::<ViewSplatBatches>();
            continue;
        };
        let batches = batch_members(&splats.0, retained, &pools, &particles, max_bytes, |e| {
            clouds.get(e).ok()
        });
        let mut old = existing.map(|mut e| std::mem::take(&mut e.0));
        let made = batches
            .into_iter()
            .map(|(key, members)| {
                let previous = old.as_mut().and_then(|o| o.remove(&key));
                let source = BatchSource {
                    pool: &pools.0[&key.pool],
                    multiple: multiple_source(&key, atlas, &pools),
                    atlas,
                };
                let batch = make_batch(&device, &queue, &layout, source, members, previous);
                (key, batch)
            })
            .collect();
        commands.entity(entity).insert(ViewSplatBatches(made));
    }
}

/// What a batch binds besides its own buffers.
struct BatchSource<'a> {
    pool: &'a VolumePool,
    multiple: &'a Buffer,
    atlas: &'a ViewVolumeAtlas,
}

/// A batch of `members`: `previous` as it was when it binds the same, else its group made anew,
/// its particles copied again only when they changed.
fn make_batch(
    device: &RenderDevice,
    queue: &RenderQueue,
    layout: &BindGroupLayout,
    source: BatchSource,
    mut members: Vec<Member>,
    previous: Option<SplatBatch>,
) -> SplatBatch {
    let counts: Vec<u32> = members.iter().map(|m| m.cloud.particle_count).collect();
    let (firsts, groups) = first_groups(&counts);
    for (m, first) in members.iter_mut().zip(firsts) {
        m.cloud.first_group = first;
    }
    let clouds: Vec<SplatCloud> = members.iter().map(|m| m.cloud).collect();
    let particles_key = key_of(
        (members.iter())
            .map(|m| (m.particles.buffer.id(), m.particles.count))
            .collect::<Vec<_>>(),
    );
    let BatchSource {
        pool,
        multiple,
        atlas,
    } = source;
    let beam_phase = members[0].beam_phase;
    let bound = key_of((
        crate::render::core::gpu::storage_bytes(&clouds),
        particles_key,
        [&pool.lights, &pool.optical_depth, multiple].map(|b| b.id()),
        [&atlas.optical_depth, &atlas.volumes, &atlas.neighbours].map(|b| b.id()),
        beam_phase.id(),
    ));
    let particles = match previous {
        Some(batch) if batch.key == bound => return batch,
        Some(batch) if batch.particles_key == particles_key => batch.particles,
        _ => copy_particles(device, queue, &members, groups),
    };
    let clouds_buffer = storage_init(device, "particle_clouds_splat_clouds", &clouds);
    let group = device.create_bind_group(
        "particle_clouds_splat_batch_bind_group",
        layout,
        &BindGroupEntries::with_indices((
            (0, clouds_buffer.as_entire_binding()),
            (2, particles.as_entire_binding()),
            (4, pool.lights.as_entire_binding()),
            (5, pool.optical_depth.as_entire_binding()),
            (6, multiple.as_entire_binding()),
            (7, atlas.optical_depth.as_entire_binding()),
            (8, atlas.volumes.as_entire_binding()),
            (9, atlas.neighbours.as_entire_binding()),
            (10, beam_phase.as_entire_binding()),
        )),
    );
    SplatBatch {
        key: bound,
        particles_key,
        particles,
        _clouds: clouds_buffer,
        group,
        groups,
        clouds: members.len() as u32,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_cloud_starts_on_a_workgroup_of_its_own() {
        // 64 particles a workgroup: 1 → 1 group, 64 → 1, 65 → 2.
        let (firsts, total) = first_groups(&[1, 64, 65, 130]);
        assert_eq!(firsts, [0, 1, 2, 4]);
        assert_eq!(total, 7);
        assert_eq!(first_groups(&[]), (vec![], 0));
    }

    #[test]
    fn clouds_whose_particles_exceed_a_binding_together_go_into_parts() {
        // 100 particles take two workgroups: 128 × 32 bytes.
        assert_eq!(padded_bytes(100), 4096);
        let mut fill = PartFill::default();
        let parts: Vec<u32> = [4096, 4096, 4096, 20_000, 4096]
            .map(|bytes| fill.take(bytes, 10_000))
            .into();
        // Two fit, the third opens part 1; a cloud above the limit has a part of its own.
        assert_eq!(parts, [0, 0, 1, 2, 3]);
    }
}
