//! Per-cloud GPU volumes, and the prepare system that sizes them, writes their uniforms and plans
//! the frame's stages ([`plan`](crate::render::plan)). The density grid lives in cloud-local space, so
//! moving or rotating a cloud never re-voxelizes it: rotation only re-shades (the lights' local
//! directions change) and scale only changes the extinction.

use bevy::{
    platform::collections::{HashMap, HashSet},
    prelude::*,
    render::{
        render_asset::RenderAssets,
        render_resource::{Buffer, ShaderType},
        renderer::{RenderDevice, RenderQueue},
    },
};

use crate::render::{
    core::gpu::{storage_bytes, uniform, uniform_bytes},
    extract::particles::{CloudBounds, GpuParticles},
    extract::{CloudLight, ExtractedCloud, ExtractedCloudLights},
    plan::budget::{RelightCandidate, relit_this_frame},
    plan::casters::{CloudSphere, WorldCloud, casters_of, casts_on},
    plan::ground::{ground_frame, ground_key, ground_map_bytes},
    plan::overlap::{neighbours_of, overlaps},
    plan::params::{
        at_resolution, cloud_params, dense_medium_warning, fine_params, frame_keys, levels_in_use,
        light_params, volume_shape,
    },
    plan::pools::{PoolSlot, Slot, VolumePool, VolumePools, VolumeShape},
    plan::{CloudIllumination, StageKeys, plan},
};
use crate::settings::CloudRelightBudget;
use crate::shadow_maps::CloudShadowMaps;
use crate::stats::CloudPassCounters;

// The uniforms lived here before `core/types.rs`; their public paths stay.
pub use crate::render::core::types::{CloudParams, DensityLevels, LightParams};

/// The GPU volumes of one cloud (render world component): its uniforms, and its slot in the
/// pool of its shape, which holds its density, light and scattering volumes
/// ([`pools`](crate::render::plan::pools)).
#[derive(Component)]
pub struct CloudVolumes {
    /// The current uniform values.
    pub params: CloudParams,
    /// The `CloudParams` uniform (the billboards).
    pub params_buffer: Buffer,
    /// The fine grid's uniform: `CloudParams` with `m` voxels per side of size `h / f` (on the
    /// GPU in the slot's `fine`, which voxelize and shade read; the view volume's pass reads it
    /// here).
    pub fine_params: CloudParams,
    /// The levels that hold particles (the fine grid and the coarser ones down to the largest
    /// particle's): only these are enlarged, so a cloud of small particles does no upsampling.
    pub levels_in_use: usize,
    /// Its lights' uniforms as its light volumes were last shaded (the cast reads them when
    /// this cloud shadows another).
    pub lights: Vec<LightParams>,
    /// Its slot in the pool of its shape.
    pub slot: PoolSlot,
}

impl CloudVolumes {
    /// Volumes for a cloud of `shape` with `particle_count` particles, in a slot of `pools`;
    /// `None` when one such cloud exceeds the adapter's storage binding limit.
    fn new(
        device: &RenderDevice,
        queue: &RenderQueue,
        pools: &mut VolumePools,
        shape: VolumeShape,
        particle_count: u32,
    ) -> Option<Self> {
        let max_binding = device.limits().max_storage_buffer_binding_size;
        let slot = pools.allocate(device, queue, shape, max_binding)?;
        Some(Self {
            params: CloudParams {
                n: shape.n,
                particle_count,
                light_n: shape.m,
                light_count: shape.lights,
                ..default()
            },
            params_buffer: uniform(
                device,
                "particle_clouds_params",
                CloudParams::min_size().get(),
            ),
            fine_params: CloudParams::default(),
            levels_in_use: 1,
            lights: Vec::new(),
            slot,
        })
    }

    fn fits(&self, shape: VolumeShape, particle_count: u32) -> bool {
        self.shape() == shape && self.params.particle_count == particle_count
    }

