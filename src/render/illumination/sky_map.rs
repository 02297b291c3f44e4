//! The render world's side of the sky map (docs/illumination.md §10; the main world places it,
//! [`ShadowMapPlacement::sky`]): which clouds hide the sky, and the dispatches that fill the map
//! (`sky_map.wgsl`) when what it holds changes (its place, or a cloud's density, medium or
//! transform), so a still sky costs nothing.
//!
//! A ray tests only the clouds that may lie on it: per direction and tile of
//! [`SKY_MAP_TILE`]² texels, the clouds whose sphere, seen along the direction, covers part of
//! the tile ([`tile_lists`]). Without the lists every ray tested every cloud: 100 clouds cost
//! about 3 s a fill on lavapipe (273 ms with them), almost all of it in those tests.

use bevy::{
    platform::collections::HashMap,
    prelude::*,
    render::{
        render_resource::{BindGroup, Buffer, ShaderType},
        renderer::RenderDevice,
    },
};

use crate::render::{
    core::gpu::{storage, uniform_bytes},
    core::key_of,
    illumination::shadow_maps::LitCloud,
    plan::pools::PoolId,
};
use crate::shadow_maps::{SKY_MAP_DIRECTIONS, ShadowMapPlacement, sky_direction};

pub use crate::render::core::workgroups::SKY_MAP_TILE;

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
    /// 1 when the dispatch adds to the optical depths (every pool's after the first).
    pub accumulate: u32,
    /// Tiles per side of the caster lists.
    pub tiles: u32,
}

impl SkyMapTarget {
    /// The texels of `map`; the dispatch adds to the optical depths with `accumulate`.
    pub fn new(map: &ShadowMapPlacement, accumulate: bool) -> Self {
        Self {
            origin: map.texel_point(0, 0),
            first: map.first,
            step_x: map.u * map.texel,
            size: map.size,
            step_y: map.v * map.texel,
            accumulate: accumulate as u32,
            tiles: map.size.div_ceil(SKY_MAP_TILE),
        }
    }
}

/// The casters each ray of `map` may meet, for casters of world spheres `spheres` (centre,
/// radius): per direction `k` and tile `(a, b)` of [`SKY_MAP_TILE`]² texels, list
/// `k T² + a + T b` (`T` tiles per side). Element `i` of the result is where list `i` starts
/// among the entries (`K T² + 1` offsets, the last the end), the entries (caster indices) follow.
///
/// A ray from point `q` of the plane along `w` (`w.y > 0`) meets the sphere of centre `c` and
/// radius `r` where `q` lies in the ellipse about `c`'s shadow along `w`,
/// `c' = c - w (c.y - h) / w.y`: semi-axes `r / w.y` along `w`'s horizontal direction and `r`
/// across it. A caster is listed in every tile its ellipse's bounding box reaches, a texel to
/// spare; spheres wholly below the plane in none.
pub fn tile_lists(map: &ShadowMapPlacement, spheres: &[(Vec3, f32)]) -> Vec<u32> {
    let tiles = map.size.div_ceil(SKY_MAP_TILE);
    let height = -map.w_end;
    let mut lists: Vec<Vec<u32>> = vec![Vec::new(); (SKY_MAP_DIRECTIONS * tiles * tiles) as usize];
    let tile_of = |x: f32| ((x / map.texel - 0.5) / SKY_MAP_TILE as f32).floor();
    for k in 0..SKY_MAP_DIRECTIONS {
        let w = sky_direction(k);
        let across = Vec2::new(w.x, w.z);
        let (cos, sin) = match across.length() {
            0.0 => (1.0, 0.0),
            l => (across.x / l, across.y / l),
        };
        for (i, &(c, r)) in spheres.iter().enumerate() {
            if c.y + r < height {
                continue;
            }
            let shadow = c - w * (c.y - height) / w.y;
            let along = r / w.y;
            let half =
                Vec2::new((along * cos).hypot(r * sin), (along * sin).hypot(r * cos)) + map.texel;
            let lo = Vec2::new(shadow.x, shadow.z) - half - map.corner;
            let hi = Vec2::new(shadow.x, shadow.z) + half - map.corner;
            let clamp = |t: f32| t.clamp(0.0, tiles as f32 - 1.0) as u32;
            if tile_of(hi.x) < 0.0 || tile_of(hi.y) < 0.0 {
                continue;
            }
            if tile_of(lo.x) >= tiles as f32 || tile_of(lo.y) >= tiles as f32 {
                continue;
            }
            for b in clamp(tile_of(lo.y))..=clamp(tile_of(hi.y)) {
                for a in clamp(tile_of(lo.x))..=clamp(tile_of(hi.x)) {
                    lists[(k * tiles * tiles + a + tiles * b) as usize].push(i as u32);
                }
            }
        }
    }
    let mut flat = Vec::with_capacity(lists.len() + 1);
    let mut at = 0;
    for list in &lists {
        flat.push(at);
        at += list.len() as u32;
    }
    flat.push(at);
    flat.extend(lists.into_iter().flatten());
    flat
}

