//! The illumination passes (the paper's Algorithm 1, lines 2–6): voxelize, shade per light,
//! gather and multiple scattering. Only the stages planned for this frame run
//! ([`plan`](crate::render::plan)). Every pass is batched: one dispatch covers every cloud of a volume
//! pool ([`pools`](crate::render::plan::pools)), its z workgroups walking a work list (voxelize first copies
//! the clouds' particles into one buffer, [`voxelize`](crate::render::illumination::voxelize)). Their bind groups and
//! work lists are made in `PrepareBindGroups`; the system in the `RenderGraph` schedule, once per
//! frame before any camera, only records.

pub mod pipelines;
pub mod scatter;
pub mod shadow_maps;
pub mod sky_map;
pub mod voxelize;

use std::num::NonZeroU64;

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_asset::RenderAssets,
        render_resource::{
            BindGroup, BindGroupEntries, BindGroupEntry, Buffer, BufferBinding, ComputePipeline,
            PipelineCache,
        },
        renderer::{RenderAdapterInfo, RenderContext, RenderDevice},
        storage::GpuShaderBuffer,
    },
};

use crate::render::{
    core::gpu::{StagePass, WorkList, record_stage, storage, storage_init},
    core::workgroups::{dispatch_columns, dispatch_linear, dispatch_rows},
    extract::particles::GpuParticles,
    extract::{ExtractedCloud, ExtractedCloudLights},
    illumination::pipelines::{
        ComputeStage, IlluminationPipelines, PerOrderSweepPipelines, ReadyPipelines,
        SWEEP_DIRECTIONS_BINDING, sweep_direction_offset, sweep_lines,
    },
    illumination::scatter::coarse_grid::CycleBatch,
    illumination::shadow_maps::{LitCloud, ShadowMapCasts, ShadowMapKeys, shadow_map_casts},
    illumination::sky_map::{SkyMapFill, SkyMapKey, sky_map_fill},
    illumination::voxelize::{
        VoxelizeCloud, VoxelizeRound, VoxelizeScratch, prepare_round, record_round, voxelize_rounds,
    },
    plan::CloudIllumination,
    plan::casters::{CastStart, CastTarget, CastWork, Caster, CasterVolume, add_cast, by_pool},
    plan::overlap::{Neighbour, OverlapItem},
    plan::pools::{PoolId, VolumePool, VolumePools},
    plan::volumes::CloudVolumes,
};
use crate::{
    particle::DeltaM,
    settings::{ScatterStencil, ShadingMethod, SweepDirections, SweepDispatch, SweepMarch},
    shadow_maps::{CloudShadowMaps, SKY_MAP_DIRECTIONS},
    stats::{CloudPass, CloudPassCounters},
};

/// One batched pass over a pool: its bind group and work list.
pub(crate) struct Batch {
    pub(crate) group: BindGroup,
    pub(crate) work: WorkList,
}

impl Batch {
    /// The batch of `items`, with the bind group `bind` makes for their work list; `None`
    /// without items.
    pub(crate) fn new<T: bytemuck::Pod>(
        device: &RenderDevice,
        items: &[T],
        bind: impl FnOnce(&WorkList) -> BindGroup,
    ) -> Option<Self> {
        if items.is_empty() {
            return None;
        }
        let work = WorkList::new(device, items);
        Some(Self {
            group: bind(&work),
            work,
        })
    }
}

/// The scattering of a pool's clouds that share an iteration count, a stencil (with its sweep
/// directions) and whether they restart warm.
struct ScatterBatch {
    iterations: u32,
    /// The discrete-ordinates sweep's directions, or `None` for the paper's stencil.
    sweep: Option<SweepDirections>,
    /// A warm restart from the solution `multiple` holds (docs/illumination.md §4).
    warm: bool,
    /// The iterations' three order pairs: `S_0 → a`, `a → b`, `b → a`.
    orders: OrderPairs,
    /// `S_0 → b`, a warm restart's start.
    restart: BindGroup,
    /// The closure, reading the last two orders.
    closure: BindGroup,
    work: WorkList,
    /// The coarse-grid cycles after the series, if any.
    cycles: Option<CycleBatch>,
}

