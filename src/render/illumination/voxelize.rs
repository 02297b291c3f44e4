//! Voxelize (the paper's Algorithm 1, line 2; docs/illumination.md §1): every particle deposits
//! its mass into its cloud's fine density grid. Each cloud's particles are a buffer of their own,
//! so the particles of the clouds voxelized this frame are first copied one after the other into
//! a scratch buffer; then, like shade, gather and scatter, one dispatch per pass covers every
//! cloud of a volume pool, its z workgroups walking a work list: the dispatch count does not grow
//! with the clouds.

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_resource::{
            BindGroup, BindGroupEntries, BindGroupEntry, Buffer, BufferBinding, BufferDescriptor,
            BufferUsages, ComputePipeline, ShaderType,
        },
        renderer::{RenderContext, RenderDevice},
    },
};

use crate::math::density_level_sizes;
use crate::render::{
    core::gpu::Batch,
    core::gpu::{DYNAMIC_UNIFORM_STRIDE, StagePass, WORK_CHUNK},
    core::workgroups::{self, dispatch_columns},
    extract::particles::GpuParticles,
    plan::pools::{BufferRange, PoolId, VolumePools},
    plan::volumes::{CloudVolumes, DensityLevels},
};

/// Bytes of one particle on the GPU (`Particle` in `types.wgsl`).
const PARTICLE_BYTES: u64 = 32;

/// The scratch buffers of the voxelize rounds (render world resource): each round's particles,
/// one cloud after the other, and their kernel sums. Grown when a frame needs more and kept for
/// the next, so a cloud whose particles change every frame allocates nothing; shrunk when a
/// frame needs a quarter or less (see `scratch_capacity`).
#[derive(Resource, Default)]
pub struct VoxelizeScratch(Vec<ScratchBuffers>);

#[derive(Clone)]
struct ScratchBuffers {
    particles: Buffer,
    totals: Buffer,
    /// Particles it holds.
    capacity: u64,
}

impl VoxelizeScratch {
    /// Every round's buffers (the memory census).
    pub(crate) fn buffers(&self) -> impl Iterator<Item = &Buffer> {
        self.0.iter().flat_map(|s| [&s.particles, &s.totals])
    }

    /// Frees every round's buffers: no cloud is left to voxelize.
    pub(crate) fn release(&mut self) {
        self.0.clear();
    }

