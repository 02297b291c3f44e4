//! The illumination passes' batches, made in `PrepareBindGroups`: what each volume pool's clouds
//! run this frame (from their plans), and the bind groups and work lists of every pass over it.

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_asset::RenderAssets,
        render_resource::{BindGroup, BindGroupEntries, BindGroupEntry, Buffer, PipelineCache},
        renderer::RenderDevice,
        storage::GpuShaderBuffer,
    },
};

use crate::render::{
    core::gpu::Batch,
    core::gpu::{WorkList, storage, storage_init},
    extract::particles::GpuParticles,
    extract::{ExtractedCloud, ExtractedCloudLights},
    illumination::cast::add_light_cast,
    illumination::pipelines::{ComputeStage, IlluminationPipelines},
    illumination::scatter::coarse_grid::CycleBatch,
    illumination::scatter::overlap::{OverlapWork, add_overlaps},
    illumination::scatter::{ScatterBatch, scatter_batch},
    illumination::shadow_maps::{LitCloud, ShadowMapCasts, ShadowMapKeys, shadow_map_casts},
    illumination::sky_map::{SkyMapFill, SkyMapKey, sky_map_fill},
    illumination::voxelize::{VoxelizeCloud, VoxelizeRound, VoxelizeScratch, voxelize_rounds},
    plan::CloudIllumination,
    plan::casters::{CastWork, Caster},
    plan::pools::{PoolId, VolumePools},
    plan::volumes::CloudVolumes,
};
use crate::{
    settings::{ScatterStencil, SweepDirections, SweepDispatch},
    shadow_maps::CloudShadowMaps,
};

/// The batched passes of one volume pool this frame.
pub(crate) struct PoolBatches {
    /// Voxels per side of the scattering grid, and of the fine grid and light volumes.
    pub(crate) n: u32,
    pub(crate) m: u32,
    /// Its scattering volumes hold angular moments: the `MOMENTS` variants of the stages run.
    pub(crate) moments: bool,
    pub(crate) shade: Option<Batch>,
    /// Other clouds' shadows, one batch per pool their casters lie in (first casts first).
    pub(crate) cast: Vec<Batch>,
    pub(crate) gather: Option<Batch>,
    /// Other clouds' media in the grids of this frame's scattering, one batch per pool the
    /// neighbours lie in (first first).
    pub(crate) overlap: Vec<Batch>,
    /// The ground's radiance under the clouds of this frame's sweeps that a ground lights.
    pub(crate) ground: Option<Batch>,
    pub(crate) scatter: Vec<ScatterBatch>,
}

/// This frame's batched passes, per pool, and the filling of the cloud shadow maps (render world
/// resource, made in `PrepareBindGroups`).
#[derive(Resource, Default)]
pub struct IlluminationBatches {
    /// The clouds whose density is rebuilt, in rounds whose particles fit one binding.
    pub(crate) voxelize: Vec<VoxelizeRound>,
    pub(crate) pools: Vec<PoolBatches>,
    pub(crate) maps: ShadowMapCasts,
    pub(crate) sky: SkyMapFill,
}

/// What the shadow maps' batches are made from: the maps, the lights, the storage buffers (the
/// maps' own) and the keys of what the maps (the lights' and the sky's) hold.
type ShadowMapInputs<'w> = (
    Option<Res<'w, CloudShadowMaps>>,
    Res<'w, ExtractedCloudLights>,
    Res<'w, RenderAssets<GpuShaderBuffer>>,
    (ResMut<'w, ShadowMapKeys>, ResMut<'w, SkyMapKey>),
);

/// What each pool's clouds run this frame: (slot, light) to shade, light volumes to cast on per
/// pool their casters lie in, slots to gather, and slots to scatter per (iterations, stencil,
/// warm restart, coarse-grid cycles).
#[derive(Default)]
struct PoolWork {
    pub(crate) shade: Vec<[u32; 2]>,
    pub(crate) cast: HashMap<PoolId, CastWork>,
    pub(crate) overlap: HashMap<PoolId, OverlapWork>,
    pub(crate) gather: Vec<u32>,
    /// The clouds a ground lights whose scattering runs (their ground maps are filled first).
    pub(crate) ground: Vec<u32>,
    pub(crate) scatter: HashMap<(u32, ScatterStencil, SweepDirections, bool, u32), Vec<u32>>,
}

