//! Particle generators for common shapes. Deterministic for a given seed.

use bevy::math::Vec3;

use crate::{particle::Particle, Particles};

/// A small deterministic generator (SplitMix64), so shapes are reproducible without a `rand` dependency.
#[derive(Clone, Debug)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform in the unit ball.
    pub fn in_unit_ball(&mut self) -> Vec3 {
        loop {
            let p = Vec3::new(self.next_f32(), self.next_f32(), self.next_f32()) * 2.0 - 1.0;
            if p.length_squared() <= 1.0 {
                return p;
            }
        }
    }
}

/// `count` particles of radius `particle_radius` filling a ball of radius `radius` (metres),
/// density 1.
pub fn sphere(radius: f32, particle_radius: f32, count: usize, seed: u64) -> Particles {
    let mut rng = SplitMix64::new(seed);
    let inner = (radius - particle_radius).max(0.0);
    Particles::new(
        (0..count)
            .map(|_| Particle { position: rng.in_unit_ball() * inner, radius: particle_radius, density: 1.0 })
            .collect(),
    )
}

/// `count` particles filling an axis-aligned box of full `extents` (metres), density 1.
pub fn cuboid(extents: Vec3, particle_radius: f32, count: usize, seed: u64) -> Particles {
    let mut rng = SplitMix64::new(seed);
    let half = (extents * 0.5 - particle_radius).max(Vec3::ZERO);
    Particles::new(
        (0..count)
            .map(|_| {
                let u = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0 - 1.0;
                Particle { position: u * half, radius: particle_radius, density: 1.0 }
            })
            .collect(),
    )
}

/// A cumulus: a flat-bottomed heap of overlapping puffs, about `size` metres across, made of
/// `count` particles. Puffs are larger and denser at the core and thin out towards the edges.
pub fn cumulus(size: f32, count: usize, seed: u64) -> Particles {
    let mut rng = SplitMix64::new(seed);
    // A few large lobes give the cauliflower silhouette; particles cluster around them.
    let lobes: Vec<(Vec3, f32)> = (0..7)
        .map(|i| {
            let a = i as f32 / 7.0 * std::f32::consts::TAU + rng.next_f32();
            let r = if i == 0 { 0.0 } else { 0.28 + 0.12 * rng.next_f32() };
            let centre = Vec3::new(a.cos() * r, 0.1 + 0.25 * rng.next_f32(), a.sin() * r * 0.7);
            (centre * size, size * (0.22 + 0.12 * rng.next_f32()))
        })
        .collect();
    let particles = (0..count)
        .map(|i| {
            let (centre, lobe_radius) = lobes[i % lobes.len()];
            let mut p = centre + rng.in_unit_ball() * lobe_radius;
            p.y = p.y.max(-0.05 * size); // flat base, as condensation starts at one altitude
            let core = 1.0 - ((p - centre).length() / lobe_radius).min(1.0);
            Particle {
                position: p,
                radius: size * (0.07 + 0.06 * core),
                density: 0.5 + 0.5 * core,
            }
        })
        .collect();
    Particles::new(particles)
}