    /// The shape of its volumes (its pool's).
    pub fn shape(&self) -> VolumeShape {
        self.slot.pool.shape
    }
}

/// The most particles one cloud may hold: the voxelize dispatch gives each 64 particles a
/// workgroup along x, where at most 65535 fit.
pub const MAX_PARTICLES: u32 = 65535 * 64;

/// Decides the work of each cloud that is seen, or that shadows or overlaps one that is, and
/// writes the uniforms it needs. Planned in two steps, since a cloud's illumination takes what
/// other clouds give it (their shadows, [`cast`](crate::render::plan::casters); their media where they overlap
/// it, [`overlap`](crate::render::plan::overlap)): first every cloud's own stages (and which of them the
/// re-light budget defers), then what each takes from the others, from the volumes the others
/// will hold.
#[allow(clippy::too_many_arguments)]
pub(crate) fn prepare_cloud_volumes(
    mut commands: Commands,
    mut clouds: Query<PreparedCloud>,
    lights: Res<ExtractedCloudLights>,
    particles: Res<RenderAssets<GpuParticles>>,
    budget: Option<Res<CloudRelightBudget>>,
    maps: Option<Res<CloudShadowMaps>>,
    mut pools: ResMut<VolumePools>,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
    counters: Res<CloudPassCounters>,
) {
    let budget = budget.map_or(0, |b| b.0);
    let mapped = maps.is_some_and(|m| m.resolution > 0);
    let max_binding = device.limits().max_storage_buffer_binding_size;
    let frames = cloud_frames(&clouds, &lights, &particles, mapped, max_binding);
    let deferred = deferred_by_budget(&clouds, &frames, &lights, &particles, budget);
    // What each cloud's volumes will hold after this frame: a deferred cloud keeps what it has.
    let world = world_clouds(&frames, |entity, frame| {
        let held = clouds.get(entity).ok().and_then(|(.., state)| state);
        match held {
            Some(state) if deferred.contains(&entity) => state.keys.clone(),
            _ => frame.keys.clone(),
        }
    });
    let directions: Vec<Vec3> = lights.lights.iter().map(|l| l.direction).collect();
    pools.release_empty();
    for (entity, cloud, volumes, state) in &mut clouds {
        let Some(gpu) = particles.get(cloud.particles) else {
            continue;
        };
        if gpu.bounds.is_none() {
            commands
                .entity(entity)
                .remove::<(CloudVolumes, CloudIllumination)>();
            continue;
        }
        // No work for clouds nobody sees (nor shadows or overlaps one that is seen), or that are
        // transparent: their cached volumes stay.
        let Some(frame) = frames.get(&entity).filter(|f| f.needed) else {
            continue;
        };
        let (cloud, bounds, shape) = (&frame.cloud, frame.bounds, frame.shape);
        let planned = PlannedFrame {
            entity,
            cloud,
            gpu,
            bounds,
            lights: &lights,
            others: from_others(entity, frame, &world, &directions),
        };
        match (volumes, state) {
            (Some(_), Some(mut state)) if deferred.contains(&entity) => {
                // Its turn comes later: it draws with what its volumes hold.
                state.plan = default();
                state.waited += 1;
            }
            (Some(mut v), Some(mut state)) if v.fits(shape, gpu.count) => {
                let pool = pools.pool(&v.slot);
                plan_cloud(&mut v, &mut state, planned, pool, &queue);
                state.waited = 0;
                if !state.plan.is_empty() {
                    counters.note_write();
                }
            }
            _ => {
                let new = (gpu.count as u64 * 32 <= max_binding)
                    .then(|| CloudVolumes::new(&device, &queue, &mut pools, shape, gpu.count))
                    .flatten();
                let Some(mut v) = new else {
                    warn_once!(
                        "particle cloud: `volume_resolution` {} (light volumes {}³ for {} lights) \
                         or {} particles exceed this adapter's storage buffer limit of \
                         {max_binding} bytes; the cloud is not drawn",
                        shape.n,
                        shape.m,
                        shape.lights,
                        gpu.count
                    );
                    commands
                        .entity(entity)
                        .remove::<(CloudVolumes, CloudIllumination)>();
                    continue;
                };
                let mut state = CloudIllumination::default();
                let pool = pools.pool(&v.slot);
                plan_cloud(&mut v, &mut state, planned, pool, &queue);
                counters.note_write();
                commands.entity(entity).insert((v, state));
            }
        }
    }
}