/// The batched passes of one volume pool this frame.
struct PoolBatches {
    /// Voxels per side of the scattering grid, and of the fine grid and light volumes.
    n: u32,
    m: u32,
    /// Its scattering volumes hold angular moments: the `MOMENTS` variants of the stages run.
    moments: bool,
    shade: Option<Batch>,
    /// Other clouds' shadows, one batch per pool their casters lie in (first casts first).
    cast: Vec<Batch>,
    gather: Option<Batch>,
    /// Other clouds' media in the grids of this frame's scattering, one batch per pool the
    /// neighbours lie in (first first).
    overlap: Vec<Batch>,
    /// The ground's radiance under the clouds of this frame's sweeps that a ground lights.
    ground: Option<Batch>,
    scatter: Vec<ScatterBatch>,
}

/// This frame's batched passes, per pool, and the filling of the cloud shadow maps (render world
/// resource, made in `PrepareBindGroups`).
#[derive(Resource, Default)]
pub struct IlluminationBatches {
    /// The clouds whose density is rebuilt, in rounds whose particles fit one binding.
    voxelize: Vec<VoxelizeRound>,
    pools: Vec<PoolBatches>,
    maps: ShadowMapCasts,
    sky: SkyMapFill,
}

/// What the shadow maps' batches are made from: the maps, the lights, the storage buffers (the
/// maps' own) and the keys of what the maps (the lights' and the sky's) hold.
type ShadowMapInputs<'w> = (
    Option<Res<'w, CloudShadowMaps>>,
    Res<'w, ExtractedCloudLights>,
    Res<'w, RenderAssets<GpuShaderBuffer>>,
    (ResMut<'w, ShadowMapKeys>, ResMut<'w, SkyMapKey>),
);

/// The volumes a scattering series reads and writes: a pool's own, or its coarse grids'
/// ([`CoarseGrids`](crate::render::plan::pools::CoarseGrids)), laid out alike.
pub(crate) struct SeriesVolumes<'a> {
    pub(crate) slots: &'a Buffer,
    pub(crate) densities: &'a Buffer,
    /// `S_0`, the series' start.
    pub(crate) source: &'a Buffer,
    /// The two order volumes, alternating.
    pub(crate) orders: &'a [Buffer; 2],
    pub(crate) multiple: &'a Buffer,
    pub(crate) order_ratios: &'a Buffer,
    /// Other clouds' media, where each slot's `foreign` points.
    pub(crate) foreign: &'a Buffer,
    /// Each direction pair's share of an order, for one dispatch per order
    /// ([`SweepDispatch::PerOrder`]), where it is asked for and fits.
    pub(crate) pair_volumes: Option<&'a Buffer>,
}

/// The bind groups of one dispatch per order for an order pair: the sweep, writing every pair's
/// share into the pair volumes, and their sum, reading those into the next order.
pub(crate) struct PerOrderGroups {
    sweep: BindGroup,
    sum: BindGroup,
}

/// A series' three order pairs (`S_0 → a`, `a → b`, `b → a`) as the sweep binds them.
pub(crate) struct OrderPairs {
    /// For one dispatch per direction pair (and the other stencils and passes on an order pair).
    per_pair: [BindGroup; 3],
    /// For one dispatch per order, where the pool has pair volumes.
    per_order: Option<[PerOrderGroups; 3]>,
}

impl OrderPairs {
    /// Order pair `i` ([`scatter_group`]).
    pub(crate) fn pair(&self, i: usize) -> OrderPair<'_> {
        OrderPair {
            per_pair: &self.per_pair[i],
            per_order: self.per_order.as_ref().map(|g| &g[i]),
        }
    }
}

/// One order pair's bind groups ([`OrderPairs::pair`]).
#[derive(Clone, Copy)]
pub(crate) struct OrderPair<'a> {
    per_pair: &'a BindGroup,
    per_order: Option<&'a PerOrderGroups>,
}

impl<'a> SeriesVolumes<'a> {
    fn of_pool(pool: &'a VolumePool) -> Self {
        Self {
            slots: &pool.slots,
            densities: &pool.densities,
            source: &pool.source,
            orders: &pool.orders,
            multiple: &pool.multiple,
            order_ratios: &pool.order_ratios,
            foreign: &pool.foreign,
            pair_volumes: None,
        }
    }

