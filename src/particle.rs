//! Plain particle data shared by the renderer, the CPU reference, the path tracer and scene files.
//!
//! Nothing here depends on the engine: the same types feed the GPU buffers (they are `Pod`) and
//! the f64 reference implementations. Units and meaning follow `docs/physics.md`.

use bevy::{
    math::Vec3,
    reflect::{Reflect, std_traits::ReflectDefault},
};

use crate::math::KERNEL_VOLUME;
use serde::{Deserialize, Serialize};

/// One particle of a participating medium.
///
/// Its density field is `density * k(|x - position| / radius)` with the kernel
/// `k(u) = (1 - u²)²` for `u < 1` and `0` beyond (docs/physics.md).
#[derive(Clone, Copy, Debug, Default, PartialEq, Reflect, Serialize, Deserialize)]
#[reflect(Default, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Particle {
    /// Centre in cloud-local space, metres.
    pub position: Vec3,
    /// Radius of the kernel's support, metres; must be finite and `> 0`.
    pub radius: f32,
    /// Dimensionless density `eta >= 0` (extinction per metre at the centre is `extinction * density`).
    pub density: f32,
}

/// The optical properties of a cloud's medium (docs/physics.md, "Medium").
#[derive(Clone, Copy, Debug, PartialEq, Reflect, Serialize, Deserialize)]
#[reflect(Default, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Medium {
    /// Extinction per world metre at density 1 (`K`, 1/m); finite and `>= 0`.
    pub extinction: f32,
    /// Single-scattering albedo `omega` in `[0, 1]`: the fraction of extinction that scatters.
    pub albedo: f32,
    /// Henyey–Greenstein anisotropy `g` in `(-1, 1)` (dimensionless): the mean cosine of the
    /// scattering angle. `0` scatters isotropically; `g > 0` scatters forward, so a cloud lit from
    /// behind glows at its edges (the silver lining). Optional in scene files, default 0.
    #[serde(default)]
    pub anisotropy: f32,
}

impl Default for Medium {
    /// A bright cumulus-like medium: 10 /m at density 1, albedo 0.99, isotropic.
    fn default() -> Self {
        Self {
            extinction: 10.0,
            albedo: 0.99,
            anisotropy: 0.0,
        }
    }
}

/// The largest coordinate and radius of a particle, metres (a thousand times Pluto's orbit):
/// every cloud's bounds, and the squared distances the renderer takes across them, stay finite
/// in f32, where a particle near f32's limits would make them infinite.
pub const MAX_PARTICLE_EXTENT: f32 = 1e15;

/// Why a particle or a medium is unusable. Every variant names the field, its value and what is allowed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum InvalidMedium {
    #[error(
        "particle {index}: `position` is {value:?}; every coordinate must be finite and within \
         ±{MAX_PARTICLE_EXTENT:e} m"
    )]
    /// A particle's position has a coordinate that is NaN, or beyond
    /// [`MAX_PARTICLE_EXTENT`] from the origin.
    Position {
        /// The particle's index in its list.
        index: usize,
        /// The position, metres.
        value: Vec3,
    },
    #[error(
        "particle {index}: `radius` is {value}; it must be > 0 and at most {MAX_PARTICLE_EXTENT:e} m"
    )]
    /// A particle's radius is not positive, or beyond [`MAX_PARTICLE_EXTENT`].
    Radius {
        /// The particle's index in its list.
        index: usize,
        /// The radius, metres.
        value: f32,
    },
    #[error("particle {index}: `density` is {value}; it must be finite and >= 0")]
    /// A particle's density is negative or not finite.
    Density {
        /// The particle's index in its list.
        index: usize,
        /// The dimensionless density.
        value: f32,
    },
    #[error("`extinction` is {0}; it must be finite and >= 0")]
    /// The medium's extinction (1/m) is negative or not finite.
    Extinction(f32),
    #[error("`albedo` is {0}; it must lie in [0, 1]")]
    /// The medium's albedo lies outside `[0, 1]`.
    Albedo(f32),
    #[error("`anisotropy` is {0}; it must lie in (-1, 1)")]
    /// The medium's Henyey–Greenstein `g` lies outside `(-1, 1)`.
    Anisotropy(f32),
}

impl Particle {
    /// Checks the particle against docs/physics.md; `index` is only used in the error message.
    pub fn validate(&self, index: usize) -> Result<(), InvalidMedium> {
        if !(self.position.abs().max_element() <= MAX_PARTICLE_EXTENT) {
            return Err(InvalidMedium::Position {
                index,
                value: self.position,
            });
        }
        if !(self.radius > 0.0 && self.radius <= MAX_PARTICLE_EXTENT) {
            return Err(InvalidMedium::Radius {
                index,
                value: self.radius,
            });
        }
        if !(self.density.is_finite() && self.density >= 0.0) {
            return Err(InvalidMedium::Density {
                index,
                value: self.density,
            });
        }
        Ok(())
    }

    /// Mass of the particle: the integral of its density over space, `eta * r³ * 32π/105` (m³).
    pub fn mass(&self) -> f64 {
        KERNEL_VOLUME * self.density as f64 * (self.radius as f64).powi(3)
    }
}