/// What each pool's passes do this frame, from its clouds' plans, and the clouds each pool
/// voxelizes.
fn pool_work(
    clouds: &Query<IlluminatedCloud>,
    particles: &RenderAssets<GpuParticles>,
    lights: &ExtractedCloudLights,
    pools: &VolumePools,
) -> (
    HashMap<PoolId, PoolWork>,
    HashMap<PoolId, Vec<VoxelizeCloud>>,
) {
    let placed: HashMap<Entity, (&ExtractedCloud, &CloudVolumes)> =
        clouds.iter().map(|(e, c, v, _)| (e, (c, v))).collect();
    let mut work: HashMap<PoolId, PoolWork> = HashMap::default();
    let mut voxelizing: HashMap<PoolId, Vec<VoxelizeCloud>> = HashMap::default();
    for (_, cloud, v, state) in clouds {
        let plan = &state.plan;
        let Some(gpu) = particles.get(cloud.particles).filter(|_| !plan.is_empty()) else {
            continue;
        };
        if plan.voxelize {
            let clouds = voxelizing.entry(v.slot.pool).or_default();
            clouds.push(VoxelizeCloud::new(gpu, v));
        }
        let slot = v.slot.index;
        let w = work.entry(v.slot.pool).or_default();
        w.shade.extend(plan.shade.iter().map(|&l| [slot, l as u32]));
        for &l in &plan.cast {
            let casters = state.casters.get(l).map_or(&[][..], Vec::as_slice);
            add_light_cast(&mut w.cast, (cloud, v), l, casters, &placed, pools);
        }
        if plan.gather {
            w.gather.push(slot);
        }
        if let Some(iterations) = plan.scatter.filter(|&i| i > 0) {
            let key = (
                iterations,
                plan.stencil,
                plan.directions,
                plan.warm,
                plan.cycles,
            );
            w.scatter.entry(key).or_default().push(slot);
            if lights.ground.is_some() && plan.stencil == ScatterStencil::DiscreteOrdinates {
                w.ground.push(slot);
            }
            if v.params.foreign != 0 {
                add_overlaps(
                    &mut w.overlap,
                    (cloud, v),
                    &state.neighbours,
                    &placed,
                    pools,
                );
            }
        }
    }
    (work, voxelizing)
}

/// A cloud as the illumination's prepare system sees it.
type IlluminatedCloud = (
    Entity,
    &'static ExtractedCloud,
    &'static CloudVolumes,
    &'static CloudIllumination,
);

