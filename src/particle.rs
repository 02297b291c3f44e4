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

/// Why a particle or a medium is unusable. Every variant names the field, its value and what is allowed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum InvalidMedium {
    #[error("particle {index}: `position` is {value:?}; every coordinate must be finite")]
    /// A particle's position has a NaN or infinite coordinate.
    Position {
        /// The particle's index in its list.
        index: usize,
        /// The position, metres.
        value: Vec3,
    },
    #[error("particle {index}: `radius` is {value}; it must be finite and > 0")]
    /// A particle's radius is not finite and positive.
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
        if !self.position.is_finite() {
            return Err(InvalidMedium::Position {
                index,
                value: self.position,
            });
        }
        if !(self.radius.is_finite() && self.radius > 0.0) {
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
    /// The medium's δ-Eddington transform (docs/illumination.md §4, §5).
    pub fn delta_eddington(&self) -> DeltaEddington {
        DeltaEddington::new(self.albedo as f64, self.anisotropy as f64)
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

/// The δ-Eddington transform of a Henyey–Greenstein medium (Joseph, Wiscombe & Weinman 1976;
/// docs/illumination.md §4): the fraction `f = g²` of its scattering (for `g > 0`; none for
/// `g <= 0`) goes on in the forward direction as if not scattered at all, and the rest scatters
/// with the asymmetry `g' = (g - f) / (1 - f)`. The transformed medium keeps the phase function's
/// first two Legendre moments, `g` and `g²`. Identity for `g = 0`: `depth_scale` 1, `albedo`
/// unchanged, `anisotropy` 0.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DeltaEddington {
    /// The fraction of the optical depth the transformed medium keeps, `1 - albedo f`: the
    /// light's beam and the multiple scattering see `depth_scale * tau`.
    pub depth_scale: f64,
    /// The transformed medium's albedo, `albedo (1 - f) / (1 - albedo f)`.
    pub albedo: f64,
    /// The transformed medium's asymmetry `g'`: `g / (1 + g)` for `g > 0`, else `g`.
    pub anisotropy: f64,
}

impl DeltaEddington {
    /// The transform of a medium of albedo `albedo` in `[0, 1]` and anisotropy `g` in `(-1, 1)`.
    pub fn new(albedo: f64, g: f64) -> Self {
        // A backward peak is not a forward one: only g > 0 is truncated (g' would leave [-1, 1]
        // for g < -1/2 otherwise).
        let f = g.max(0.0).powi(2);
        // > 0: f < 1.
        let depth_scale = 1.0 - albedo * f;
        Self {
            depth_scale,
            albedo: albedo * (1.0 - f) / depth_scale,
            anisotropy: (g - f) / (1.0 - f),
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

    /// The transformed phase function `f δ + (1 - f) p_g'` keeps the first two Legendre moments
    /// of Henyey–Greenstein's, `g` and `g²`; the transformed medium's scattering coefficient is
    /// `(1 - f)` of the medium's; `g = 0` and backward media are not truncated.
    #[test]
    fn delta_eddington_keeps_the_phase_functions_first_two_moments() {
        for (albedo, g) in [(0.9, 0.7), (1.0, 0.85), (0.5, 0.2), (0.99, 0.0)] {
            let d = DeltaEddington::new(albedo, g);
            let f = g * g;
            assert!((f + (1.0 - f) * d.anisotropy - g).abs() < 1e-12);
            assert!((d.depth_scale - (1.0 - albedo * f)).abs() < 1e-12);
            assert!((d.albedo * d.depth_scale - albedo * (1.0 - f)).abs() < 1e-12);
            assert!((0.0..=1.0).contains(&d.albedo) && d.anisotropy.abs() < 1.0);
        }
        assert_eq!(
            DeltaEddington::new(0.8, -0.6),
            DeltaEddington {
                depth_scale: 1.0,
                albedo: 0.8,
                anisotropy: -0.6
            }
        );
    }
}
