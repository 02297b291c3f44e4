//! The ground under a cloud as its multiple scattering sees it (docs/illumination.md §4, "The
//! ground"): the CPU mirror of `render/ground.rs` and `ground.wgsl`, and of the sweep's lookup.

use std::f64::consts::PI;

use bevy::math::{Affine3A, DVec3, Vec3};

use super::composite::CloudPlacement;
use super::illumination::{DensityGrid, LightVolume};
use crate::ground::{
    CloudGround, GROUND_MAP_SIDE, GroundMapPlacement, ground_point_behind, sample_ground_map,
};

/// A cloud's ground map: where it lies and, per texel, the ground's radiance (linear RGB, the
/// units of `E` per steradian).
#[derive(Clone, Debug)]
pub struct GroundLight {
    placement: CloudPlacement,
    height: f64,
    map: GroundMapPlacement,
    /// Texel `i + side j`.
    pub radiance: Vec<DVec3>,
}

impl GroundLight {
    /// The map of the cloud `placement` puts with its scattering grid `grid` and its light
    /// volumes `lights` (other clouds' shadows included) over `ground`, under the sky `sky`:
    /// at each texel's centre `x`, `R / pi (sum_l E_l max(0, -d_l . y) T_l(x) + pi L_sky)`, `T_l`
    /// the light volume's transmittance there (clamped to its edge voxels).
    pub fn new(
        ground: &CloudGround,
        placement: CloudPlacement,
        grid: &DensityGrid,
        lights: &[(LightVolume, DVec3)],
        sky: DVec3,
    ) -> Self {
        let to_world = Affine3A::from_scale_rotation_translation(
            Vec3::splat(placement.scale as f32),
            placement.rotation.as_quat(),
            placement.translation.as_vec3(),
        );
        let map = GroundMapPlacement::new(
            to_world,
            grid.origin().as_vec3(),
            grid.side as f32,
            ground.height,
        );
        let height = ground.height as f64;
        let reflectance = ground.reflectance.as_dvec3();
        let side = GROUND_MAP_SIDE;
        let radiance = (0..side * side)
            .map(|t| {
                let xz = map.texel_centre(t % side, t / side).as_dvec2();
                let local = placement.local_point(DVec3::new(xz.x, height, xz.y));
                let beams: DVec3 = lights
                    .iter()
                    .map(|(volume, irradiance)| {
                        let cosine = -(placement.rotation * volume.basis[2]).y;
                        *irradiance * cosine.max(0.0) * volume.transmittance_at(local)
                    })
                    .sum();
                reflectance / PI * (beams + PI * sky)
            })
            .collect();
        Self {
            placement,
            height,
            map,
            radiance,
        }
    }

    /// The radiance entering `grid` on a lattice line whose first voxel is `v`, travelling
    /// along the local unit direction `w`, `half_step` before that voxel's centre: the ground's
    /// (bilinear in the map) where the line climbs in the world, else `None` (the sky's).
    pub fn entering(
        &self,
        grid: &DensityGrid,
        v: [usize; 3],
        w: DVec3,
        half_step: f64,
    ) -> Option<DVec3> {
        let travel = self.placement.rotation * w;
        if travel.y <= 0.0 {
            return None;
        }
        let p = grid.voxel_centre(v[0], v[1], v[2]) - w * half_step;
        let entry = self.placement.world_point(p);
        let from = ground_point_behind(entry.as_vec3(), travel.as_vec3(), self.height as f32);
        Some(sample_ground_map(&self.map, &self.radiance, from))
    }
}

#[cfg(test)]
mod tests {
    use bevy::math::{DQuat, Vec3};

    use super::*;
    use crate::reference::illumination::{PlacedCloud, illuminate_clouds_over_ground};
    use crate::{CloudQualitySettings, LightSample, Medium, Particle};