/// Makes the bind groups and work lists of every pool's batched passes, voxelize's included.
#[allow(clippy::too_many_arguments)]
pub(crate) fn prepare_illumination_bind_groups(
    mut commands: Commands,
    clouds: Query<IlluminatedCloud>,
    mut scratch: ResMut<VoxelizeScratch>,
    particles: Res<RenderAssets<GpuParticles>>,
    pools: Res<VolumePools>,
    pipelines: Option<Res<IlluminationPipelines>>,
    pipeline_cache: Res<PipelineCache>,
    device: Res<RenderDevice>,
    (maps, lights, storage, (mut map_keys, mut sky_key)): ShadowMapInputs,
    (dispatch, mut pair_volumes): (Option<Res<SweepDispatch>>, ResMut<SweepPairVolumes>),
) {
    let Some(pipelines) = pipelines else { return };
    let bind = |stage: &ComputeStage, entries: &[BindGroupEntry]| -> BindGroup {
        let layout = pipeline_cache.get_bind_group_layout(&stage.layout);
        device.create_bind_group(None, &layout, entries)
    };
    let (work, voxelizing) = pool_work(&clouds, &particles, &lights, &pools);
    let lit: Vec<LitCloud> = clouds.iter().collect();
    let map_buffer = maps
        .as_deref()
        .and_then(|m| storage.get(&m.buffer))
        .map(|b| &b.buffer);
    let sky = sky_map_fill(
        maps.as_deref().and_then(|m| m.sky.as_ref()),
        map_buffer,
        &lit,
        &mut sky_key,
        &device,
        |pool, casters, lists, target, scratch| {
            let pool = &pools.0[&pool];
            let casters = storage_init(&device, "particle_clouds_sky_casters", casters);
            let lists = storage_init(&device, "particle_clouds_sky_lists", lists);
            let target = storage_init(&device, "particle_clouds_sky_target", &[*target]);
            bind(
                &pipelines.march_sky,
                &BindGroupEntries::sequential((
                    pool.slots.as_entire_binding(),
                    casters.as_entire_binding(),
                    pool.densities.as_entire_binding(),
                    scratch.as_entire_binding(),
                    target.as_entire_binding(),
                    map_buffer.expect("the maps' buffer").as_entire_binding(),
                    lists.as_entire_binding(),
                )),
            )
        },
    );
    let maps = match maps.as_deref() {
        Some(maps) => shadow_map_casts(
            maps,
            map_buffer,
            &lights,
            &lit,
            &pools,
            &mut map_keys,
            &device,
            |casters, pool, list| {
                let casters = storage_init(&device, "particle_clouds_map_casters", casters);
                let own = &pools.0[&pool].own_depth;
                bind(
                    &pipelines.cast,
                    &BindGroupEntries::sequential((
                        // Unread: a map starts from nothing.
                        own.as_entire_binding(),
                        map_buffer.expect("the maps' buffer").as_entire_binding(),
                        casters.as_entire_binding(),
                        own.as_entire_binding(),
                        list.binding(),
                    )),
                )
            },
        ),
        None => ShadowMapCasts::default(),
    };
    let voxelize = voxelize_rounds(
        &device,
        &mut scratch,
        &pools,
        voxelizing,
        device.limits().max_storage_buffer_binding_size,
        |entries| bind(&pipelines.voxelize[0], entries),
    );
    let per_order = dispatch.is_some_and(|d| *d == SweepDispatch::PerOrder);
    pair_volumes.provide(per_order, &work, &pools, &device);
    let batches = work
        .into_iter()
        .map(|(id, w)| {
            let volumes = pair_volumes.0.get(&id);
            pool_batches((id, w, volumes), &pools, &device, &bind, &pipelines)
        })
        .collect();
    commands.insert_resource(IlluminationBatches {
        voxelize,
        pools: batches,
        maps,
        sky,
    });
}