    /// `S_0` for `k = 0`, else the order written by iteration `k - 1`.
    fn order(&self, k: u32) -> &'a Buffer {
        if k == 0 {
            self.source
        } else {
            &self.orders[(k as usize - 1) % 2]
        }
    }

    /// The sweep's bind group reading `from` and writing `to`, for the slots of `work` in
    /// `pool` (whose ground maps the sweep reads).
    fn order_pair(
        &self,
        bind: &impl Fn(&ComputeStage, &[BindGroupEntry]) -> BindGroup,
        pipelines: &IlluminationPipelines,
        pool: &VolumePool,
        (from, to): (&Buffer, &Buffer),
        work: &WorkList,
    ) -> BindGroup {
        bind(
            pipelines.sweep[0].stage(pool.shape().moments),
            &BindGroupEntries::sequential((
                self.slots.as_entire_binding(),
                BufferBinding {
                    buffer: &pipelines.sweep_directions,
                    offset: 0,
                    size: NonZeroU64::new(SWEEP_DIRECTIONS_BINDING),
                },
                self.densities.as_entire_binding(),
                from.as_entire_binding(),
                to.as_entire_binding(),
                self.multiple.as_entire_binding(),
                work.binding(),
                self.foreign.as_entire_binding(),
                pool.ground.as_entire_binding(),
            )),
        )
    }

    /// The order pairs of [`scatter_group`]'s iterations (`S_0 → a`, `a → b`, `b → a`), and
    /// where the pair volumes exist, their groups for one dispatch per order: the sweep writes
    /// the pair volumes (bound as its `s_out`), the sum reads them (as its `s_in`).
    pub(crate) fn iteration_groups(
        &self,
        bind: &impl Fn(&ComputeStage, &[BindGroupEntry]) -> BindGroup,
        pipelines: &IlluminationPipelines,
        pool: &VolumePool,
        work: &WorkList,
    ) -> OrderPairs {
        let pairs = [0, 1, 2].map(|k| (self.order(k), self.order(k + 1)));
        let group = |pair| self.order_pair(bind, pipelines, pool, pair, work);
        OrderPairs {
            per_pair: pairs.map(group),
            per_order: self.pair_volumes.map(|volumes| {
                pairs.map(|(from, to)| PerOrderGroups {
                    sweep: group((from, volumes)),
                    sum: group((volumes, to)),
                })
            }),
        }
    }

    /// The closure's bind group after `iterations` orders (it reads the last two).
    pub(crate) fn closure(
        &self,
        bind: &impl Fn(&ComputeStage, &[BindGroupEntry]) -> BindGroup,
        pipelines: &IlluminationPipelines,
        iterations: u32,
        work: &WorkList,
    ) -> BindGroup {
        bind(
            &pipelines.order_ratio,
            &BindGroupEntries::sequential((
                self.slots.as_entire_binding(),
                self.densities.as_entire_binding(),
                self.order(iterations).as_entire_binding(),
                self.order(iterations - 1).as_entire_binding(),
                self.multiple.as_entire_binding(),
                self.order_ratios.as_entire_binding(),
                work.binding(),
            )),
        )
    }
}

/// Which of a series' iteration groups ([`ScatterBatch::groups`]) iteration `k` reads and writes
/// with.
pub(crate) fn scatter_group(k: u32) -> usize {
    match k {
        0 => 0,
        k if k % 2 == 1 => 1,
        _ => 2,
    }
}