impl Medium {
    /// The medium's δ-M transform (docs/illumination.md §4, §5).
    pub fn delta_m(&self) -> DeltaM {
        DeltaM::new(self.albedo as f64, self.anisotropy as f64)
    }

    /// Checks the medium against docs/physics.md.
    pub fn validate(&self) -> Result<(), InvalidMedium> {
        if !(self.extinction.is_finite() && self.extinction >= 0.0) {
            return Err(InvalidMedium::Extinction(self.extinction));
        }
        if !(0.0..=1.0).contains(&self.albedo) {
            return Err(InvalidMedium::Albedo(self.albedo));
        }
        if !(self.anisotropy > -1.0 && self.anisotropy < 1.0) {
            return Err(InvalidMedium::Anisotropy(self.anisotropy));
        }
        Ok(())
    }
}

/// The fraction `f` of a Henyey–Greenstein medium's scattering that its δ-M transform takes as
/// not scattered at all: `g³` for `g > 0` (Wiscombe 1977's rule for a phase function kept to
/// three Legendre terms, the sweep's P2 source), none for `g <= 0`.
pub fn peak_fraction(g: f64) -> f64 {
    // A backward peak is not a forward one: only g > 0 is truncated (the remainder's moments
    // would leave [-1, 1] otherwise).
    g.max(0.0).powi(3)
}

/// The δ-M transform of a Henyey–Greenstein medium (Wiscombe 1977; docs/illumination.md §4):
/// the fraction `f` of its scattering ([`peak_fraction`]) goes on in the forward direction as if
/// not scattered at all, and the rest scatters with the remainder's Legendre moments
/// `chi'_l = (g^l - f) / (1 - f)`, `l = 1, 2`, what the sweep's P2 source holds. So the
/// transformed medium keeps the phase function's first four moments, `1, g, g², g³`. Identity
/// for `g = 0`: `depth_scale` 1, `albedo` unchanged, `anisotropy` 0, `second_moment` 0.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DeltaM {
    /// The fraction of the optical depth the transformed medium keeps, `1 - albedo f`: the
    /// light's beam and the multiple scattering see `depth_scale * tau`.
    pub depth_scale: f64,
    /// The transformed medium's albedo, `albedo (1 - f) / (1 - albedo f)`.
    pub albedo: f64,
    /// The remainder's first moment, its asymmetry `g' = (g - f) / (1 - f)`.
    pub anisotropy: f64,
    /// The remainder's second moment, `(g² - f) / (1 - f)`: `g²` where nothing is truncated.
    pub second_moment: f64,
}

impl DeltaM {
    /// The transform of a medium of albedo `albedo` in `[0, 1]` and anisotropy `g` in `(-1, 1)`.
    pub fn new(albedo: f64, g: f64) -> Self {
        let f = peak_fraction(g);
        // > 0: f < 1.
        let depth_scale = 1.0 - albedo * f;
        Self {
            depth_scale,
            albedo: albedo * (1.0 - f) / depth_scale,
            anisotropy: (g - f) / (1.0 - f),
            second_moment: (g * g - f) / (1.0 - f),
        }
    }
}

/// Validates a whole cloud: the medium first, then every particle.
pub fn validate_cloud(medium: &Medium, particles: &[Particle]) -> Result<(), InvalidMedium> {
    medium.validate()?;
    particles
        .iter()
        .enumerate()
        .try_for_each(|(i, p)| p.validate(i))
}

/// A directional light as the physics sees it (docs/physics.md, "Lights").
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LightSample {
    /// Direction in which the light travels, world space; need not be unit length, must not be zero.
    pub direction: Vec3,
    /// Linear RGB irradiance `E` perpendicular to the direction.
    pub irradiance: Vec3,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The transformed phase function `f δ + (1 - f) p'` keeps the first four Legendre moments
    /// of Henyey–Greenstein's, `1, g, g², g³` (`p'` holds the first three, `1, g', chi'_2`); the
    /// transformed medium's scattering coefficient is `(1 - f)` of the medium's; `g = 0` and
    /// backward media are not truncated.
    #[test]
    fn delta_m_keeps_the_phase_functions_first_four_moments() {
        for (albedo, g) in [(0.9, 0.7), (1.0, 0.85), (0.5, 0.2), (0.99, 0.0)] {
            let d = DeltaM::new(albedo, g);
            let f = g.powi(3);
            assert!((f + (1.0 - f) * d.anisotropy - g).abs() < 1e-12);
            assert!((f + (1.0 - f) * d.second_moment - g * g).abs() < 1e-12);
            assert!((d.depth_scale - (1.0 - albedo * f)).abs() < 1e-12);
            assert!((d.albedo * d.depth_scale - albedo * (1.0 - f)).abs() < 1e-12);
            assert!((0.0..=1.0).contains(&d.albedo) && d.anisotropy.abs() < 1.0);
            assert!((0.0..1.0).contains(&d.second_moment));
        }
        assert_eq!(
            DeltaM::new(0.8, -0.6),
            DeltaM {
                depth_scale: 1.0,
                albedo: 0.8,
                anisotropy: -0.6,
                second_moment: -0.6 * -0.6
            }
        );
    }
}