/// A cloud as the prepare system sees it.
type PreparedCloud = (
    Entity,
    &'static ExtractedCloud,
    Option<&'static mut CloudVolumes>,
    Option<&'static mut CloudIllumination>,
);

/// A cloud with particles and extinction, as this frame illuminates it.
struct CloudFrame {
    /// The cloud at the resolution it is illuminated at this frame (its level of detail's, or
    /// the one its volumes hold).
    cloud: ExtractedCloud,
    bounds: CloudBounds,
    shape: VolumeShape,
    /// Its bounding sphere in the world.
    sphere: CloudSphere,
    /// Seen in a view, or shadowing or overlapping a cloud that is: it must be illuminated.
    needed: bool,
    /// This frame's stage keys, without what other clouds give it.
    keys: StageKeys,
}

/// Every cloud that has particles and extinction, as this frame illuminates it; with cloud
/// shadow maps (`mapped`), every cloud that casts shadows is needed, seen or not.
fn cloud_frames(
    clouds: &Query<PreparedCloud>,
    lights: &ExtractedCloudLights,
    particles: &RenderAssets<GpuParticles>,
    mapped: bool,
    max_binding: u64,
) -> HashMap<Entity, CloudFrame> {
    let mut frames: HashMap<Entity, CloudFrame> = HashMap::default();
    for (entity, cloud, volumes, state) in clouds {
        let Some(gpu) = particles.get(cloud.particles) else {
            continue;
        };
        let Some(bounds) = gpu.bounds.filter(|_| cloud.extinction > 0.0) else {
            continue;
        };
        let held = volumes.zip(state);
        let n = held_resolution(cloud, held, gpu, bounds, lights, max_binding);
        let cloud = at_resolution(cloud, n, lights, max_binding);
        let shape = volume_shape(&cloud, lights);
        let frame = CloudFrame {
            sphere: CloudSphere::new(bounds, &cloud.world_from_local, cloud.scale()),
            needed: cloud.visible || (mapped && cloud.casts_shadows),
            keys: frame_keys(&cloud, gpu, bounds, lights, &[], 0),
            cloud,
            bounds,
            shape,
        };
        frames.insert(entity, frame);
    }
    // A cloud nobody sees is still illuminated when it shadows or overlaps one that is seen.
    let seen: Vec<(CloudSphere, bool)> = frames
        .values()
        .filter(|f| f.needed)
        .map(|f| (f.sphere, f.cloud.receives_shadows))
        .collect();
    for frame in frames.values_mut().filter(|f| !f.needed) {
        let casts = |receiver: CloudSphere| {
            let light = |l: &CloudLight| casts_on(l.direction, receiver, frame.sphere);
            frame.cloud.casts_shadows && lights.lights.iter().any(light)
        };
        frame.needed = seen.iter().any(|&(receiver, receives)| {
            overlaps(receiver, frame.sphere) || (receives && casts(receiver))
        });
    }
    frames
}

/// The clouds of `frames` that must be illuminated, as other clouds see them, each with the keys
/// `held` gives it (what its volumes will hold after this frame).
fn world_clouds(
    frames: &HashMap<Entity, CloudFrame>,
    held: impl Fn(Entity, &CloudFrame) -> StageKeys,
) -> Vec<WorldCloud> {
    frames
        .iter()
        .filter(|(_, f)| f.needed)
        .map(|(&entity, f)| world_cloud(entity, f, held(entity, f)))
        .collect()
}