/// What each pool's clouds run this frame: (slot, light) to shade, light volumes to cast on per
/// pool their casters lie in, slots to gather, and slots to scatter per (iterations, stencil,
/// warm restart, coarse-grid cycles).
#[derive(Default)]
struct PoolWork {
    shade: Vec<[u32; 2]>,
    cast: HashMap<PoolId, CastWork>,
    overlap: HashMap<PoolId, OverlapWork>,
    gather: Vec<u32>,
    /// The clouds a ground lights whose scattering runs (their ground maps are filled first).
    ground: Vec<u32>,
    scatter: HashMap<(u32, ScatterStencil, SweepDirections, bool, u32), Vec<u32>>,
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
        |entries| bind(&pipelines.voxelize, entries),
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

/// Adds the cast of light slot `light` of `receiver` (its cloud and volumes) by `casters` (render
/// entities, found in `placed`) to `work` ([`add_cast`]).
fn add_light_cast(
    work: &mut HashMap<PoolId, CastWork>,
    (receiver, volumes): (&ExtractedCloud, &CloudVolumes),
    light: usize,
    casters: &[Entity],
    placed: &HashMap<Entity, (&ExtractedCloud, &CloudVolumes)>,
    pools: &VolumePools,
) {
    let Some(params) = volumes.lights.get(light) else {
        return;
    };
    let own = pools.pool(&volumes.slot).optical_depth(volumes.slot.index);
    let first = (own.offset / 4) as u32 + params.offset;
    let n = volumes.params.light_n;
    let target = CastTarget::light_volume(params, volumes.params.grid_centre, n, first);
    let casters = casters
        .iter()
        .filter_map(|e| placed.get(e))
        .filter_map(|&(cloud, v)| {
            let caster = light_caster(cloud, v, light, pools)?;
            Some((v.slot.pool, caster.on(&receiver.world_from_local)))
        });
    add_cast(work, target, CastStart::Own, casters, volumes.slot.pool);
}

/// Light volume `light` of a cloud (its own optical depth), as the clouds it shadows see it.
pub(crate) fn light_caster(
    cloud: &ExtractedCloud,
    volumes: &CloudVolumes,
    light: usize,
    pools: &VolumePools,
) -> Option<CasterVolume> {
    let params = volumes.lights.get(light)?;
    let first = pools
        .pool(&volumes.slot)
        .optical_depth(volumes.slot.index)
        .offset
        / 4;
    Some(CasterVolume::new(
        params,
        volumes.params.grid_centre,
        &cloud.world_from_local,
        first as u32 + params.offset,
        volumes.params.light_n,
    ))
}

/// The overlap work of one receivers' pool whose neighbours lie in one pool.
#[derive(Default)]
struct OverlapWork {
    items: Vec<OverlapItem>,
    neighbours: Vec<Neighbour>,
}

/// Adds the overlap of `receiver` (its cloud and volumes) by `neighbours` (render entities,
/// found in `placed`) to `work`, one item per pool the neighbours lie in: the first (in pool
/// order) writes `foreign`, the others add to it.
fn add_overlaps(
    work: &mut HashMap<PoolId, OverlapWork>,
    (receiver, volumes): (&ExtractedCloud, &CloudVolumes),
    neighbours: &[Entity],
    placed: &HashMap<Entity, (&ExtractedCloud, &CloudVolumes)>,
    pools: &VolumePools,
) {
    let placed_neighbours = neighbours
        .iter()
        .filter_map(|e| placed.get(e))
        .map(|&(cloud, v)| {
            let first = pools.pool(&v.slot).density(v.slot.index).offset / 4;
            // Its medium as the sweep takes it: δ-M transformed (docs/illumination.md §4).
            let delta = DeltaM::new(cloud.albedo as f64, cloud.anisotropy as f64);
            let neighbour = Neighbour::new(
                v.params.grid_origin,
                v.params.h,
                v.params.n,
                first as u32,
                &cloud.world_from_local,
                &receiver.world_from_local,
                delta.depth_scale as f32 * cloud.extinction / receiver.extinction,
                delta.albedo as f32,
            );
            (v.slot.pool, neighbour)
        });
    for (i, (pool, neighbours)) in by_pool(placed_neighbours).into_iter().enumerate() {
        let w = work.entry(pool).or_default();
        w.items.push(OverlapItem {
            slot: volumes.slot.index,
            first_neighbour: w.neighbours.len() as u32,
            neighbours: neighbours.len() as u32,
            accumulate: (i > 0) as u32,
        });
        w.neighbours.extend(neighbours);
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

/// The bind groups of `iterations` of scattering for the slots of `work`, in `pool` (the
/// discrete-ordinates stencil along the 26 directions, full series: set `sweep` and `warm` for
/// the others).
fn scatter_batch(
    bind: &impl Fn(&ComputeStage, &[BindGroupEntry]) -> BindGroup,
    pipelines: &IlluminationPipelines,
    (pool, pair_volumes): (&VolumePool, Option<&Buffer>),
    iterations: u32,
    work: WorkList,
) -> ScatterBatch {
    let volumes = SeriesVolumes {
        pair_volumes,
        ..SeriesVolumes::of_pool(pool)
    };
    let orders = volumes.iteration_groups(bind, pipelines, pool, &work);
    let restart = (&pool.source, &pool.orders[1]);
    let restart = volumes.order_pair(bind, pipelines, pool, restart, &work);
    let closure = volumes.closure(bind, pipelines, iterations, &work);
    ScatterBatch {
        iterations,
        sweep: Some(SweepDirections::Lattice26),
        warm: false,
        orders,
        restart,
        closure,
        work,
        cycles: None,
    }
}

impl IlluminationBatches {
    /// Whether anything shades or casts this frame.
    fn shades(&self) -> bool {
        let casting = |b: &PoolBatches| b.shade.is_some() || !b.cast.is_empty();
        self.pools.iter().any(casting) || !self.maps.batches.is_empty()
    }

    /// Whether anything gathers or marches the sky map this frame.
    fn gathers(&self) -> bool {
        self.pools.iter().any(|b| b.gather.is_some()) || !self.sky.marches.is_empty()
    }

    /// Whether any cloud scatters this frame.
    fn scatters(&self) -> bool {
        self.pools.iter().any(|b| !b.scatter.is_empty())
    }

    /// Shade (§2): one column per invocation, marching slice by slice away from the light (or,
    /// with `ShadingMethod::BruteForce`, one voxel per invocation marching all the way to the
    /// light); every (cloud, light) of a pool in one dispatch. Then, once every cloud's own
    /// optical depth is shaded, other clouds' shadows and the shadow maps (§10), one
    /// invocation per column along the light (`cast.wgsl`): their dispatches count as shade's,
    /// their runs do not. Returns the runs: the lights shaded.
    fn record_shade(
        &self,
        pass: &mut StagePass,
        ready: &ReadyPipelines,
        shade: &ComputePipeline,
        brute_force: bool,
    ) -> u32 {
        pass.set_pipeline(shade);
        let mut runs = 0;
        for b in &self.pools {
            let Some(batch) = &b.shade else { continue };
            for (offset, items) in batch.work.chunks() {
                pass.set_bind_group(0, &batch.group, &[offset]);
                if brute_force {
                    dispatch_linear(pass, b.m.pow(3), items);
                } else {
                    dispatch_columns(pass, b.m, items);
                }
            }
            runs += batch.work.items;
        }
        pass.set_pipeline(ready.cast);
        let pools = self.pools.iter();
        let light_volumes = pools.flat_map(|b| b.cast.iter().map(move |c| (c, b.m.pow(2))));
        let map_texels = self.maps.batches.iter().map(|(c, columns)| (c, *columns));
        for (batch, columns) in light_volumes.chain(map_texels) {
            for (offset, items) in batch.work.chunks() {
                pass.set_bind_group(0, &batch.group, &[offset]);
                dispatch_linear(pass, columns, items);
            }
        }
        runs
    }

    /// Gather (§1, §3): the scattering grid's density, and every light's single scattering into
    /// its source `S_0`; every cloud of a pool in one dispatch. Then the sky map (§10), marched
    /// through the scattering grids' densities: every pool's clouds along each texel's
    /// directions, then each texel's occlusion. Its dispatches count as gather's, not its runs.
    fn record_gather(&self, pass: &mut StagePass, ready: &ReadyPipelines) -> u32 {
        let mut runs = 0;
        for b in &self.pools {
            let Some(batch) = &b.gather else { continue };
            pass.set_pipeline(ready.gather[b.moments as usize]);
            for (offset, items) in batch.work.chunks() {
                pass.set_bind_group(0, &batch.group, &[offset]);
                dispatch_linear(pass, b.n.pow(3), items);
            }
            runs += batch.work.items;
        }
        let sky = &self.sky;
        if let Some(first) = sky.marches.first() {
            pass.set_pipeline(ready.march_sky);
            for group in &sky.marches {
                pass.set_bind_group(0, group, &[]);
                dispatch_linear(pass, sky.texels * SKY_MAP_DIRECTIONS, 1);
            }
            pass.set_pipeline(ready.resolve_sky);
            pass.set_bind_group(0, first, &[]);
            dispatch_linear(pass, sky.texels, 1);
        }
        runs
    }

    /// Multiple scattering (§4): other clouds' media in the grids to scatter in (once every
    /// density is gathered), the ground's radiance under the clouds it lights (once their light
    /// volumes hold every shadow), then each batch's iterations and the series' closure.
    /// Returns the runs: iterations times clouds.
    fn record_scatter(&self, pass: &mut StagePass, ready: &ReadyPipelines) -> u32 {
        pass.set_pipeline(ready.overlap);
        for b in &self.pools {
            for batch in &b.overlap {
                for (offset, items) in batch.work.chunks() {
                    pass.set_bind_group(0, &batch.group, &[offset]);
                    dispatch_linear(pass, b.n.pow(3), items);
                }
            }
        }
        pass.set_pipeline(ready.ground);
        let side = crate::ground::GROUND_MAP_SIDE;
        for batch in self.pools.iter().filter_map(|b| b.ground.as_ref()) {
            for (offset, items) in batch.work.chunks() {
                pass.set_bind_group(0, &batch.group, &[offset]);
                dispatch_linear(pass, side * side, items);
            }
        }
        let mut runs = 0;
        for b in &self.pools {
            for batch in &b.scatter {
                scatter_batch_passes(pass, ready, batch, b.n, b.moments);
                runs += batch.iterations * batch.work.items;
            }
        }
        runs
    }
}

/// What the passes are recorded with: the shading method, the sweep's march and dispatch (and
/// the pipelines of one dispatch per order, once queued), and the adapter they suit.
type IlluminationChoices<'w> = (
    Option<Res<'w, ShadingMethod>>,
    Option<Res<'w, SweepMarch>>,
    Option<Res<'w, SweepDispatch>>,
    Option<Res<'w, PerOrderSweepPipelines>>,
    Res<'w, RenderAdapterInfo>,
);

/// Records every planned illumination stage of every cloud.
#[allow(clippy::too_many_arguments)]
pub(crate) fn illuminate_clouds(
    mut ctx: RenderContext,
    mut clouds: Query<(&ExtractedCloud, &CloudVolumes, &mut CloudIllumination)>,
    batches: Option<Res<IlluminationBatches>>,
    pools: Res<VolumePools>,
    particles: Res<RenderAssets<GpuParticles>>,
    pipelines: Option<Res<IlluminationPipelines>>,
    pipeline_cache: Res<PipelineCache>,
    counters: Res<CloudPassCounters>,
    (shading, march, dispatch, per_order, adapter): IlluminationChoices,
    (mut map_keys, mut sky_key): (ResMut<ShadowMapKeys>, ResMut<SkyMapKey>),
) {
    let Some(pipelines) = pipelines else { return };
    let maps_pending = batches.as_ref().is_some_and(|b| {
        !b.maps.clears.is_empty() || !b.maps.batches.is_empty() || b.sky.is_pending()
    });
    if clouds.iter().all(|(_, _, s)| s.plan.is_empty()) && !maps_pending {
        return;
    }
    let brute_force = shading.is_some_and(|s| *s == ShadingMethod::BruteForce);
    let shade_stage = if brute_force {
        &pipelines.shade_brute_force
    } else {
        &pipelines.shade
    };
    let cpu = adapter.device_type == wgpu::DeviceType::Cpu;
    let read_ahead = march.map_or(SweepMarch::default(), |m| *m).reads_ahead(cpu);
    // One dispatch per order waits for its pipelines as for the others.
    let wants_per_order = dispatch.is_some_and(|d| *d == SweepDispatch::PerOrder);
    let per_order = per_order.as_deref().filter(|_| wants_per_order);
    let ready = (!wants_per_order || per_order.is_some())
        .then(|| pipelines.ready(&pipeline_cache, read_ahead, per_order))
        .flatten();
    let (Some(ready), Some(shade), Some(batches)) =
        (ready, shade_stage.get(&pipeline_cache), batches)
    else {
        // Not compiled yet: forget the plan so that the next frame does all of it.
        clouds.iter_mut().for_each(|(_, _, mut s)| s.invalidate());
        *map_keys = ShadowMapKeys::default();
        *sky_key = SkyMapKey::default();
        return;
    };
    let recorder = ctx.diagnostic_recorder();
    let mut clouds: Vec<_> = clouds
        .iter_mut()
        .filter(|(_, _, s)| !s.plan.is_empty())
        .filter(|(cloud, _, _)| particles.get(cloud.particles).is_some())
        .map(|(_, v, s)| (v, s))
        .collect();

    // Voxelize (docs/illumination.md §1): clear, copy the particles together, then every
    // particle deposits its mass on its density level, one row of its support per invocation:
    // the kernel's sums, then the deposit. Then the coarse levels are enlarged into the fine
    // grid, coarsest first.
    for round in &batches.voxelize {
        prepare_round(&mut ctx, round);
        let voxelize = [ready.kernel_sums, ready.voxelize, ready.upsample];
        record_stage(
            &mut ctx,
            recorder.as_deref(),
            &counters,
            CloudPass::Voxelize,
            |pass| record_round(pass, voxelize, round),
        );
    }

    // Shade (§2), then the casts of other clouds' shadows and the shadow maps.
    let (maps, sky) = (&batches.maps, &batches.sky);
    if let Some(buffer) = &maps.buffer {
        for &(offset, size) in maps.clears.iter().chain(&sky.clear) {
            ctx.command_encoder()
                .clear_buffer(buffer, offset, Some(size));
        }
    }
    if batches.shades() {
        record_stage(
            &mut ctx,
            recorder.as_deref(),
            &counters,
            CloudPass::Shade,
            |pass| batches.record_shade(pass, &ready, shade, brute_force),
        );
    }
    // Gather (§1, §3), then the sky map.
    if batches.gathers() {
        record_stage(
            &mut ctx,
            recorder.as_deref(),
            &counters,
            CloudPass::Gather,
            |pass| batches.record_gather(pass, &ready),
        );
    }
    // Multiple scattering (§4): a warm restart starts from what `multiple` holds; the full
    // series from zero.
    for (v, s) in &clouds {
        if (s.plan.scatter.is_some() && !s.plan.warm) || s.plan.unlit {
            let multiple = pools.pool(&v.slot).multiple(v.slot.index);
            ctx.command_encoder().clear_buffer(
                &multiple.buffer,
                multiple.offset,
                Some(multiple.size),
            );
        }
    }
    if batches.scatters() {
        record_stage(
            &mut ctx,
            recorder.as_deref(),
            &counters,
            CloudPass::Scatter,
            |pass| batches.record_scatter(pass, &ready),
        );
    }

    for (_, s) in &mut clouds {
        let scattered = s.plan.scatter.is_some() || s.plan.unlit;
        s.ready |= scattered;
        s.scattered = s.scattered.wrapping_add(scattered as u32);
        s.plan = default();
    }
}

/// Records a batch's scattering iterations (the discrete-ordinates `sweep`, else the paper's
/// stencil) on its clouds' `n³` grids, the closure (§4), then its coarse-grid cycles. A warm
/// restart's first iteration scatters `S_0` plus the solution held, and turns it into the
/// correction's first order.
fn scatter_batch_passes(
    pass: &mut StagePass,
    ready: &ReadyPipelines,
    batch: &ScatterBatch,
    n: u32,
    moments: bool,
) {
    let variant = moments as usize;
    let series = SeriesPasses {
        ready,
        sweep: batch.sweep,
        n,
        variant,
    };
    for (work, items) in batch.work.chunks() {
        let first = if batch.warm {
            series.restart_sweep(pass, (&batch.orders, &batch.restart), work, items);
            1
        } else {
            0
        };
        series.set_stencil(pass);
        for k in first..batch.iterations {
            let pair = batch.orders.pair(scatter_group(k));
            series.iterate(pass, pair, (work, items), k == 0);
            // Orders M - 2 and M - 3 lie where the closure reads M and M - 1 (the two order
            // volumes alternate): their sizes, for a two-mode closure of the full series.
            if !batch.warm && batch.iterations >= 4 && k + 3 == batch.iterations {
                series.order_sizes(pass, &batch.closure, work, items);
            }
        }
    }
    for (work, items) in batch.work.chunks() {
        series.close(pass, &batch.closure, work, items);
    }
    if let Some(cycles) = &batch.cycles {
        for (work, items) in batch.work.chunks() {
            cycles.record(
                pass,
                &series,
                (&batch.orders, &batch.restart),
                (work, items),
            );
        }
    }
}

/// Records the passes of a scattering series on a pool's `n³` grids (or on its coarse grids).
pub(crate) struct SeriesPasses<'a> {
    pub(crate) ready: &'a ReadyPipelines<'a>,
    /// The discrete-ordinates sweep's directions, else (`None`) the paper's stencil.
    pub(crate) sweep: Option<SweepDirections>,
    /// Voxels per side of the grids.
    pub(crate) n: u32,
    /// 1 for the pipelines with angular moments, else 0.
    pub(crate) variant: usize,
}

impl SeriesPasses<'_> {
    fn stencil(&self) -> &ComputePipeline {
        if self.sweep.is_some() {
            self.ready.sweep[self.variant]
        } else {
            self.ready.scatter_paper
        }
    }

