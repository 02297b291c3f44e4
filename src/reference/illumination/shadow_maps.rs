//! Section 10: the cloud shadow maps and the sky map, the optical depth of every cloud along a
//! light or towards the sky.

use bevy::math::DVec3;
use rayon::prelude::*;

use super::illuminate::CloudIllumination;
use crate::reference::composite::CloudPlacement;
use crate::shadow_maps::{SKY_MAP_DIRECTIONS, ShadowMapPlacement, sky_direction_among};

/// The cloud shadow map `map` of light `light` (contract section 10): at each texel, the sum over
/// `clouds` (each with its placement) of [`LightVolume::cast_depth_at`](super::LightVolume::cast_depth_at) of its own volume of that
/// light at the texel's column point past every cloud. Index `i + size j`.
pub fn cloud_shadow_map(
    clouds: &[(&CloudIllumination, CloudPlacement)],
    light: usize,
    map: &ShadowMapPlacement,
) -> Vec<f64> {
    over_texels(map, |world| {
        clouds
            .iter()
            .filter_map(|(c, p)| Some(c.own_lights.get(light)?.cast_depth_at(p.local_point(world))))
            .sum()
    })
}

/// `value` at each texel's point of `map` (its column's end), index `i + size j`.
fn over_texels(map: &ShadowMapPlacement, value: impl Fn(DVec3) -> f64 + Sync) -> Vec<f64> {
    let n = map.size;
    (0..n * n)
        .into_par_iter()
        .map(|t| value(map.texel_point(t % n, t / n).as_dvec3()))
        .collect()
}

/// The optical depth at world point `x` in the shadow map `map` holding `values`: bilinear
/// between texel centres, zero outside the map and before `w_begin` along the light.
pub fn shadow_map_depth_at(map: &ShadowMapPlacement, values: &[f64], x: DVec3) -> f64 {
    let [u, v, d] = [map.u, map.v, map.d].map(|a| a.as_dvec3());
    if x.dot(d) < map.w_begin as f64 {
        return 0.0;
    }
    let corner = map.corner.as_dvec2();
    let g = (bevy::math::DVec2::new(x.dot(u), x.dot(v)) - corner) / map.texel as f64 - 0.5;
    let n = map.size as i64;
    let texel = |i: i64, j: i64| {
        if (0..n).contains(&i) && (0..n).contains(&j) {
            values[(i + n * j) as usize]
        } else {
            0.0
        }
    };
    let (i, j) = (g.x.floor() as i64, g.y.floor() as i64);
    let f = g - g.floor();
    let bottom = texel(i, j) * (1.0 - f.x) + texel(i + 1, j) * f.x;
    let top = texel(i, j + 1) * (1.0 - f.x) + texel(i + 1, j + 1) * f.x;
    bottom * (1.0 - f.y) + top * f.y
}

/// The sky map `map` ([`ShadowMapPlacement::sky`], contract section 10): at each texel's point
/// on the plane, the fraction of the sky's irradiance on an upward-facing surface that `clouds`
/// (each with its placement) take away, `1 - (1/K) sum_k exp(-tau_k)` over the
/// [`SKY_MAP_DIRECTIONS`] cosine-weighted directions `k`
/// ([`sky_direction`](crate::shadow_maps::sky_direction)), `tau_k` the optical
/// depth of every cloud along it ([`grid_optical_depth`]). Index `i + size j`; read it with
/// [`shadow_map_depth_at`].
pub fn sky_occlusion_map(
    clouds: &[(&CloudIllumination, CloudPlacement)],
    map: &ShadowMapPlacement,
) -> Vec<f64> {
    over_texels(map, |x| sky_occlusion_at(clouds, x, SKY_MAP_DIRECTIONS))
}

/// The fraction of the sky's irradiance on an upward-facing surface at world point `x` that
/// `clouds` take away, over `directions` cosine-weighted directions
/// ([`sky_direction_among`]); the sky map's texels take [`SKY_MAP_DIRECTIONS`].
pub fn sky_occlusion_at(
    clouds: &[(&CloudIllumination, CloudPlacement)],
    x: DVec3,
    directions: u32,
) -> f64 {
    let visible: f64 = (0..directions)
        .map(|k| {
            let up = sky_direction_among(k, directions).as_dvec3();
            let tau: f64 = clouds
                .iter()
                .map(|(c, p)| grid_optical_depth(c, p, x, up))
                .sum();
            (-tau).exp()
        })
        .sum();
    1.0 - visible / directions as f64
}

