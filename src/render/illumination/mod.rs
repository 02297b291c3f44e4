//! The illumination passes (the paper's Algorithm 1, lines 2–6): voxelize, shade per light,
//! gather and multiple scattering. Only the stages planned for this frame run
//! ([`plan`](crate::render::plan)). Every pass is batched: one dispatch covers every cloud of a volume
//! pool ([`pools`](crate::render::plan::pools)), its z workgroups walking a work list (voxelize first copies
//! the clouds' particles into one buffer, [`voxelize`](crate::render::illumination::voxelize)). Their bind groups and
//! work lists are made in `PrepareBindGroups`; the system in the `RenderGraph` schedule, once per
//! frame before any camera, only records.

pub mod cast;
pub mod pipelines;
pub mod scatter;
pub mod shadow_maps;
pub mod sky_map;
pub mod voxelize;

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_asset::RenderAssets,
        render_resource::{
            BindGroup, BindGroupEntries, BindGroupEntry, Buffer, ComputePipeline, PipelineCache,
        },
        renderer::{RenderAdapterInfo, RenderContext, RenderDevice},
        storage::GpuShaderBuffer,
    },
};

use crate::render::{
    core::gpu::Batch,
    core::gpu::{StagePass, WorkList, record_stage, storage, storage_init},
    core::workgroups::{dispatch_columns, dispatch_linear},
    extract::particles::GpuParticles,
    extract::{ExtractedCloud, ExtractedCloudLights},
    illumination::cast::add_light_cast,
    illumination::pipelines::{
        ComputeStage, IlluminationPipelines, PerOrderSweepPipelines, ReadyPipelines,
    },
    illumination::scatter::coarse_grid::CycleBatch,
    illumination::scatter::series::{OrderPairs, SeriesPasses, SeriesVolumes, scatter_group},
    illumination::shadow_maps::{LitCloud, ShadowMapCasts, ShadowMapKeys, shadow_map_casts},
    illumination::sky_map::{SkyMapFill, SkyMapKey, sky_map_fill},
    illumination::voxelize::{
        VoxelizeCloud, VoxelizeRound, VoxelizeScratch, prepare_round, record_round, voxelize_rounds,
    },
    plan::CloudIllumination,
    plan::casters::{CastWork, Caster, by_pool},
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