fn world_cloud(entity: Entity, frame: &CloudFrame, keys: StageKeys) -> WorldCloud {
    WorldCloud {
        entity,
        sphere: frame.sphere,
        world_from_local: frame.cloud.world_from_local,
        extinction: frame.cloud.extinction,
        albedo: frame.cloud.albedo,
        anisotropy: frame.cloud.anisotropy,
        density: keys.density,
        shade_keys: keys.lights,
        casts_shadows: frame.cloud.casts_shadows,
    }
}

/// What other clouds give a cloud this frame ([`casters_of`], [`neighbours_of`]).
#[derive(Default)]
struct FromOthers {
    /// Per light slot, the clouds casting their shadow on it.
    casters: Vec<Vec<Entity>>,
    /// Per light slot, the key of what they cast.
    cast_keys: Vec<u64>,
    /// The clouds whose media reach into its grid.
    neighbours: Vec<Entity>,
    /// The key of their media.
    media: u64,
}

/// What the clouds of `world` give cloud `entity`: shadows along the lights travelling along
/// `directions` (none on a cloud that takes no shadows), and their media where they overlap it.
fn from_others(
    entity: Entity,
    frame: &CloudFrame,
    world: &[WorldCloud],
    directions: &[Vec3],
) -> FromOthers {
    let receiver = world_cloud(entity, frame, StageKeys::default());
    let (casters, cast_keys) = if frame.cloud.receives_shadows {
        casters_of(&receiver, world, directions)
    } else {
        (Vec::new(), Vec::new())
    };
    let (neighbours, media) = neighbours_of(&receiver, world);
    FromOthers {
        casters,
        cast_keys,
        neighbours,
        media,
    }
}

/// The needed clouds whose pending illumination work waits for a later frame under the
/// re-light `budget` (none when it is 0): every cloud whose stage keys changed is a candidate,
/// and [`relit_this_frame`] picks those that go now. What other clouds give a candidate is
/// judged as if they were all re-lit.
fn deferred_by_budget(
    clouds: &Query<PreparedCloud>,
    frames: &HashMap<Entity, CloudFrame>,
    lights: &ExtractedCloudLights,
    particles: &RenderAssets<GpuParticles>,
    budget: u32,
) -> HashSet<Entity> {
    if budget == 0 {
        return HashSet::default();
    }
    let world = world_clouds(frames, |_, f| f.keys.clone());
    let directions: Vec<Vec3> = lights.lights.iter().map(|l| l.direction).collect();
    let mut candidates = Vec::new();
    for (entity, cloud, volumes, state) in clouds {
        let (Some(frame), Some(gpu)) = (frames.get(&entity), particles.get(cloud.particles)) else {
            continue;
        };
        if !frame.needed {
            continue;
        }
        // A cloud whose level of detail changes (its volumes no longer fit) waits its turn like
        // any other; only one never illuminated cannot wait.
        match volumes.zip(state) {
            Some((v, s)) if s.ready => {
                let others = from_others(entity, frame, &world, &directions);
                let (casts, media) = (&others.cast_keys, others.media);
                let keys = frame_keys(&frame.cloud, gpu, frame.bounds, lights, casts, media);
                let pending = !v.fits(frame.shape, gpu.count)
                    || !plan(&s.keys, &keys, &frame.cloud.settings).is_empty();
                if pending {
                    candidates.push(RelightCandidate {
                        entity,
                        first: false,
                        waited: s.waited,
                    });
                }
            }
            _ => candidates.push(RelightCandidate {
                entity,
                first: true,
                waited: 0,
            }),
        }
    }
    let pending: HashSet<Entity> = candidates.iter().map(|c| c.entity).collect();
    let relit: HashSet<Entity> = relit_this_frame(candidates, budget).into_iter().collect();
    pending.difference(&relit).copied().collect()
}

/// What [`plan_cloud`] plans from: the cloud, its particles and grid, the lights, and what other
/// clouds give it.
struct PlannedFrame<'a> {
    entity: Entity,
    cloud: &'a ExtractedCloud,
    gpu: &'a GpuParticles,
    bounds: CloudBounds,
    lights: &'a ExtractedCloudLights,
    others: FromOthers,
}

