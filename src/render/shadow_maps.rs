//! The render world's side of the cloud shadow maps (docs/illumination.md §10; the main world
//! places them, [`crate::shadow_maps`]): which maps the cast pass fills this frame, and with
//! which clouds. A map is filled anew only when what it holds changes (its place, or a cloud's
//! light volume or transform), so a still sky costs nothing.

use bevy::{
    math::Affine3A,
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_resource::{BindGroup, Buffer},
        renderer::RenderDevice,
    },
};

use super::{
    cast::{CastStart, CastTarget, CastWork, Caster, add_cast},
    extract::{ExtractedCloud, ExtractedCloudLights},
    gpu::{WorkList, uniform_bytes},
    illumination::{Batch, light_caster},
    key_of,
    plan::CloudIllumination,
    pools::{PoolId, VolumePools},
    volumes::CloudVolumes,
};
use crate::shadow_maps::{CloudShadowMaps, ShadowMapPlacement};

/// The key of what each light's map holds (render world resource).
#[derive(Resource, Default)]
pub struct ShadowMapKeys(HashMap<Entity, u64>);

/// This frame's filling of the shadow maps: the maps' buffer, the regions (bytes) of maps no cloud
/// casts on (cleared), and one batch of cast targets per pool the casters lie in, with the texels
/// each target covers.
#[derive(Default)]
pub(crate) struct ShadowMapCasts {
    pub(crate) buffer: Option<Buffer>,
    pub(crate) clears: Vec<(u64, u64)>,
    pub(crate) batches: Vec<(Batch, u32)>,
}

/// A cloud with its volumes and illumination state.
pub(crate) type LitCloud<'a> = (
    Entity,
    &'a ExtractedCloud,
    &'a CloudVolumes,
    &'a CloudIllumination,
);

/// The maps to fill this frame, in `buffer` (the maps' GPU buffer, once uploaded), from the own
/// light volumes of `clouds`; `bind` makes a batch's bind group from its casters, the pool they
/// lie in and its work list.
#[allow(clippy::too_many_arguments)]
pub(crate) fn shadow_map_casts<'a>(
    maps: &CloudShadowMaps,
    buffer: Option<&Buffer>,
    lights: &ExtractedCloudLights,
    clouds: &[LitCloud<'a>],
    pools: &VolumePools,
    keys: &mut ShadowMapKeys,
    device: &RenderDevice,
    bind: impl Fn(&[Caster], PoolId, &WorkList) -> BindGroup,
) -> ShadowMapCasts {
    let Some(buffer) = buffer.filter(|_| maps.resolution > 0) else {
        keys.0.clear();
        return ShadowMapCasts::default();
    };
    let mut casts = ShadowMapCasts {
        buffer: Some(buffer.clone()),
        ..default()
    };
    let mut work: HashMap<PoolId, CastWork> = HashMap::default();
    for (l, light) in lights.lights.iter().enumerate() {
        let Some(map) = maps.map_of(light.entity) else {
            continue;
        };
        let casters: Vec<&LitCloud> = clouds
            .iter()
            .filter(|(_, cloud, v, state)| cloud.casts_shadows && state.ready && v.lights.len() > l)
            .collect();
        let held: Vec<_> = casters
            .iter()
            .map(|(e, cloud, _, state)| {
                let place = cloud.world_from_local.to_cols_array().map(f32::to_bits);
                (*e, state.keys.lights.get(l).copied(), place)
            })
            .collect();
        let key = key_of((uniform_bytes(map), buffer.id(), held));
        if keys.0.get(&light.entity) == Some(&key) {
            continue;
        }
        keys.0.insert(light.entity, key);
        let placed = casters.iter().filter_map(|&&(_, cloud, v, _)| {
            let caster = light_caster(cloud, v, l, pools)?;
            Some((v.slot.pool, caster.on(&Affine3A::IDENTITY)))
        });
        let placed: Vec<_> = placed.collect();
        match placed.first() {
            // The first pool's dispatch writes the map from nothing, the others add to it.
            Some(&(own, _)) => add_cast(&mut work, map_target(map), CastStart::Zero, placed, own),
            // No cloud casts on it: it holds nothing.
            None => {
                let texels = (map.size * map.size) as u64;
                casts.clears.push((map.first as u64 * 4, texels * 4));
            }
        }
    }
    let mut work: Vec<_> = work.into_iter().collect();
    work.sort_by_key(|(pool, _)| *pool);
    for (pool, w) in work {
        let columns = w.targets.iter().map(CastTarget::columns).max().unwrap_or(0);
        if let Some(batch) = Batch::new(device, &w.targets, |list| bind(&w.casters, pool, list)) {
            casts.batches.push((batch, columns));
        }
    }
    casts
}

/// The texels of `map`, in world space: each at its column's end, past every cloud.
fn map_target(map: &ShadowMapPlacement) -> CastTarget {
    let step = |axis: Vec3| (axis * map.texel).to_array();
    CastTarget {
        origin: map.texel_point(0, 0).to_array(),
        first: map.first,
        step_x: step(map.u),
        size_x: map.size,
        step_y: step(map.v),
        size_y: map.size,
        step_z: [0.0; 3],
        size_z: 1,
        ..default()
    }
}