    fn cloud(seed: u64) -> Vec<Particle> {
        let mut rng = crate::math::SplitMix64::mixed(seed);
        (0..30)
            .map(|_| {
                let mut r = || rng.next_f32();
                let position = Vec3::new(r() * 2.0 - 1.0, r() - 0.5, r() * 2.0 - 1.0);
                Particle {
                    position,
                    radius: 0.2 + 0.5 * r(),
                    density: 0.5 + r(),
                }
            })
            .collect()
    }

    fn placed(particles: &[Particle], albedo: f32, height: f64) -> PlacedCloud<'_> {
        PlacedCloud {
            particles,
            medium: Medium {
                extinction: 3.0,
                albedo,
                anisotropy: 0.0,
            },
            placement: CloudPlacement {
                translation: DVec3::new(0.5, height, -0.3),
                rotation: DQuat::from_rotation_y(0.4),
                scale: 1.0,
            },
            settings: CloudQualitySettings {
                volume_resolution: 12,
                scatter_iterations: 40,
                ..Default::default()
            },
        }
    }

    /// The furnace with a ground: at albedo 1, a white ground lit by the uniform sky alone
    /// reflects the sky's radiance, so the cloud still holds it everywhere; a black ground
    /// darkens the cloud's underside more than its top.
    #[test]
    fn a_white_ground_under_a_uniform_sky_is_the_sky() {
        let particles = cloud(5);
        let sky = DVec3::new(0.2, 0.3, 0.5);
        let white = CloudGround {
            height: 0.0,
            reflectance: Vec3::ONE,
        };
        let clouds = [placed(&particles, 1.0, 2.0)];
        let lit = illuminate_clouds_over_ground(&clouds, &[], sky, Some(&white));
        let ill = lit[0].as_ref().unwrap();
        for (idx, rho) in ill.grid.rho.iter().enumerate() {
            if *rho >= 0.5 * ill.grid.max() {
                let s = ill.multiple.total[idx];
                assert!(((s - sky) / sky).abs().max_element() < 0.01, "{s}");
            }
        }
        let black = CloudGround {
            reflectance: Vec3::ZERO,
            ..white
        };
        let dark = illuminate_clouds_over_ground(&clouds, &[], sky, Some(&black));
        let dark = dark[0].as_ref().unwrap();
        let n = dark.grid.n;
        let layer = |j: usize| -> f64 {
            let v = (0..n * n).map(|t| dark.multiple.total[dark.grid.index(t % n, j, t / n)].x);
            v.sum::<f64>() / (n * n) as f64
        };
        let (bottom, top) = (layer(1), layer(n - 2));
        assert!(
            bottom < 0.9 * top && top < sky.x,
            "bottom {bottom}, top {top}"
        );
    }

    /// The map holds the sun's light reflected off the ground, `R / pi E cos`, away from the
    /// cloud, and less in the cloud's shadow (straight below it, the sun overhead).
    #[test]
    fn the_map_holds_the_cloud_s_shadow() {
        let particles = cloud(9);
        let sun = LightSample {
            direction: Vec3::NEG_Y,
            irradiance: Vec3::new(3.0, 2.0, 1.0),
        };
        let ground = CloudGround {
            height: -1.0,
            reflectance: Vec3::splat(0.5),
        };
        let clouds = [placed(&particles, 0.9, 1.5)];
        let ill = illuminate_clouds_over_ground(&clouds, &[sun], DVec3::ZERO, Some(&ground));
        let ill = ill[0].as_ref().unwrap();
        let map = GroundLight::new(
            &ground,
            clouds[0].placement,
            &ill.grid,
            &ill.lights,
            DVec3::ZERO,
        );
        let open = 0.5 / PI * DVec3::new(3.0, 2.0, 1.0);
        let corner = map.radiance[0];
        assert!((corner - open).abs().max_element() < 1e-9, "{corner}");
        let below = sample_ground_map(&map.map, &map.radiance, bevy::math::Vec2::new(0.5, -0.3));
        assert!(
            below.x < 0.5 * open.x,
            "below the cloud {below}, in the open {open}"
        );
    }
}