/// Plans the cloud's stages and writes the uniforms they read: its own, and its slot's in `pool`.
fn plan_cloud(
    volumes: &mut CloudVolumes,
    state: &mut CloudIllumination,
    frame: PlannedFrame,
    pool: &VolumePool,
    queue: &RenderQueue,
) {
    let PlannedFrame {
        entity,
        cloud,
        gpu,
        bounds,
        lights,
        others,
    } = frame;
    let params = CloudParams {
        foreign: !others.neighbours.is_empty() as u32,
        ..cloud_params(cloud, gpu, bounds, lights)
    };
    // Slot i shades the i-th light (none: the cloud only absorbs, and the plan zeroes its
    // multiple scattering once).
    let light_params = light_params(&params, cloud, lights);
    let ground = ground_frame(cloud, &params, lights.ground.as_ref(), lights.sky);
    state.update(
        StageKeys::new(
            &params,
            &light_params,
            &others.cast_keys,
            others.media,
            (lights.sky, ground_key(&ground)),
            gpu.generation,
            &cloud.settings,
        ),
        &cloud.settings,
    );
    state.casters = others.casters;
    state.neighbours = others.neighbours;
    if state.plan.is_empty() {
        return;
    }
    if params != volumes.params {
        if let Some(problem) =
            dense_medium_warning(cloud.extinction, &volumes.params, &params, bounds)
        {
            warn!("particle cloud {entity}: {problem}");
        }
        queue.write_buffer(&volumes.params_buffer, 0, &uniform_bytes(&params));
        volumes.params = params;
    }
    volumes.levels_in_use = levels_in_use(bounds, params.light_n);
    let fine = fine_params(&params);
    volumes.fine_params = fine;
    let index = volumes.slot.index;
    let slot = pool.slot(index, params, fine);
    let slot_bytes = Slot::min_size().get();
    queue.write_buffer(
        &pool.slots,
        index as u64 * slot_bytes,
        &storage_bytes(&[slot]),
    );
    if let Some(coarse) = &pool.coarse {
        let coarse_slot = pool.coarse_slot(index, params);
        let at = index as u64 * slot_bytes;
        queue.write_buffer(&coarse.slots, at, &storage_bytes(&[coarse_slot]));
    }
    if !light_params.is_empty() {
        let first = slot.lights as u64 * LightParams::min_size().get();
        queue.write_buffer(&pool.lights, first, &storage_bytes(&light_params));
    }
    if state.plan.scatter.is_some() {
        let at = index as u64 * ground_map_bytes();
        queue.write_buffer(&pool.ground, at, &storage_bytes(&[ground]));
    }
    volumes.lights = light_params;
}

/// The volume resolution a cloud is illuminated at this frame: the one its level of detail asks
/// for, once its volumes must be re-lit anyway (new particles, or a light that moved) or when it
/// has none yet; until then the one its volumes hold, so a level change never pops on a still
/// sky (docs/illumination.md §7). Without level of detail, the settings' resolution at once.
fn held_resolution(
    cloud: &ExtractedCloud,
    held: Option<(&CloudVolumes, &CloudIllumination)>,
    gpu: &GpuParticles,
    bounds: CloudBounds,
    lights: &ExtractedCloudLights,
    max_binding: u64,
) -> u32 {
    let wanted = cloud.lod_resolution;
    let Some((volumes, state)) = held else {
        return wanted;
    };
    let n = volumes.params.n;
    if n == wanted || !cloud.lod_enabled || !state.ready || !lights.any() {
        return wanted;
    }
    let at_n = at_resolution(cloud, n, lights, max_binding);
    let now = frame_keys(&at_n, gpu, bounds, lights, &[], 0);
    let relit = now.density != state.keys.density || now.lights != state.keys.lights;
    if relit { wanted } else { n }
}
