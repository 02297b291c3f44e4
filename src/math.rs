//! The math that the real-time renderer, the CPU reference and the path tracer share: the density
//! kernel and its chord integral (`docs/physics.md`), the light-aligned basis, and one small random
//! number generator. It depends on nothing else in the crate, so `render/` never imports its oracle.

use bevy::math::{DVec3, Vec3};

/// Integral of the kernel `k(|x|)` over the unit ball: `4π ∫ (1-u²)² u² du = 32π/105`.
pub const KERNEL_VOLUME: f64 = 32.0 * std::f64::consts::PI / 105.0;

/// The density kernel `k(u) = (1 - u²)²` for `u < 1`, `0` otherwise, of the squared argument `u²`.
#[inline]
pub fn kernel_u2(u2: f64) -> f64 {
    if u2 < 1.0 {
        let a = 1.0 - u2;
        a * a
    } else {
        0.0
    }
}

/// Optical depth of one particle along a line passing at distance `b` (metres) from its centre:
/// the chord integral `K * eta * r * 16/15 * (1 - b²/r²)^(5/2)` for `b < r`, `0` outside.
#[inline]
pub fn particle_optical_depth(extinction: f64, density: f64, radius: f64, b: f64) -> f64 {
    let q = 1.0 - (b * b) / (radius * radius);
    if q <= 0.0 {
        return 0.0;
    }
    extinction * density * radius * (16.0 / 15.0) * q * q * q.sqrt()
}

/// Largest radius, in voxels of its level, of a particle deposited on a density level: a larger
/// one goes to a coarser level, so no particle visits more than `(2·32 + 1)³` voxels
/// (docs/illumination.md §1, "Density levels"). Each level's upsampling blurs by about a third of
/// a coarse voxel, which the narrowed kernel ([`level_kernel_radius`]) makes up for at the
/// particle's centre. A particle on a level spans 16 to 32 of its voxels per radius whatever the
/// fine grid, so this also bounds how finely a wide particle is resolved: at 16 (8 to 16) the
/// error of one wide particle against the path tracer rose by up to 0.001 relative RMSE as the
/// fine grid grew past 256 and moved the particle to a coarser level (docs/performance.md).
pub const MAX_RADIUS_IN_LEVEL_VOXELS: f64 = 32.0;

/// Most density levels of a fine grid (enough for `m = 256`: 256, 128, 64, 32, 16, 8, 4).
pub const MAX_DENSITY_LEVELS: usize = 8;

/// Voxels per side of the density levels of a fine grid of `m` voxels per side: `m`, then each
/// level half the one before it (rounded up) while that one has at least 8 voxels per side. All
/// share the fine grid's origin; level `l` has voxels `2^l` times as wide.
pub fn density_level_sizes(m: u32) -> Vec<u32> {
    let mut sizes = vec![m];
    while let Some(&last) = sizes.last()
        && last >= 8
        && sizes.len() < MAX_DENSITY_LEVELS
    {
        sizes.push(last.div_ceil(2));
    }
    sizes
}

/// The level a particle of radius `r_over_h` fine voxels is deposited on, of `levels` levels: the
/// finest whose voxels it spans at most [`MAX_RADIUS_IN_LEVEL_VOXELS`] of, else the coarsest.
pub fn density_level(r_over_h: f64, levels: usize) -> usize {
    let mut level = 0;
    while level + 1 < levels && r_over_h > MAX_RADIUS_IN_LEVEL_VOXELS * (1u32 << level) as f64 {
        level += 1;
    }
    level
}

/// The kernel radius with which a particle of radius `r` is deposited on a density level of voxel
/// size `h_level` (fine voxel size `h`): narrower than `r` by what the upsampling to the fine grid
/// spreads (docs/illumination.md §1). The upsampling blurs by a per-axis variance
/// `s² = (h_level² - h²) / 4`, which lowers the particle's central column optical depth (its
/// chord integral, `∝ (1 - b²/r²)^(5/2)`) by `5 s² / r²`; a kernel of radius `r'` raises it by
/// `r² / r'² - 1`. So `r'² = r² - 5 s²` ([`LEVEL_KERNEL_NARROWING`]). The particle's mass is
/// unchanged.
pub fn level_kernel_radius(r: f64, h: f64, h_level: f64) -> f64 {
    (r * r - LEVEL_KERNEL_NARROWING * (h_level * h_level - h * h))
        .max(0.0)
        .sqrt()
}

