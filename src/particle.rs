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
    /// The fraction of its optical depth that the light's beam keeps for single scattering:
    /// `1 - albedo g²` (docs/illumination.md §5). 1 for an isotropic medium.
    pub fn single_scattering_depth_scale(&self) -> f64 {
        single_scattering_depth_scale(self.albedo as f64, self.anisotropy as f64)
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

/// The fraction of its optical depth that a light's beam keeps in a Henyey–Greenstein medium of
/// anisotropy `g` and albedo `albedo`, as single scattering sees it: `1 - albedo g²`. The
/// δ-Eddington truncation (Joseph, Wiscombe & Weinman 1976) takes the fraction `g²` of the
/// scattering as not scattered at all (it stays in the forward peak), so light that scattered a
/// few times at small angles still lights a point as if it came straight from the light.
/// Exactly 1 for `g = 0`.
pub fn single_scattering_depth_scale(albedo: f64, g: f64) -> f64 {
    1.0 - albedo * g * g
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
