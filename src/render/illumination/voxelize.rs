//! Voxelize (the paper's Algorithm 1, line 2; docs/illumination.md §1): every particle deposits
//! its mass into its cloud's fine density grid, as a gather. The particles are binned into bricks
//! of voxels by their centres, and one workgroup per brick sums the particles within reach and
//! writes each voxel once: no float atomic, so the density is the same bit for bit on every run,
//! and particles piled on one spot cost what spread ones do (`voxelize.wgsl`).
//!
//! Each cloud's particles are a buffer of their own, so the particles of the clouds voxelized
//! this frame are first copied one after the other into a scratch buffer; then, like shade,
//! gather and scatter, one dispatch per pass covers every cloud of a volume pool, its z
//! workgroups walking a work list: the dispatch count does not grow with the clouds.

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_resource::{
            BindGroup, BindGroupEntries, BindGroupEntry, Buffer, BufferBinding, BufferDescriptor,
            BufferInitDescriptor, BufferUsages, ComputePipeline, ShaderType,
        },
        renderer::{RenderContext, RenderDevice},
    },
};

use crate::math::density_level_sizes;
use crate::render::{
    core::gpu::Batch,
    core::gpu::{DYNAMIC_UNIFORM_STRIDE, StagePass, WORK_CHUNK, WorkList},
    core::workgroups::{self, BRICK_THREADS, dispatch_columns, spread_groups},
    extract::particles::GpuParticles,
    plan::pools::{BufferRange, PoolId, VolumePools},
    plan::volumes::{CloudVolumes, DensityLevels},
};

/// Bytes of one particle on the GPU (`Particle` in `types.wgsl`).
const PARTICLE_BYTES: u64 = 32;
/// Words before a cloud's bricks in the bricks' buffer: each density level's reach, and the
/// number of its marked bricks (`HEADER_WORDS` in `voxelize.wgsl`).
const HEADER_WORDS: u64 = 9;
/// The x workgroups of the gather's indirect dispatch; `scan_bricks` sets y so that x·y covers
/// the marked bricks. Small, so that an item with fewer marked bricks than the round's most
/// launches few workgroups that find nothing to do.
const GATHER_ROW: u32 = 64;
/// Particles whose kernel sums one workgroup reduces (`SUMS_PER_GROUP` in `voxelize.wgsl`).
const SUMS_PER_GROUP: u32 = 8;

/// The entry points of `voxelize.wgsl`, in the order a round records them (all share one
/// layout): the binning (count, scan, scatter, sort), the kernels' sums, the gather, and the
/// coarse levels enlarged into the fine grid.
pub const VOXELIZE_PASSES: [&str; 7] = [
    "bin",
    "scan_bricks",
    "scatter",
    "sort_bricks",
    "kernel_sums",
    "gather",
    "upsample",
];

/// The scratch buffers of the voxelize rounds (render world resource): each round's particles,
/// one cloud after the other, their kernel sums and lists, and the clouds' bricks. Grown when a
/// frame needs more and kept for the next, so a cloud whose particles change every frame
/// allocates nothing; shrunk when a frame needs a quarter or less (see `scratch_capacity`).
#[derive(Resource, Default)]
pub struct VoxelizeScratch(Vec<ScratchBuffers>);

#[derive(Clone)]
struct ScratchBuffers {
    particles: Buffer,
    totals: Buffer,
    binned: Buffer,
    /// Particles they hold.
    capacity: u64,
    bricks: Buffer,
    /// Words `bricks` holds.
    brick_capacity: u64,
}

impl VoxelizeScratch {
    /// Every round's buffers (the memory census).
    pub(crate) fn buffers(&self) -> impl Iterator<Item = &Buffer> {
        self.0
            .iter()
            .flat_map(|s| [&s.particles, &s.totals, &s.binned, &s.bricks])
    }

    /// Frees every round's buffers: no cloud is left to voxelize.
    pub(crate) fn release(&mut self) {
        self.0.clear();
    }