/// `r'² = r² - LEVEL_KERNEL_NARROWING (h_level² - h²)` in [`level_kernel_radius`]: `5 / 4`.
pub const LEVEL_KERNEL_NARROWING: f64 = 1.25;

/// Orthonormal basis `[u, v, w]` with `w` the given unit vector (Duff et al. 2017, branchless, with
/// `sign(0) = +1` so that `w.z = ±0` is handled like the WGSL `select`). The light-aligned volumes
/// of the renderer and of the reference are laid out along it.
pub fn light_basis(w: DVec3) -> [DVec3; 3] {
    let sg = if w.z >= 0.0 { 1.0 } else { -1.0 };
    let a = -1.0 / (sg + w.z);
    let b = w.x * w.y * a;
    let u = DVec3::new(1.0 + sg * w.x * w.x * a, sg * b, -sg * w.x);
    let v = DVec3::new(b, sg + w.y * w.y * a, -w.y);
    [u, v, w]
}

/// `1 / 4π`: the isotropic phase function, per steradian.
pub const INV_4PI: f64 = 0.25 * std::f64::consts::FRAC_1_PI;

/// The Henyey–Greenstein phase function (per steradian) of anisotropy `g` in `(-1, 1)`, at the
/// cosine of the angle between the light's travel direction and the scattered direction:
/// `(1 - g²) / (4π (1 + g² - 2 g cos)^(3/2))`. Exactly [`INV_4PI`] for `g = 0`.
pub fn henyey_greenstein(g: f64, cos_theta: f64) -> f64 {
    if g == 0.0 {
        return INV_4PI;
    }
    // >= (1 - |g|)² > 0 for |g| < 1.
    let d = 1.0 + g * g - 2.0 * g * cos_theta;
    (1.0 - g * g) * INV_4PI / (d * d.sqrt())
}

/// The SplitMix64 output function (Steele, Lea & Flood 2014): a bijective 64-bit mixer.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// SplitMix64: a tiny, fast generator with a 64-bit state, good enough for Monte Carlo and for
/// shapes, reproducible without a `rand` dependency, and trivially seeded per pixel sample (which
/// makes renders independent of the thread schedule).
#[derive(Clone, Debug)]
pub struct SplitMix64 {
    state: u64,
}

impl SplitMix64 {
    const GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;

    /// A generator whose sequence is fixed by `seed` (any value, 0 included), used as the state.
    pub fn new(seed: u64) -> Self {
        Self { state: seed }
    }

    /// A generator whose state is `seed` mixed first, so that nearby seeds give unrelated streams.
    pub fn mixed(seed: u64) -> Self {
        Self::new(mix64(seed))
    }

    /// The generator of sample `sample` of pixel `pixel` in a render seeded with `seed`.
    /// Nested mixing (rather than e.g. `seed + pixel`) keeps nearby streams uncorrelated.
    pub fn for_sample(seed: u64, pixel: u64, sample: u64) -> Self {
        Self::mixed(
            mix64(mix64(seed ^ 0x5851_F42D_4C95_7F2D).wrapping_add(pixel)).wrapping_add(sample),
        )
    }

