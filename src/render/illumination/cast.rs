//! The cast pass's work (docs/illumination.md §2, "Clouds shadow each other"): which light volumes
//! of a cloud take which other clouds' optical depth (`cast.wgsl`). Who casts on whom is planned
//! in [`plan::casters`](crate::render::plan::casters); this file turns it into the pass's items.

use bevy::{platform::collections::HashMap, prelude::*};

use crate::render::{
    extract::ExtractedCloud,
    plan::casters::{CastStart, CastTarget, CastWork, CasterVolume, add_cast},
    plan::pools::{PoolId, VolumePools},
    plan::volumes::CloudVolumes,
};

/// Adds the cast of light slot `light` of `receiver` (its cloud and volumes) by `casters` (render
/// entities, found in `placed`) to `work` ([`add_cast`]).
pub(crate) fn add_light_cast(
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
