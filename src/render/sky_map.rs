//! The render world's side of the sky map (docs/illumination.md §10; the main world places it,
//! [`ShadowMapPlacement::sky`]): which clouds hide the sky, and the dispatches that fill the map
//! (`sky_map.wgsl`) when what it holds changes (its place, or a cloud's density, medium or
//! transform), so a still sky costs nothing.

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_resource::{BindGroup, Buffer, ShaderType},
        renderer::RenderDevice,
    },
};

use super::{
    gpu::{storage, uniform_bytes},
    key_of,
    pools::PoolId,
    shadow_maps::LitCloud,
};
use crate::shadow_maps::{SKY_MAP_DIRECTIONS, ShadowMapPlacement};

/// The key of what the sky map holds (render world resource).
#[derive(Resource, Default)]
pub struct SkyMapKey(pub(crate) Option<u64>);

/// A cloud as the sky map's rays see it (mirror of `SkyCaster` in `sky_map.wgsl`).
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct SkyCaster {
    /// Cloud-local from world.
    pub local_from_world: Mat4,
    /// World centre of a sphere that holds its density (its scattering grid's cube widened by half
    /// a voxel).
    pub centre: Vec3,
    /// Its radius, metres.
    pub radius: f32,
    /// Its slot in its pool.
    pub slot: u32,
}

/// One dispatch of the sky map's march (mirror of `SkyMapTarget` in `sky_map.wgsl`): the map's
/// texels on the plane, and whether it adds to the optical depths or writes them.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct SkyMapTarget {
    /// Texel `(0, 0)`'s point on the plane, world metres.
    pub origin: Vec3,
    /// The map's first element in the maps' buffer.
    pub first: u32,
    /// From one texel to the next along the map's first axis.
    pub step_x: Vec3,
    /// Texels per side.
    pub size: u32,
    /// From one texel to the next along its second axis.
    pub step_y: Vec3,
    /// The dispatch's casters.
    pub casters: u32,
    /// 1 when the dispatch adds to the optical depths (every pool's after the first).
    pub accumulate: u32,
}

impl SkyMapTarget {
    /// The texels of `map`, for `casters` casters.
    pub fn new(map: &ShadowMapPlacement, casters: u32, accumulate: bool) -> Self {
        Self {
            origin: map.texel_point(0, 0),
            first: map.first,
            step_x: map.u * map.texel,
            size: map.size,
            step_y: map.v * map.texel,
            casters,
            accumulate: accumulate as u32,
        }
    }
}

/// This frame's filling of the sky map: the region (bytes) to clear when no cloud hides the sky,
/// else one march per pool the clouds lie in, then the resolve.
#[derive(Default)]
pub(crate) struct SkyMapFill {
    pub(crate) clear: Option<(u64, u64)>,
    pub(crate) marches: Vec<BindGroup>,
    pub(crate) resolve: Option<BindGroup>,
    /// Texels of the map.
    pub(crate) texels: u32,
}

impl SkyMapFill {
    /// Whether anything is to be done this frame.
    pub(crate) fn is_pending(&self) -> bool {
        self.clear.is_some() || self.resolve.is_some()
    }
}

/// The sky map's filling this frame, when `map` (in `buffer`, the maps' GPU buffer) is stale:
/// every cloud of `clouds` that casts shadows hides the sky. `bind` makes a dispatch's bind
/// group from the pool its casters lie in, the casters, the target and the optical depths'
/// scratch buffer.
pub(crate) fn sky_map_fill(
    map: Option<&ShadowMapPlacement>,
    buffer: Option<&Buffer>,
    clouds: &[LitCloud],
    key: &mut SkyMapKey,
    device: &RenderDevice,
    bind: impl Fn(PoolId, &[SkyCaster], &SkyMapTarget, &Buffer) -> BindGroup,
) -> SkyMapFill {
    let (Some(map), Some(buffer)) = (map, buffer) else {
        key.0 = None;
        return SkyMapFill::default();
    };
    let hiding: Vec<&LitCloud> = clouds
        .iter()
        .filter(|(_, cloud, _, state)| cloud.casts_shadows && state.ready)
        .collect();
    let held: Vec<_> = hiding
        .iter()
        .map(|(e, cloud, _, state)| {
            let place = cloud.world_from_local.to_cols_array().map(f32::to_bits);
            (*e, state.keys.density, cloud.extinction.to_bits(), place)
        })
        .collect();
    let now = key_of((uniform_bytes(map), buffer.id(), held));
    if key.0 == Some(now) {
        return SkyMapFill::default();
    }
    key.0 = Some(now);
    let texels = map.size * map.size;
    let mut fill = SkyMapFill {
        texels,
        ..default()
    };
    let mut by_pool: HashMap<PoolId, Vec<SkyCaster>> = HashMap::default();
    for &&(_, cloud, v, _) in &hiding {
        by_pool
            .entry(v.slot.pool)
            .or_default()
            .push(sky_caster(cloud, v));
    }
    let mut by_pool: Vec<_> = by_pool.into_iter().collect();
    by_pool.sort_by_key(|(pool, _)| *pool);
    if by_pool.is_empty() {
        fill.clear = Some((map.first as u64 * 4, texels as u64 * 4));
        return fill;
    }
    let depths = (texels * SKY_MAP_DIRECTIONS) as u64 * 4;
    let scratch = storage(device, "particle_clouds_sky_depth", depths);
    for (i, (pool, casters)) in by_pool.iter().enumerate() {
        let target = SkyMapTarget::new(map, casters.len() as u32, i > 0);
        fill.marches.push(bind(*pool, casters, &target, &scratch));
    }
    let (pool, casters) = &by_pool[0];
    fill.resolve = Some(bind(
        *pool,
        casters,
        &SkyMapTarget::new(map, 0, false),
        &scratch,
    ));
    fill
}

/// The sky map's view of `cloud` with its `volumes`.
fn sky_caster(
    cloud: &super::extract::ExtractedCloud,
    volumes: &super::volumes::CloudVolumes,
) -> SkyCaster {
    let grid = &volumes.params;
    let side = (grid.n + 1) as f32 * grid.h;
    let centre = grid.grid_origin + Vec3::splat(0.5 * grid.n as f32 * grid.h);
    SkyCaster {
        local_from_world: Mat4::from(cloud.world_from_local.inverse()),
        centre: cloud.world_from_local.transform_point3(centre),
        radius: 0.5 * 3f32.sqrt() * side * cloud.scale(),
        slot: volumes.slot.index,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The target's texels are the map's: its origin, steps and first element.
    #[test]
    fn a_target_walks_the_maps_texels() {
        let clouds = [(Vec3::new(3.0, 10.0, -2.0), 2.0)];
        let map = ShadowMapPlacement::sky(&clouds, 1.0, 16, 512).unwrap();
        let target = SkyMapTarget::new(&map, 3, true);
        for (i, j) in [(0, 0), (15, 0), (4, 11)] {
            let x = target.origin + i as f32 * target.step_x + j as f32 * target.step_y;
            assert!(x.distance(map.texel_point(i, j)) < 1e-4, "{i} {j}");
            assert!((x.y - 1.0).abs() < 1e-5, "on the plane");
        }
        assert_eq!((target.first, target.size, target.casters), (512, 16, 3));
        assert_eq!(target.accumulate, 1);
    }
}
