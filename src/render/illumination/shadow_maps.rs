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

use crate::render::{
    core::gpu::Batch,
    core::gpu::{WorkList, uniform_bytes},
    core::key_of,
    extract::{ExtractedCloud, ExtractedCloudLights},
    illumination::cast::light_caster,
    plan::CloudIllumination,
    plan::casters::{CastStart, CastTarget, CastWork, Caster, add_cast},
    plan::pools::{PoolId, VolumePools},
    plan::volumes::CloudVolumes,
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
            let span = caster.span_along(map.v);
            Some((v.slot.pool, caster.on(&Affine3A::IDENTITY), span))
        });
        let placed: Vec<_> = placed.collect();
        match placed.first() {
            // Per band, the first pool's dispatch writes it from nothing, the others add to it.
            Some(&(own, ..)) => {
                for (band, casters) in map_bands(map, &placed) {
                    add_cast(&mut work, band, CastStart::Zero, casters, own);
                }
            }
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

/// Rows of a shadow map per cast target (band).
pub const BAND_ROWS: u32 = 16;

/// `map` cut into bands of [`BAND_ROWS`] rows, each a cast target with the casters whose
/// columns may cross its texels: those whose span along the map's `v` axis (the third member,
/// metres) meets the band's, a row to spare either side. So a map over many clouds costs its
/// texels times the clouds across each band, not times every cloud.
pub(crate) fn map_bands<P: Copy>(
    map: &ShadowMapPlacement,
    casters: &[(P, Caster, (f32, f32))],
) -> Vec<(CastTarget, Vec<(P, Caster)>)> {
    let n = map.size;
    // Texel row j's centre lies at v = corner.y + (j + 1/2) texel.
    let row = |v: f32| (v - map.corner.y) / map.texel - 0.5;
    (0..n.div_ceil(BAND_ROWS))
        .map(|b| {
            let rows = (b * BAND_ROWS)..(n.min((b + 1) * BAND_ROWS));
            let (first_row, last_row) = (rows.start as f32 - 1.0, rows.end as f32);
            let crossing = casters
                .iter()
                .filter(|(.., (lo, hi))| row(*hi) >= first_row && row(*lo) <= last_row)
                .map(|&(pool, caster, _)| (pool, caster))
                .collect();
            (band_target(map, rows), crossing)
        })
        .collect()
}

/// The texels of rows `rows` of `map`, in world space: each at its column's end, past every
/// cloud.
fn band_target(map: &ShadowMapPlacement, rows: std::ops::Range<u32>) -> CastTarget {
    let step = |axis: Vec3| (axis * map.texel).to_array();
    CastTarget {
        origin: map.texel_point(0, rows.start).to_array(),
        first: map.first + rows.start * map.size,
        step_x: step(map.u),
        size_x: map.size,
        step_y: step(map.v),
        size_y: rows.len() as u32,
        step_z: [0.0; 3],
        size_z: 1,
        ..default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn caster(first: u32) -> Caster {
        Caster { first, ..default() }
    }

    #[test]
    fn a_maps_bands_tile_it_and_take_the_casters_that_cross_them() {
        let map = ShadowMapPlacement {
            u: Vec3::X,
            v: Vec3::Z,
            d: Vec3::NEG_Y,
            texel: 0.5,
            corner: Vec2::new(-10.0, 100.0),
            size: 40,
            first: 1000,
            ..default()
        };
        // Rows of texel centres: v = 100.25 + 0.5 j. One caster over rows 4–12, one over 30–35.
        let casters = [
            (0u8, caster(1), (102.3, 106.2)),
            (1u8, caster(2), (115.1, 117.6)),
        ];
        let bands = map_bands(&map, &casters);
        let rows: Vec<u32> = bands.iter().map(|(t, _)| t.size_y).collect();
        assert_eq!(rows, [16, 16, 8]);
        let mut next = map.first;
        for (b, (target, _)) in bands.iter().enumerate() {
            assert_eq!(target.first, next, "band {b} follows the one before");
            assert_eq!((target.size_x, target.size_z), (40, 1));
            let origin = map.texel_point(0, b as u32 * 16);
            assert!(Vec3::from(target.origin).distance(origin) < 1e-4);
            next += target.size_x * target.size_y;
        }
        assert_eq!(next, map.first + 40 * 40, "the bands cover the map");
        let firsts = |b: usize| bands[b].1.iter().map(|(_, c)| c.first).collect::<Vec<_>>();
        assert_eq!(firsts(0), [1]);
        assert_eq!(firsts(1), [2], "rows 29.7-34.7 lie in band 1 (16-31)");
        assert_eq!(firsts(2), [2], "and in band 2 (32-39)");
        // A caster beside the map (or one no band meets) casts on nothing.
        assert!(
            map_bands(&map, &[(0u8, caster(3), (150.0, 151.0))])
                .iter()
                .all(|(_, c)| c.is_empty())
        );
    }
}
