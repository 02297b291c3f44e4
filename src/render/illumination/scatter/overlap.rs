//! Other clouds' media in a cloud's scattering grid (docs/illumination.md §4, "Clouds that
//! overlap"; `overlap.wgsl`): the work items of the overlap pass, per pool the neighbours lie in.

use bevy::{platform::collections::HashMap, prelude::*};

use crate::particle::DeltaM;
use crate::render::{
    extract::ExtractedCloud,
    plan::casters::by_pool,
    plan::overlap::{Neighbour, OverlapItem},
    plan::pools::{PoolId, VolumePools},
    plan::volumes::CloudVolumes,
};

/// The overlap work of one receivers' pool whose neighbours lie in one pool.
#[derive(Default)]
pub(crate) struct OverlapWork {
    pub(crate) items: Vec<OverlapItem>,
    pub(crate) neighbours: Vec<Neighbour>,
}

/// Adds the overlap of `receiver` (its cloud and volumes) by `neighbours` (render entities,
/// found in `placed`) to `work`, one item per pool the neighbours lie in: the first (in pool
/// order) writes `foreign`, the others add to it.
pub(crate) fn add_overlaps(
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