    /// Round `round`'s buffers (rounds are reserved in order), holding at least `particles` and
    /// `words` of bricks, and at most what one storage binding of `max_binding` bytes does. Only
    /// the buffers whose capacity changes are made anew.
    fn reserve(
        &mut self,
        device: &RenderDevice,
        round: usize,
        (particles, words): (u64, u64),
        max_binding: u64,
    ) -> ScratchBuffers {
        let buffer = |label, bytes: u64| {
            device.create_buffer(&BufferDescriptor {
                label: Some(label),
                size: bytes.max(16),
                usage: BufferUsages::STORAGE | BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let per_particle = |capacity: u64| {
            (
                buffer(
                    "particle_clouds_voxelize_particles",
                    capacity * PARTICLE_BYTES,
                ),
                buffer("particle_clouds_voxelize_totals", capacity * 4),
                buffer("particle_clouds_voxelize_binned", capacity * 4),
            )
        };
        let bricks = |capacity: u64| buffer("particle_clouds_voxelize_bricks", capacity * 4);
        let current = self.0.get(round);
        let grown_particles = scratch_capacity(
            current.map(|s| s.capacity),
            particles,
            max_binding / PARTICLE_BYTES,
        );
        let grown_words =
            scratch_capacity(current.map(|s| s.brick_capacity), words, max_binding / 4);
        let buffers = match current {
            Some(s) if grown_particles.is_none() && grown_words.is_none() => return s.clone(),
            Some(s) => {
                let mut s = s.clone();
                if let Some(capacity) = grown_particles {
                    (s.particles, s.totals, s.binned) = per_particle(capacity);
                    s.capacity = capacity;
                }
                if let Some(capacity) = grown_words {
                    s.bricks = bricks(capacity);
                    s.brick_capacity = capacity;
                }
                s
            }
            None => {
                let capacity = grown_particles.unwrap_or(1);
                let brick_capacity = grown_words.unwrap_or(1);
                let (particles, totals, binned) = per_particle(capacity);
                ScratchBuffers {
                    particles,
                    totals,
                    binned,
                    capacity,
                    bricks: bricks(brick_capacity),
                    brick_capacity,
                }
            }
        };
        if round < self.0.len() {
            self.0[round] = buffers.clone();
        } else {
            self.0.push(buffers.clone());
        }
        buffers
    }
}

/// The particles a round's scratch should be reallocated to hold, or `None` to keep its
/// `current` capacity: grown to the next power of two when `particles` do not fit (so particles
/// that change every frame allocate only now and then), shrunk the same way once they need a
/// quarter of it or less (so one big scene does not hold its memory for ever, and counts that
/// halve and double again keep their buffer); never above `max_particles`, never below what
/// `particles` need.
fn scratch_capacity(current: Option<u64>, particles: u64, max_particles: u64) -> Option<u64> {
    let wanted = particles
        .max(1)
        .next_power_of_two()
        .min(max_particles)
        .max(particles);
    match current {
        Some(capacity) if capacity >= particles && particles.max(1) > capacity / 4 => None,
        _ => Some(wanted),
    }
}

/// A cloud whose density is rebuilt this frame.
pub(crate) struct VoxelizeCloud {
    slot: u32,
    particles: Buffer,
    count: u32,
    levels_in_use: u32,
}

impl VoxelizeCloud {
    pub(crate) fn new(gpu: &GpuParticles, volumes: &CloudVolumes) -> Self {
        Self {
            slot: volumes.slot.index,
            particles: gpu.buffer.clone(),
            count: gpu.count,
            levels_in_use: volumes.levels_in_use as u32,
        }
    }
}

/// Words a cloud of a pool whose fine grid has `m` voxels per side takes in the bricks' buffer:
/// the header, then per brick its list's place, whether a particle reaches it, and the list of
/// those it reaches.
fn brick_words(m: u32) -> u64 {
    HEADER_WORDS + 3 * DensityLevels::bricks(m)
}

/// One pool's clouds in a round.
struct PoolVoxelize {
    /// `(slot, first particle, first brick word, particles)` per cloud, those with the most density
    /// levels first.
    batch: Batch,
    /// The batch's bind group for the gather, whose `gather_groups` is a stand-in: the gather
    /// reads the real one as its indirect dispatch.
    gather_group: BindGroup,
    /// The clouds' density levels, cleared before the gather.
    clears: Vec<BufferRange>,
    /// The most particles of a cloud.
    particles: u32,
    /// Bricks of a cloud.
    bricks: u32,
    /// Per coarse level to enlarge, coarsest first: the level, voxels per side of the level
    /// below, and the clouds (the first of the work list) that use it.
    upsample: Vec<(u32, u32, u32)>,
}

/// The clouds voxelized together: their particles in one scratch buffer.
pub(crate) struct VoxelizeRound {
    scratch: ScratchBuffers,
    /// Words of the bricks' buffer in use (cleared before the passes).
    words: u64,
    /// Each cloud's particles and their first element in the scratch.
    copies: Vec<(Buffer, u64, u32)>,
    pools: Vec<PoolVoxelize>,
    /// The gather's indirect dispatches, one per pool and chunk of its work list, in the order
    /// they are recorded.
    gather_groups: Buffer,
}

/// Splits the clouds to voxelize into rounds whose particles and bricks fit in one storage
/// binding of `max_binding` bytes each (one round unless they hold millions), and makes each
/// pool's batch.
pub(crate) fn voxelize_rounds(
    device: &RenderDevice,
    scratch: &mut VoxelizeScratch,
    pools: &VolumePools,
    clouds: HashMap<PoolId, Vec<VoxelizeCloud>>,
    max_binding: u64,
    bind: impl Fn(&[BindGroupEntry]) -> BindGroup,
) -> Vec<VoxelizeRound> {
    let limits = (
        (max_binding / PARTICLE_BYTES).max(1),
        (max_binding / 4).max(1),
    );
    let mut by_pool: Vec<_> = clouds.into_iter().collect();
    by_pool.sort_by_key(|(id, _)| *id);
    let in_order: Vec<_> = by_pool
        .into_iter()
        .flat_map(|(id, clouds)| clouds.into_iter().map(move |c| (id, c)))
        .collect();
    let sizes: Vec<(u64, u64)> = in_order
        .iter()
        .map(|(id, c)| (c.count as u64, brick_words(id.shape.m)))
        .collect();
    let mut rounds: Vec<Vec<(PoolId, Vec<VoxelizeCloud>)>> = Vec::new();
    for ((id, cloud), round) in in_order.into_iter().zip(round_of_each(&sizes, limits)) {
        if round == rounds.len() {
            rounds.push(Vec::new());
        }
        match rounds[round].last_mut() {
            Some((last, list)) if *last == id => list.push(cloud),
            _ => rounds[round].push((id, vec![cloud])),
        }
    }
    rounds
        .into_iter()
        .enumerate()
        .map(|(i, round)| make_round(device, scratch, pools, (i, max_binding), round, &bind))
        .collect()
}

/// The round of each cloud of `(particles, brick words)` in `sizes`, in order: a round holds
/// what one storage binding of `limits` particles and words does, and at least one cloud.
fn round_of_each(sizes: &[(u64, u64)], limits: (u64, u64)) -> Vec<usize> {
    let mut round = 0;
    let mut in_round = (0u64, 0u64);
    sizes
        .iter()
        .map(|&(count, words)| {
            let count = count.max(1);
            let fits = in_round.0.saturating_add(count) <= limits.0
                && in_round.1.saturating_add(words) <= limits.1;
            if in_round.0 > 0 && !fits {
                round += 1;
                in_round = (0, 0);
            }
            in_round = (
                in_round.0.saturating_add(count),
                in_round.1.saturating_add(words),
            );
            round
        })
        .collect()
}

fn make_round(
    device: &RenderDevice,
    scratch: &mut VoxelizeScratch,
    pools: &VolumePools,
    (index, max_binding): (usize, u64),
    round: Vec<(PoolId, Vec<VoxelizeCloud>)>,
    bind: &impl Fn(&[BindGroupEntry]) -> BindGroup,
) -> VoxelizeRound {
    let particles: u64 = round
        .iter()
        .flat_map(|(_, c)| c)
        .map(|c| c.count as u64)
        .sum();
    let words: u64 = round
        .iter()
        .map(|(id, c)| c.len() as u64 * brick_words(id.shape.m))
        .sum();
    let buffers = scratch.reserve(device, index, (particles, words), max_binding);
    let gather_groups = device.create_buffer_with_data(&BufferInitDescriptor {
        label: Some("particle_clouds_voxelize_gather_groups"),
        contents: bytemuck::cast_slice(&gather_dispatches(round.iter().map(|(_, c)| c.len()))),
        usage: BufferUsages::STORAGE | BufferUsages::INDIRECT,
    });
    let stand_in = device.create_buffer(&BufferDescriptor {
        label: Some("particle_clouds_voxelize_gather_groups_stand_in"),
        size: 16,
        usage: BufferUsages::STORAGE,
        mapped_at_creation: false,
    });
    let mut copies = Vec::new();
    let (mut first, mut first_word) = (0, 0);
    let mut batches = Vec::new();
    for (id, mut clouds) in round {
        let pool = &pools.0[&id];
        clouds.sort_by_key(|c| std::cmp::Reverse(c.levels_in_use));
        let mut items = Vec::with_capacity(clouds.len());
        for c in &clouds {
            items.push([c.slot, first as u32, first_word as u32, c.count]);
            copies.push((c.particles.clone(), first, c.count));
            first += c.count as u64;
            first_word += brick_words(id.shape.m);
        }
        let group = |work: &WorkList, groups: &Buffer| {
            bind(&BindGroupEntries::sequential((
                pool.slots.as_entire_binding(),
                buffers.particles.as_entire_binding(),
                pool.densities.as_entire_binding(),
                buffers.totals.as_entire_binding(),
                BufferBinding {
                    buffer: &pool.density_levels,
                    offset: 0,
                    size: Some(DensityLevels::min_size()),
                },
                work.binding(),
                buffers.bricks.as_entire_binding(),
                buffers.binned.as_entire_binding(),
                groups.as_entire_binding(),
            )))
        };
        let batch = Batch::new(device, &items, |work| group(work, &gather_groups))
            .expect("a pool in a round has clouds");
        let gather_group = group(&batch.work, &stand_in);
        let most = |f: fn(&VoxelizeCloud) -> u32| clouds.iter().map(f).max().unwrap_or(0);
        let sizes = density_level_sizes(id.shape.m);
        let upsample = (1..most(|c| c.levels_in_use))
            .rev()
            .map(|coarse| {
                let using = clouds.iter().filter(|c| c.levels_in_use > coarse).count();
                (coarse, sizes[coarse as usize - 1], using as u32)
            })
            .collect();
        batches.push(PoolVoxelize {
            batch,
            gather_group,
            clears: clouds.iter().map(|c| pool.fine_density(c.slot)).collect(),
            particles: most(|c| c.count),
            bricks: DensityLevels::bricks(id.shape.m) as u32,
            upsample,
        });
    }
    VoxelizeRound {
        scratch: buffers,
        words,
        copies,
        pools: batches,
        gather_groups,
    }
}

/// The gather's indirect dispatches of a round whose pools hold `clouds` each: one per pool and
/// chunk of its work list, `(GATHER_ROW, 0, clouds in the chunk)`; `scan_bricks` raises the 0.
fn gather_dispatches(clouds: impl Iterator<Item = usize>) -> Vec<[u32; 3]> {
    clouds
        .flat_map(|n| {
            (0..n as u32)
                .step_by(WORK_CHUNK as usize)
                .map(move |first| [GATHER_ROW, 0, (n as u32 - first).min(WORK_CHUNK)])
        })
        .collect()
}

/// Everything a round writes is cleared, and its particles copied into the scratch, before its
/// passes (outside any compute pass).
pub(crate) fn prepare_round(ctx: &mut RenderContext, round: &VoxelizeRound) {
    let encoder = ctx.command_encoder();
    for (particles, first, count) in &round.copies {
        if *count > 0 {
            let bytes = *count as u64 * PARTICLE_BYTES;
            encoder.copy_buffer_to_buffer(
                particles,
                0,
                &round.scratch.particles,
                first * PARTICLE_BYTES,
                bytes,
            );
        }
    }
    encoder.clear_buffer(&round.scratch.bricks, 0, Some(round.words.max(1) * 4));
    for clear in round.pools.iter().flat_map(|p| &p.clears) {
        encoder.clear_buffer(&clear.buffer, clear.offset, Some(clear.size));
    }
}

/// The workgroups of each of the binning's passes and the kernels' sums, for one pool's clouds
/// (each dispatch has one z workgroup per cloud).
fn pass_groups(p: &PoolVoxelize) -> [[u32; 2]; 5] {
    let per_particle = [p.particles.div_ceil(workgroups::LINEAR).max(1), 1];
    [
        per_particle,
        [1, 1],
        per_particle,
        [p.bricks.div_ceil(BRICK_THREADS).max(1), 1],
        spread_groups(p.particles.div_ceil(SUMS_PER_GROUP)),
    ]
}

/// The passes of a round: the binning and the kernels' sums, one dispatch each per pool (and per
/// chunk of its list); the gather over the marked bricks, an indirect dispatch each; then the
/// coarse levels enlarged into the fine grid, coarsest first, one dispatch per level.
pub(crate) fn record_round(
    pass: &mut StagePass,
    pipelines: [&ComputePipeline; 7],
    round: &VoxelizeRound,
) -> u32 {
    let [passes @ .., gather, upsample] = pipelines;
    for (i, pipeline) in passes.into_iter().enumerate() {
        pass.set_pipeline(pipeline);
        for p in &round.pools {
            let [x, y] = pass_groups(p)[i];
            for (offset, items) in p.batch.work.chunks() {
                pass.set_bind_group(0, &p.batch.group, &[0, offset]);
                pass.dispatch(x, y, items);
            }
        }
    }
    pass.set_pipeline(gather);
    let mut args = 0;
    for p in &round.pools {
        for (offset, _) in p.batch.work.chunks() {
            pass.set_bind_group(0, &p.gather_group, &[0, offset]);
            pass.dispatch_indirect(&round.gather_groups, args);
            args += 12;
        }
    }
    pass.set_pipeline(upsample);
    for p in &round.pools {
        for &(coarse, below, using) in &p.upsample {
            let levels = coarse * DYNAMIC_UNIFORM_STRIDE;
            for (chunk, (offset, items)) in p.batch.work.chunks().enumerate() {
                let first = chunk as u32 * WORK_CHUNK;
                let items = items.min(using.saturating_sub(first));
                if items > 0 {
                    pass.set_bind_group(0, &p.batch.group, &[levels, offset]);
                    dispatch_columns(pass, below, items);
                }
            }
        }
    }
    round.copies.len() as u32
}

#[cfg(test)]
mod tests {
    use super::{GATHER_ROW, WORK_CHUNK, gather_dispatches, round_of_each, scratch_capacity};

    #[test]
    fn voxelize_adds_no_float_with_an_atomic() {
        let source = include_str!("voxelize.wgsl");
        assert!(!source.contains("atomicCompareExchange"));
        // The density and the kernels' sums are plain floats, each written by one invocation;
        // the only atomics are the binning's integer counts.
        assert!(source.contains("var<storage, read_write> density: array<f32>;"));
        assert!(source.contains("var<storage, read_write> totals: array<f32>;"));
        let atomics: Vec<&str> = source.lines().filter(|l| l.contains("atomic<")).collect();
        assert_eq!(
            atomics,
            [
                "@group(0) @binding(6) var<storage, read_write> bricks: array<atomic<u32>>;",
                "@group(0) @binding(8) var<storage, read_write> gather_groups: array<atomic<u32>>;",
                "var<workgroup> long_count: atomic<u32>;"
            ]
        );
    }

    #[test]
    fn the_gather_dispatches_once_per_pool_and_chunk_of_its_clouds() {
        let chunk = WORK_CHUNK;
        assert_eq!(
            gather_dispatches([3, 1].into_iter()),
            [[GATHER_ROW, 0, 3], [GATHER_ROW, 0, 1]]
        );
        // A pool of more clouds than one dispatch's z holds: one dispatch per chunk.
        assert_eq!(
            gather_dispatches([chunk as usize + 5].into_iter()),
            [[GATHER_ROW, 0, chunk], [GATHER_ROW, 0, 5]]
        );
        assert!(gather_dispatches([].into_iter()).is_empty());
    }

    #[test]
    fn the_scratch_grows_by_doubling_and_shrinks_below_a_quarter() {
        // None yet, or too small: the next power of two, within one binding.
        assert_eq!(scratch_capacity(None, 1000, 1 << 20), Some(1024));
        assert_eq!(scratch_capacity(Some(1024), 1025, 1 << 20), Some(2048));
        assert_eq!(scratch_capacity(Some(1024), 3000, 2500), Some(3000));
        assert_eq!(scratch_capacity(None, 0, 100), Some(1));
        // Enough, and more than a quarter used: kept.
        assert_eq!(scratch_capacity(Some(4096), 4096, 1 << 20), None);
        assert_eq!(scratch_capacity(Some(4096), 1025, 1 << 20), None);
        // A quarter or less: shrunk to what a doubling would have given.
        assert_eq!(scratch_capacity(Some(4096), 1024, 1 << 20), Some(1024));
        assert_eq!(scratch_capacity(Some(1 << 21), 3, 1 << 22), Some(4));
        // Halving and doubling again keeps the buffer.
        assert_eq!(scratch_capacity(Some(2048), 1000, 1 << 20), None);
        assert_eq!(scratch_capacity(Some(2048), 2000, 1 << 20), None);
    }

    #[test]
    fn a_round_holds_what_one_binding_does_and_at_least_one_cloud() {
        let particles =
            |counts: &[u64]| -> Vec<(u64, u64)> { counts.iter().map(|&c| (c, 1)).collect() };
        let limits = (100, 1000);
        assert_eq!(
            round_of_each(&particles(&[60, 50, 30, 200, 0]), limits),
            [0, 1, 1, 2, 3]
        );
        assert_eq!(round_of_each(&particles(&[40, 60, 1]), limits), [0, 0, 1]);
        assert_eq!(round_of_each(&[(u64::MAX, 1), (5, 1)], (1, 1)), [0, 1]);
        assert!(round_of_each(&[], limits).is_empty());
        // The bricks' words split rounds too.
        assert_eq!(
            round_of_each(&[(1, 600), (1, 300), (1, 200), (1, 5000)], limits),
            [0, 0, 1, 2]
        );
    }
}