/// The bind groups and work lists of pool `id`'s batched passes, from its clouds' `work`; its
/// sweeps dispatch once per order where it has `pair_volumes`.
fn pool_batches(
    (id, w, pair_volumes): (PoolId, PoolWork, Option<&Buffer>),
    pools: &VolumePools,
    device: &RenderDevice,
    bind: &impl Fn(&ComputeStage, &[BindGroupEntry]) -> BindGroup,
    pipelines: &IlluminationPipelines,
) -> PoolBatches {
    let pool = &pools.0[&id];
    let shade = Batch::new(device, &w.shade, |work| {
        bind(
            &pipelines.shade,
            &BindGroupEntries::sequential((
                pool.slots.as_entire_binding(),
                pool.lights.as_entire_binding(),
                pool.densities.as_entire_binding(),
                pool.optical_depth.as_entire_binding(),
                pool.own_depth.as_entire_binding(),
                work.binding(),
            )),
        )
    });
    let mut casts: Vec<_> = w.cast.into_iter().collect();
    casts.sort_by_key(|(caster_pool, _)| *caster_pool);
    let cast = casts
        .into_iter()
        .filter_map(|(caster_pool, mut c)| {
            if c.casters.is_empty() {
                c.casters.push(Caster::default()); // a binding may not be empty
            }
            let casters = storage_init(device, "particle_clouds_casters", &c.casters);
            Batch::new(device, &c.targets, |work| {
                bind(
                    &pipelines.cast,
                    &BindGroupEntries::sequential((
                        pool.own_depth.as_entire_binding(),
                        pool.optical_depth.as_entire_binding(),
                        casters.as_entire_binding(),
                        pools.0[&caster_pool].own_depth.as_entire_binding(),
                        work.binding(),
                    )),
                )
            })
        })
        .collect();
    let moments = id.shape.moments;
    let gather = Batch::new(device, &w.gather, |work| {
        bind(
            pipelines.gather.stage(moments),
            &BindGroupEntries::sequential((
                pool.slots.as_entire_binding(),
                pool.lights.as_entire_binding(),
                pool.optical_depth.as_entire_binding(),
                pool.densities.as_entire_binding(),
                pool.source.as_entire_binding(),
                work.binding(),
            )),
        )
    });
    let ground = Batch::new(device, &w.ground, |work| {
        bind(
            &pipelines.ground,
            &BindGroupEntries::sequential((
                pool.slots.as_entire_binding(),
                pool.lights.as_entire_binding(),
                pool.optical_depth.as_entire_binding(),
                pool.ground.as_entire_binding(),
                work.binding(),
            )),
        )
    });
    let scatter = w
        .scatter
        .into_iter()
        .map(|((iterations, stencil, directions, warm, cycles), slots)| {
            let work = WorkList::new(device, &slots);
            let volumes = (pool, pair_volumes);
            let mut batch = scatter_batch(bind, pipelines, volumes, iterations, work);
            batch.sweep = (stencil == ScatterStencil::DiscreteOrdinates).then_some(directions);
            batch.warm = warm;
            batch.cycles = (cycles > 0)
                .then(|| CycleBatch::new(bind, pipelines, volumes, &batch.work, cycles));
            batch
        })
        .collect();
    let mut overlaps: Vec<_> = w.overlap.into_iter().collect();
    overlaps.sort_by_key(|(neighbour_pool, _)| *neighbour_pool);
    let overlap = overlaps
        .into_iter()
        .filter_map(|(neighbour_pool, o)| {
            let neighbours = storage_init(device, "particle_clouds_neighbours", &o.neighbours);
            Batch::new(device, &o.items, |work| {
                bind(
                    &pipelines.overlap,
                    &BindGroupEntries::sequential((
                        pool.slots.as_entire_binding(),
                        neighbours.as_entire_binding(),
                        pools.0[&neighbour_pool].densities.as_entire_binding(),
                        pool.foreign.as_entire_binding(),
                        work.binding(),
                    )),
                )
            })
        })
        .collect();
    PoolBatches {
        n: id.shape.n,
        m: id.shape.m,
        moments,
        shade,
        cast,
        gather,
        overlap,
        ground,
        scatter,
    }
}

/// Each pool's pair volumes for one dispatch per order ([`SweepDispatch::PerOrder`]): a share
/// of an order per direction pair, for its grids' series and its coarse grids' in turn (render
/// world resource).
#[derive(Resource, Default)]
pub struct SweepPairVolumes(HashMap<PoolId, Buffer>);

impl SweepPairVolumes {
    /// Every pool's pair volumes (the memory census).
    pub(crate) fn buffers(&self) -> impl Iterator<Item = &Buffer> {
        self.0.values()
    }

    /// With `per_order`, a buffer for every pool of `work` that sweeps, holding a share of its
    /// order volume per pair of the largest direction set it sweeps, made anew where the one it
    /// had is too small; none where that would not fit one storage binding (it then sweeps per
    /// pair). Without, none at all.
    fn provide(
        &mut self,
        per_order: bool,
        work: &HashMap<PoolId, PoolWork>,
        pools: &VolumePools,
        device: &RenderDevice,
    ) {
        self.0.retain(|id, _| per_order && pools.0.contains_key(id));
        let limits = device.limits();
        let max = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        for (id, w) in work.iter().filter(|_| per_order) {
            let sweeps = w
                .scatter
                .keys()
                .filter(|k| k.1 == ScatterStencil::DiscreteOrdinates);
            let Some(pairs) = sweeps.map(|k| k.2.pairs().len() as u64).max() else {
                continue;
            };
            let bytes = pairs * pools.0[id].source.size();
            if bytes > max {
                self.0.remove(id);
            } else if self.0.get(id).is_none_or(|b| b.size() < bytes) {
                let label = "particle_clouds_sweep_pair_volumes";
                self.0.insert(*id, storage(device, label, bytes));
            }
        }
    }
}