    pub(crate) fn set_stencil(&self, pass: &mut StagePass) {
        pass.set_pipeline(self.stencil());
    }

    /// One iteration with the stencil set: with `accumulate`, its order goes into `multiple`;
    /// with `boundary`, the light entering the grid comes in.
    fn pass_once(
        &self,
        pass: &mut StagePass,
        group: OrderPair,
        (work, items): (u32, u32),
        accumulate: bool,
        boundary: bool,
    ) {
        let n = self.n;
        let Some(directions) = self.sweep else {
            // The paper's stencil reads only the pair's `accumulate`.
            let direction =
                sweep_direction_offset(SweepDirections::Lattice26, 0, accumulate, boundary);
            pass.set_bind_group(0, group.per_pair, &[direction, work]);
            dispatch_linear(pass, n.pow(3), items);
            return;
        };
        if let (Some(groups), Some(per_order)) = (group.per_order, self.ready.per_order) {
            // Every pair at once, each into its own volume; then their sum (and into `multiple`).
            let direction = sweep_direction_offset(directions, 0, accumulate, boundary);
            let lines = directions
                .pairs()
                .iter()
                .map(|d| sweep_lines(IVec3::from_array(d.o), n));
            let pairs = directions.pairs().len() as u32;
            pass.set_pipeline(per_order.sweep[self.variant]);
            pass.set_bind_group(0, &groups.sweep, &[direction, work]);
            dispatch_rows(pass, lines.max().unwrap_or(0), pairs, items);
            pass.set_pipeline(per_order.sum_pairs[self.variant]);
            pass.set_bind_group(0, &groups.sum, &[direction, work]);
            dispatch_linear(pass, n.pow(3), items);
            pass.set_pipeline(self.stencil());
            return;
        }
        let group = group.per_pair;
        // One dispatch per direction pair: the lines of one direction partition the grid.
        for (i, d) in directions.pairs().iter().enumerate() {
            let direction = sweep_direction_offset(directions, i, accumulate, boundary);
            pass.set_bind_group(0, group, &[direction, work]);
            dispatch_linear(pass, sweep_lines(IVec3::from_array(d.o), n), items);
        }
        // The order into `multiple` once, not in each direction's dispatch.
        if accumulate {
            pass.set_pipeline(self.ready.accumulate_order[self.variant]);
            dispatch_linear(pass, n.pow(3), items);
            pass.set_pipeline(self.stencil());
        }
    }