/// This frame's filling of the sky map: the region (bytes) to clear when no cloud hides the sky,
/// else one march per pool the clouds lie in, then the resolve (with the first march's bind
/// group: the same scratch, map and target texels).
#[derive(Default)]
pub(crate) struct SkyMapFill {
    pub(crate) clear: Option<(u64, u64)>,
    pub(crate) marches: Vec<BindGroup>,
    /// Texels of the map.
    pub(crate) texels: u32,
}

impl SkyMapFill {
    /// Whether anything is to be done this frame.
    pub(crate) fn is_pending(&self) -> bool {
        self.clear.is_some() || !self.marches.is_empty()
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
    bind: impl Fn(PoolId, &[SkyCaster], &[u32], &SkyMapTarget, &Buffer) -> BindGroup,
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
        let target = SkyMapTarget::new(map, i > 0);
        let spheres: Vec<_> = casters.iter().map(|c| (c.centre, c.radius)).collect();
        let lists = tile_lists(map, &spheres);
        fill.marches
            .push(bind(*pool, casters, &lists, &target, &scratch));
    }
    fill
}

/// The sky map's view of `cloud` with its `volumes`.
fn sky_caster(
    cloud: &crate::render::extract::ExtractedCloud,
    volumes: &crate::render::plan::volumes::CloudVolumes,
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
        let target = SkyMapTarget::new(&map, true);
        for (i, j) in [(0, 0), (15, 0), (4, 11)] {
            let x = target.origin + i as f32 * target.step_x + j as f32 * target.step_y;
            assert!(x.distance(map.texel_point(i, j)) < 1e-4, "{i} {j}");
            assert!((x.y - 1.0).abs() < 1e-5, "on the plane");
        }
        assert_eq!((target.first, target.size), (512, 16));
        assert_eq!((target.accumulate, target.tiles), (1, 2));
    }

    /// Every caster a ray meets is in the list of the ray's direction and tile: checked against
    /// the exact ray–sphere test for every texel and direction; and the lists cull (most
    /// directions and tiles list few of the clouds).
    #[test]
    fn the_tile_lists_hold_every_cloud_a_ray_meets() {
        let spheres: Vec<(Vec3, f32)> = (0..12)
            .map(|i| {
                let a = i as f32 * 2.1;
                (
                    Vec3::new(30.0 * a.cos(), 8.0 + (i % 3) as f32 * 4.0, 25.0 * a.sin()),
                    3.0,
                )
            })
            .chain([(Vec3::new(0.0, -20.0, 0.0), 2.0)])
            .collect();
        let map = ShadowMapPlacement::sky(&spheres, 1.0, 40, 0).unwrap();
        let lists = tile_lists(&map, &spheres);
        let tiles = map.size.div_ceil(SKY_MAP_TILE);
        let start = (SKY_MAP_DIRECTIONS * tiles * tiles + 1) as usize;
        let list = |k: u32, t: u32| {
            let i = (k * tiles * tiles + t) as usize;
            lists[start + lists[i] as usize..start + lists[i + 1] as usize].to_vec()
        };
        let (mut listed, mut hits) = (0, 0);
        for k in 0..SKY_MAP_DIRECTIONS {
            let w = sky_direction(k);
            for j in 0..map.size {
                for i in 0..map.size {
                    let q = map.texel_point(i, j);
                    let tile = i / SKY_MAP_TILE + tiles * (j / SKY_MAP_TILE);
                    let held = list(k, tile);
                    for (c, &(centre, r)) in spheres.iter().enumerate() {
                        let oc = centre - q;
                        let b = oc.dot(w);
                        if b >= -r && oc.length_squared() - b * b <= r * r {
                            hits += 1;
                            assert!(held.contains(&(c as u32)), "{k} ({i}, {j}) misses {c}");
                        }
                    }
                    listed += held.len();
                }
            }
        }
        let tested = (SKY_MAP_DIRECTIONS * map.size * map.size) as usize * spheres.len();
        assert!(hits > 1000, "{hits}");
        assert!(listed * 3 < tested, "{listed} of {tested}");
    }
}