    /// The next uniformly distributed 64-bit value.
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(Self::GAMMA);
        mix64(self.state)
    }

    /// Uniform in `[0, 1)` with 24 random bits.
    #[inline]
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform in `[0, 1)` with 53 random bits.
    #[inline]
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Exponential with rate 1 (mean 1): `-ln(1 - u)`, finite since `1 - u > 0`.
    #[inline]
    pub fn exponential(&mut self) -> f64 {
        -(1.0 - self.next_f64()).ln()
    }

    /// Uniform direction on the unit sphere (pdf `1/4π` per steradian).
    pub fn unit_sphere(&mut self) -> DVec3 {
        let z = 1.0 - 2.0 * self.next_f64();
        let phi = std::f64::consts::TAU * self.next_f64();
        let s = (1.0 - z * z).max(0.0).sqrt();
        DVec3::new(s * phi.cos(), s * phi.sin(), z)
    }

    /// A direction scattered from `forward` (unit) with the Henyey–Greenstein phase function of
    /// anisotropy `g` in `(-1, 1)` as its pdf (inverting its cumulative distribution in
    /// `cos theta`). For `|g| < 1e-6` it draws exactly [`Self::unit_sphere`]'s directions: the
    /// inversion loses precision there, and the phase function differs from isotropic by less
    /// than `3e-6` of itself.
    pub fn henyey_greenstein(&mut self, g: f64, forward: DVec3) -> DVec3 {
        if g.abs() < 1e-6 {
            return self.unit_sphere();
        }
        let s = (1.0 - g * g) / (1.0 - g + 2.0 * g * self.next_f64());
        let cos = ((1.0 + g * g - s * s) / (2.0 * g)).clamp(-1.0, 1.0);
        let sin = (1.0 - cos * cos).max(0.0).sqrt();
        let phi = std::f64::consts::TAU * self.next_f64();
        let [u, v, w] = light_basis(forward);
        w * cos + (u * phi.cos() + v * phi.sin()) * sin
    }

    /// Uniform in the unit ball (rejection from the cube).
    pub fn in_unit_ball(&mut self) -> Vec3 {
        loop {
            let p = Vec3::new(self.next_f32(), self.next_f32(), self.next_f32()) * 2.0 - 1.0;
            if p.length_squared() <= 1.0 {
                return p;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn density_levels_halve_down_to_a_few_voxels() {
        assert_eq!(density_level_sizes(144), [144, 72, 36, 18, 9, 5]);
        assert_eq!(density_level_sizes(256), [256, 128, 64, 32, 16, 8, 4]);
        assert_eq!(density_level_sizes(7), [7]);
        assert_eq!(density_level_sizes(8), [8, 4]);
        for m in 1..=256 {
            assert!(density_level_sizes(m).len() <= MAX_DENSITY_LEVELS, "{m}");
        }
    }

    #[test]
    fn particles_go_to_the_finest_level_they_span_at_most_32_voxels_of() {
        let cases = [
            (0.5, 0),
            (32.0, 0),
            (32.01, 1),
            (64.0, 1),
            (64.01, 2),
            (256.0, 3),
            (1e9, 5),
        ];
        for (r_over_h, level) in cases {
            assert_eq!(density_level(r_over_h, 6), level, "r/h = {r_over_h}");
        }
        assert_eq!(
            density_level(100.0, 1),
            0,
            "one level: always the fine grid"
        );
    }

    /// The phase function integrates to 1 over the sphere and has mean cosine `g`; `g = 0` is
    /// exactly isotropic.
    #[test]
    fn henyey_greenstein_is_normalised_with_mean_cosine_g() {
        for g in [-0.9, -0.3, 0.0, 0.5, 0.7, 0.95] {
            // Integral over the sphere: 2π ∫ p(μ) dμ, μ in [-1, 1], midpoint rule in μ.
            let n = 200_000;
            let (mut total, mut mean_cos) = (0.0, 0.0);
            for i in 0..n {
                let mu = -1.0 + (i as f64 + 0.5) * 2.0 / n as f64;
                let w = std::f64::consts::TAU * henyey_greenstein(g, mu) * 2.0 / n as f64;
                total += w;
                mean_cos += w * mu;
            }
            assert!((total - 1.0).abs() < 1e-4, "g {g}: integral {total}");
            assert!((mean_cos - g).abs() < 1e-4, "g {g}: mean cosine {mean_cos}");
        }
        for mu in [-1.0, -0.3, 0.0, 0.9, 1.0] {
            assert_eq!(henyey_greenstein(0.0, mu), INV_4PI);
        }
    }

    /// Sampled directions follow the phase function: their mean cosine is `g` and a histogram
    /// of `cos theta` matches its density; `g = 0` draws the isotropic sampler's directions.
    #[test]
    fn henyey_greenstein_sampling_follows_the_phase_function() {
        let forward = DVec3::new(0.3, -0.5, 0.8).normalize();
        let n = 400_000;
        for g in [-0.6, 0.3, 0.85] {
            let mut rng = SplitMix64::new(11);
            let mut bins = [0usize; 10];
            let mut mean = 0.0;
            for _ in 0..n {
                let d = rng.henyey_greenstein(g, forward);
                assert!((d.length() - 1.0).abs() < 1e-12);
                let mu = d.dot(forward);
                mean += mu / n as f64;
                bins[(((mu + 1.0) * 5.0) as usize).min(9)] += 1;
            }
            assert!((mean - g).abs() < 0.005, "g {g}: mean cosine {mean}");
            for (b, &count) in bins.iter().enumerate() {
                // Expected fraction: 2π ∫ p over the bin (midpoint rule).
                let lo = -1.0 + b as f64 * 0.2;
                let expected: f64 = (0..1000)
                    .map(|i| {
                        let mu = lo + (i as f64 + 0.5) * 0.2e-3;
                        std::f64::consts::TAU * henyey_greenstein(g, mu) * 0.2e-3
                    })
                    .sum();
                let got = count as f64 / n as f64;
                let sigma = (expected / n as f64).sqrt();
                assert!(
                    (got - expected).abs() < 5.0 * sigma + 2e-3 * expected,
                    "g {g}, bin {b}: {got} against {expected}"
                );
            }
        }
        let (mut a, mut b) = (SplitMix64::new(3), SplitMix64::new(3));
        for _ in 0..100 {
            assert_eq!(a.henyey_greenstein(0.0, forward), b.unit_sphere());
        }
    }

    #[test]
    fn light_basis_is_orthonormal_for_axes_and_random_directions() {
        let mut dirs = vec![
            DVec3::X,
            DVec3::NEG_X,
            DVec3::Y,
            DVec3::NEG_Y,
            DVec3::Z,
            DVec3::NEG_Z,
            DVec3::new(1e-9, -1e-9, -1.0).normalize(),
        ];
        let mut rng = SplitMix64::new(7);
        for _ in 0..100 {
            dirs.push(rng.unit_sphere());
        }
        for w in dirs {
            let [u, v, w2] = light_basis(w);
            assert_eq!(w2, w);
            for (a, b) in [(u, v), (u, w), (v, w)] {
                assert!(a.dot(b).abs() < 1e-12, "{w}: not orthogonal");
            }
            for a in [u, v] {
                assert!((a.length() - 1.0).abs() < 1e-12, "{w}: not unit");
            }
            assert!((u.cross(v) - w).length() < 1e-12, "{w}: not right-handed");
        }
        // Straight down (w.z = 0, sign(0) = +1): u = +X, v = +Z, as in the WGSL.
        let [u, v, _] = light_basis(DVec3::NEG_Y);
        assert_eq!((u, v), (DVec3::X, DVec3::Z));
    }

    #[test]
    fn chord_integral_matches_numerical_integration_of_the_kernel() {
        let (k, eta, r): (f64, f64, f64) = (1.7, 0.6, 0.9);
        for b in [0.0, 0.3, 0.6, 0.85, 0.95] {
            let n = 20_000;
            let half = (r * r - b * b).max(0.0).sqrt();
            let dt = 2.0 * half / n as f64;
            let numeric: f64 = (0..n)
                .map(|i| {
                    let t = -half + (i as f64 + 0.5) * dt;
                    k * eta * kernel_u2((t * t + b * b) / (r * r)) * dt
                })
                .sum();
            let exact = particle_optical_depth(k, eta, r, b);
            assert!(
                (numeric - exact).abs() < 1e-6 * exact.max(1e-3),
                "b {b}: {numeric} vs {exact}"
            );
        }
        assert_eq!(particle_optical_depth(k, eta, r, r), 0.0);
    }

    #[test]
    fn the_generators_streams_are_uniform_and_reproducible() {
        let mut a = SplitMix64::new(42);
        let mut b = SplitMix64::new(42);
        let n = 100_000;
        let mean: f64 = (0..n).map(|_| a.next_f64()).sum::<f64>() / n as f64;
        assert!((mean - 0.5).abs() < 0.005, "mean {mean}");
        let dir_mean = (0..n).map(|_| a.unit_sphere()).sum::<DVec3>() / n as f64;
        assert!(
            dir_mean.length() < 0.02,
            "directions not isotropic: {dir_mean}"
        );
        let mut c = SplitMix64::new(42);
        assert_eq!(b.next_u64(), c.next_u64());
        assert_ne!(
            SplitMix64::mixed(42).next_u64(),
            SplitMix64::new(42).next_u64()
        );
        let a = SplitMix64::for_sample(1, 2, 3).next_u64();
        assert_ne!(a, SplitMix64::for_sample(1, 2, 4).next_u64());
        assert_ne!(a, SplitMix64::for_sample(1, 3, 3).next_u64());
        assert_ne!(a, SplitMix64::for_sample(2, 2, 3).next_u64());
    }
}