    /// An accumulating iteration of the series, the first (`boundary`) bringing the light
    /// entering the grid in (§4).
    pub(crate) fn iterate(
        &self,
        pass: &mut StagePass,
        group: OrderPair,
        work: (u32, u32),
        boundary: bool,
    ) {
        self.pass_once(pass, group, work, true, boundary);
    }

    /// `S <- K (S_0 + S) + b` on what `multiple` holds, the change `K (S_0 + S) + b - S` left in
    /// order a: a warm restart's first order, and a coarse-grid cycle's residual and smoothing
    /// sweeps. `S_0 + S` goes into b, is scattered into a without accumulating, then
    /// `multiple` takes a and a the change. Leaves the stencil set.
    /// `orders` are the series' order pairs, `restart` its `S_0 → b`.
    pub(crate) fn restart_sweep(
        &self,
        pass: &mut StagePass,
        (orders, restart): (&OrderPairs, &BindGroup),
        work: u32,
        items: u32,
    ) {
        let n3 = self.n.pow(3);
        pass.set_pipeline(self.ready.warm_start[self.variant]);
        pass.set_bind_group(0, restart, &[0, work]);
        dispatch_linear(pass, n3, items);
        self.set_stencil(pass);
        self.pass_once(pass, orders.pair(2), (work, items), false, true);
        pass.set_pipeline(self.ready.warm_correction[self.variant]);
        pass.set_bind_group(0, &orders.per_pair[2], &[0, work]);
        dispatch_linear(pass, n3, items);
        self.set_stencil(pass);
    }

    /// The sizes of orders `M - 3` and `M - 2` (the full series' two-mode closure), from the
    /// closure's bindings while they hold them; leaves the stencil set.
    pub(crate) fn order_sizes(
        &self,
        pass: &mut StagePass,
        closure: &BindGroup,
        work: u32,
        items: u32,
    ) {
        pass.set_bind_group(0, closure, &[work]);
        pass.set_pipeline(self.ready.order_sizes);
        pass.dispatch(1, 1, items);
        self.set_stencil(pass);
    }

    /// The closure: the tail's coefficients, then the tail added to `multiple`.
    pub(crate) fn close(&self, pass: &mut StagePass, closure: &BindGroup, work: u32, items: u32) {
        pass.set_bind_group(0, closure, &[work]);
        pass.set_pipeline(self.ready.order_ratio);
        pass.dispatch(1, 1, items);
        pass.set_pipeline(self.ready.extrapolate[self.variant]);
        dispatch_linear(pass, self.n.pow(3), items);
    }
}