/// The optical depth of `cloud` (placed by `placement`) along the world ray from `origin` along
/// the unit `direction`: its scattering grid's density marched from where the ray enters the
/// cube around its voxels' centres, widened by half a voxel (where the zero-border density
/// ends), to where it leaves, in `ceil(chord / h - 0.001)` equal steps sampled at their middles.
/// (The sky map takes the scattering grid, not the finer one the lights are shaded through: what
/// a surface sees of the sky averages the clouds over many directions, and the fine grid
/// changed the occlusion by less than the directions' own error, at 3× the steps.)
pub fn grid_optical_depth(
    cloud: &CloudIllumination,
    placement: &CloudPlacement,
    origin: DVec3,
    direction: DVec3,
) -> f64 {
    let grid = &cloud.grid;
    let o = placement.local_point(origin);
    let d = placement.local_direction(direction);
    let lo = grid.origin() - DVec3::splat(0.5 * grid.h);
    let hi = lo + DVec3::splat((grid.n + 1) as f64 * grid.h);
    let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
    for a in 0..3 {
        if d[a].abs() < 1e-12 {
            if o[a] < lo[a] || o[a] > hi[a] {
                return 0.0;
            }
            continue;
        }
        let (near, far) = ((lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]);
        t0 = t0.max(near.min(far));
        t1 = t1.min(near.max(far));
    }
    if t1 <= t0 {
        return 0.0;
    }
    // A chord a rounding error over a whole number of voxels takes that number of steps.
    let steps = ((t1 - t0) / grid.h - 1e-3).ceil().max(1.0);
    let dt = (t1 - t0) / steps;
    let sum: f64 = (0..steps as usize)
        .map(|i| grid.sample(o + d * (t0 + (i as f64 + 0.5) * dt)))
        .sum();
    cloud.k_local * sum * dt
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reference::illumination::illuminate;
    use bevy::math::DQuat;

    use crate::particle::Medium;
    use crate::reference::illumination::test_support::*;
    use crate::settings::CloudQualitySettings;

    /// Through a grid of uniform density the march is exact: the zero-border density ramps to 0
    /// half a voxel beyond the outer centres, so a chord along an axis holds `K rho n h`; and
    /// the sky map sees the cloud most under it and not at all far beside it.
    #[test]
    fn the_sky_map_marches_the_fine_density() {
        let settings = CloudQualitySettings {
            volume_resolution: 8,
            light_supersampling: 1,
            ..Default::default()
        };
        let medium = Medium::default();
        let particles = random_cloud(40, 3);
        let mut ill = illuminate(&particles, &medium, 1.0, &[], &settings).unwrap();
        ill.grid.rho.iter_mut().for_each(|r| *r = 0.75);
        let grid = ill.grid.clone();
        let placement = CloudPlacement {
            translation: DVec3::new(1.0, 10.0, -2.0),
            rotation: DQuat::from_rotation_y(0.3),
            scale: 1.0,
        };
        let below = placement.world_point(grid.centre) - DVec3::Y * 8.0;
        let tau = grid_optical_depth(&ill, &placement, below, DVec3::Y);
        let exact = ill.k_local * 0.75 * grid.n as f64 * grid.h;
        assert!((tau - exact).abs() < 1e-9 * exact, "{tau} against {exact}");
        assert_eq!(
            grid_optical_depth(&ill, &placement, below, DVec3::NEG_Y),
            0.0
        );

        let world = placement.world_point(grid.centre).as_vec3();
        let radius = (0.5 * 3f64.sqrt() * grid.side) as f32;
        let map = ShadowMapPlacement::sky(&[(world, radius)], 2.0, 24, 0).unwrap();
        let occlusion = sky_occlusion_map(&[(&ill, placement)], &map);
        let at = |x: DVec3| shadow_map_depth_at(&map, &occlusion, x);
        let under = at(DVec3::new(world.x as f64, 2.0, world.z as f64));
        let beside = at(DVec3::new(world.x as f64 + 16.0, 2.0, world.z as f64));
        assert!(occlusion.iter().all(|o| (0.0..1.0).contains(o)));
        assert!(under > 0.05 && beside < 0.5 * under, "{under} {beside}");
        assert_eq!(at(DVec3::new(1e3, 2.0, 0.0)), 0.0, "nothing beyond the map");
    }
}