    /// Round `round`'s buffers (rounds are reserved in order), holding at least `particles` and
    /// at most `max_particles` (one storage binding).
    fn reserve(
        &mut self,
        device: &RenderDevice,
        round: usize,
        particles: u64,
        max_particles: u64,
    ) -> ScratchBuffers {
        let current = self.0.get(round).map(|s| s.capacity);
        let Some(capacity) = scratch_capacity(current, particles, max_particles) else {
            return self.0[round].clone();
        };
        let buffer = |label, bytes: u64| {
            device.create_buffer(&BufferDescriptor {
                label: Some(label),
                size: capacity * bytes,
                usage: BufferUsages::STORAGE | BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let buffers = ScratchBuffers {
            particles: buffer("particle_clouds_voxelize_particles", PARTICLE_BYTES),
            totals: buffer("particle_clouds_voxelize_totals", 4),
            capacity,
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
    /// Rows per axis of its largest particle's support.
    rows: u32,
    levels_in_use: u32,
}

impl VoxelizeCloud {
    pub(crate) fn new(gpu: &GpuParticles, volumes: &CloudVolumes) -> Self {
        Self {
            slot: volumes.slot.index,
            particles: gpu.buffer.clone(),
            count: gpu.count,
            rows: volumes.fine_params.rows,
            levels_in_use: volumes.levels_in_use as u32,
        }
    }
}

/// One pool's clouds in a round.
struct PoolVoxelize {
    /// `(slot, first particle)` per cloud, those with the most density levels first.
    batch: Batch,
    /// The clouds' density levels, cleared before the deposit.
    clears: Vec<BufferRange>,
    /// Workgroups along x (the most particles of a cloud) and y (the most rows²).
    groups: [u32; 2],
    /// Per coarse level to enlarge, coarsest first: the level, voxels per side of the level
    /// below, and the clouds (the first of the work list) that use it.
    upsample: Vec<(u32, u32, u32)>,
}

/// The clouds voxelized together: their particles in one scratch buffer.
pub(crate) struct VoxelizeRound {
    scratch: ScratchBuffers,
    /// Particles in the scratch.
    particles: u64,
    /// Each cloud's particles and their first element in the scratch.
    copies: Vec<(Buffer, u64, u32)>,
    pools: Vec<PoolVoxelize>,
}

/// Splits the clouds to voxelize into rounds whose particles fit in one storage binding of
/// `max_binding` bytes (one round unless they hold millions), and makes each pool's batch.
pub(crate) fn voxelize_rounds(
    device: &RenderDevice,
    scratch: &mut VoxelizeScratch,
    pools: &VolumePools,
    clouds: HashMap<PoolId, Vec<VoxelizeCloud>>,
    max_binding: u64,
    bind: impl Fn(&[BindGroupEntry]) -> BindGroup,
) -> Vec<VoxelizeRound> {
    let max_particles = (max_binding / PARTICLE_BYTES).max(1);
    let mut by_pool: Vec<_> = clouds.into_iter().collect();
    by_pool.sort_by_key(|(id, _)| *id);
    let in_order: Vec<_> = by_pool
        .into_iter()
        .flat_map(|(id, clouds)| clouds.into_iter().map(move |c| (id, c)))
        .collect();
    let counts: Vec<u64> = in_order.iter().map(|(_, c)| c.count as u64).collect();
    let mut rounds: Vec<Vec<(PoolId, Vec<VoxelizeCloud>)>> = Vec::new();
    for ((id, cloud), round) in in_order
        .into_iter()
        .zip(round_of_each(&counts, max_particles))
    {
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
        .map(|(i, round)| make_round(device, scratch, pools, (i, max_particles), round, &bind))
        .collect()
}

/// The round of each cloud of `counts` particles, in order: a round holds what one storage
/// binding of `max_particles` does, and at least one cloud.
fn round_of_each(counts: &[u64], max_particles: u64) -> Vec<usize> {
    let mut round = 0;
    let mut in_round = 0u64;
    counts
        .iter()
        .map(|&count| {
            let count = count.max(1);
            if in_round > 0 && in_round.saturating_add(count) > max_particles {
                round += 1;
                in_round = 0;
            }
            in_round = in_round.saturating_add(count);
            round
        })
        .collect()
}

fn make_round(
    device: &RenderDevice,
    scratch: &mut VoxelizeScratch,
    pools: &VolumePools,
    (index, max_particles): (usize, u64),
    round: Vec<(PoolId, Vec<VoxelizeCloud>)>,
    bind: &impl Fn(&[BindGroupEntry]) -> BindGroup,
) -> VoxelizeRound {
    let particles: u64 = round
        .iter()
        .flat_map(|(_, c)| c)
        .map(|c| c.count as u64)
        .sum();
    let buffers = scratch.reserve(device, index, particles, max_particles);
    let mut copies = Vec::new();
    let mut first = 0;
    let mut batches = Vec::new();
    for (id, mut clouds) in round {
        let pool = &pools.0[&id];
        clouds.sort_by_key(|c| std::cmp::Reverse(c.levels_in_use));
        let mut items = Vec::with_capacity(clouds.len());
        for c in &clouds {
            items.push([c.slot, first as u32]);
            copies.push((c.particles.clone(), first, c.count));
            first += c.count as u64;
        }
        let batch = Batch::new(device, &items, |work| {
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
            )))
        })
        .expect("a pool in a round has clouds");
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
            clears: clouds.iter().map(|c| pool.fine_density(c.slot)).collect(),
            groups: [
                most(|c| c.count).div_ceil(workgroups::LINEAR).max(1),
                most(|c| c.rows).pow(2).max(1),
            ],
            upsample,
        });
    }
    VoxelizeRound {
        scratch: buffers,
        particles,
        copies,
        pools: batches,
    }
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
    encoder.clear_buffer(&round.scratch.totals, 0, Some(round.particles.max(1) * 4));
    for clear in round.pools.iter().flat_map(|p| &p.clears) {
        encoder.clear_buffer(&clear.buffer, clear.offset, Some(clear.size));
    }
}

/// The three passes of a round: the kernels' sums, the deposit, then the coarse levels enlarged
/// into the fine grid, coarsest first; one dispatch each per pool (and per chunk of its list).
pub(crate) fn record_round(
    pass: &mut StagePass,
    [kernel_sums, deposit, upsample]: [&ComputePipeline; 3],
    round: &VoxelizeRound,
) -> u32 {
    for pipeline in [kernel_sums, deposit] {
        pass.set_pipeline(pipeline);
        for p in &round.pools {
            for (offset, items) in p.batch.work.chunks() {
                pass.set_bind_group(0, &p.batch.group, &[0, offset]);
                pass.dispatch(p.groups[0], p.groups[1], items);
            }
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
    use super::{round_of_each, scratch_capacity};

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
        assert_eq!(round_of_each(&[60, 50, 30, 200, 0], 100), [0, 1, 1, 2, 3]);
        assert_eq!(round_of_each(&[40, 60, 1], 100), [0, 0, 1]);
        assert_eq!(round_of_each(&[u64::MAX, 5], 1), [0, 1]);
        assert!(round_of_each(&[], 100).is_empty());
    }
}
