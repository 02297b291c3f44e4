//! Fixtures shared by the stages' tests.

use bevy::math::DVec3;

use super::shade::ShadeInputs;
use super::voxelize::DensityGrid;
use crate::particle::Particle;
use bevy::math::Vec3;

pub(super) fn particle(x: f32, y: f32, z: f32, radius: f32, density: f32) -> Particle {
    Particle {
        position: Vec3::new(x, y, z),
        radius,
        density,
    }
}

/// A uniform grid `rho = value` of `n³` voxels of size 1 centred at the origin.
pub(super) fn uniform_grid(n: usize, value: f64) -> DensityGrid {
    DensityGrid {
        n,
        centre: DVec3::ZERO,
        side: n as f64,
        h: 1.0,
        rho: vec![value; n * n * n],
    }
}

pub(super) fn random_cloud(count: usize, seed: u64) -> Vec<Particle> {
    let mut rng = crate::math::SplitMix64::mixed(seed);
    (0..count)
        .map(|_| {
            let mut r = || rng.next_f32();
            particle(
                r() * 2.0 - 1.0,
                r() - 0.5,
                r() * 2.0 - 1.0,
                0.2 + 0.5 * r(),
                0.5 + r(),
            )
        })
        .collect()
}

pub(super) fn max_component(values: &[DVec3]) -> f64 {
    values.iter().map(|v| v.max_element()).fold(0.0, f64::max)
}

pub(super) fn inputs(k_local: f64, albedo: f64, forward: f64, resolution: usize) -> ShadeInputs {
    ShadeInputs {
        k_local,
        albedo,
        forward_scattering: forward,
        resolution,
    }
}
