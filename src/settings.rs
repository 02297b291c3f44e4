//! Quality knobs of the real-time renderer.
//!
//! Every knob lives in [`CloudQualitySettings`], a component on a [`ParticleCloud`](crate::ParticleCloud)
//! entity; clouds without it use the [`DefaultCloudQuality`] resource. Scene files carry the same
//! struct under `settings`. The cost and error of each knob are measured by the time–error
//! benchmark (see the README).

use bevy::prelude::*;
use serde::Deserialize;

/// How one multiple-scattering iteration weighs the 26 neighbours of a voxel.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Reflect, Deserialize)]
#[reflect(Default, Debug, PartialEq)]
pub enum ScatterStencil {
    /// Derived from transport: neighbour `j` at distance `d_j` contributes
    /// `albedo / 26 * (1 - exp(-tau_j)) * S_j`, `tau_j` the optical depth between the two voxel
    /// centres. Energy can only decrease (see `docs/illumination.md`).
    Transmittance,
    /// The paper's Algorithm 2: every neighbour weighted by the voxel's own opacity,
    /// `albedo / 26 * (1 - exp(-sigma_t h)) * S_j`.
    Paper,
    /// Resolution-consistent hops: along each of the 26 directions, `S` is taken about one mean
    /// free path away (a whole number of voxels, at least one, inside the grid) and stands for
    /// the segment of twice that length (midpoint rule), `albedo / 26 * (1 - exp(-2 tau_m)) * S_m`.
    /// Light no longer needs one scattering per voxel to cross optically thin voxels. The default:
    /// 2.5× lower relative RMSE than `Transmittance` on thick clouds at the same cost (README).
    #[default]
    FreePath,
}

/// Per-cloud quality knobs. Missing fields in scene files take these defaults.
#[derive(Component, Clone, Copy, Debug, PartialEq, Reflect, Deserialize)]
#[serde(default, deny_unknown_fields)]
#[reflect(Component, Default, Debug, PartialEq)]
pub struct CloudQualitySettings {
    /// Voxels per side of the cloud's density and illumination volumes (and of each light's
    /// shaded volume). Allowed: `MIN_VOLUME_RESOLUTION..=MAX_VOLUME_RESOLUTION`. Default 32, on the
    /// time–error benchmark's Pareto front (README, "Performance and accuracy").
    pub volume_resolution: u32,
    /// Multiple-scattering iterations (orders beyond the first); 0 = single scattering only.
    /// Allowed: `0..=MAX_SCATTER_ITERATIONS`. Default 8.
    pub scatter_iterations: u32,
    /// Fraction `f` in `[0, 1]` of scattered light treated as continuing forward in the shading
    /// pass (the paper's forward scattering): light attenuates with `sigma_t * (1 - f * albedo)`.
    /// Default 0, which is exactly the isotropic model of PHYSICS.md.
    pub forward_scattering: f32,
    /// The multiple-scattering stencil. Default [`ScatterStencil::FreePath`].
    pub scatter_stencil: ScatterStencil,
}

/// Smallest allowed `volume_resolution`.
pub const MIN_VOLUME_RESOLUTION: u32 = 4;
/// Largest allowed `volume_resolution` (a 256³ RGBA f32 volume is 256 MiB).
pub const MAX_VOLUME_RESOLUTION: u32 = 256;
/// Largest allowed `scatter_iterations`.
pub const MAX_SCATTER_ITERATIONS: u32 = 4096;

impl Default for CloudQualitySettings {
    fn default() -> Self {
        Self {
            volume_resolution: 32,
            scatter_iterations: 8,
            forward_scattering: 0.0,
            scatter_stencil: ScatterStencil::FreePath,
        }
    }
}

/// Why a settings value is refused; each variant names the field, its value and what is allowed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum InvalidSettings {
    #[error(
        "`volume_resolution` is {0}; allowed is {MIN_VOLUME_RESOLUTION}..={MAX_VOLUME_RESOLUTION}"
    )]
    /// `volume_resolution` outside `MIN_VOLUME_RESOLUTION..=MAX_VOLUME_RESOLUTION`.
    VolumeResolution(u32),
    #[error("`scatter_iterations` is {0}; allowed is 0..={MAX_SCATTER_ITERATIONS}")]
    /// `scatter_iterations` above `MAX_SCATTER_ITERATIONS`.
    ScatterIterations(u32),
    #[error("`forward_scattering` is {0}; it must lie in [0, 1]")]
    /// `forward_scattering` outside `[0, 1]` (or NaN).
    ForwardScattering(f32),
}

impl CloudQualitySettings {
    /// Checks every knob's range.
    pub fn validate(&self) -> Result<(), InvalidSettings> {
        if !(MIN_VOLUME_RESOLUTION..=MAX_VOLUME_RESOLUTION).contains(&self.volume_resolution) {
            return Err(InvalidSettings::VolumeResolution(self.volume_resolution));
        }
        if self.scatter_iterations > MAX_SCATTER_ITERATIONS {
            return Err(InvalidSettings::ScatterIterations(self.scatter_iterations));
        }
        if !(0.0..=1.0).contains(&self.forward_scattering) {
            return Err(InvalidSettings::ForwardScattering(self.forward_scattering));
        }
        Ok(())
    }
}

/// The settings of clouds that have no [`CloudQualitySettings`] component.
#[derive(Resource, Clone, Copy, Debug, Default, PartialEq, Reflect, Deref, DerefMut)]
#[reflect(Resource, Default, Debug, PartialEq)]
pub struct DefaultCloudQuality(pub CloudQualitySettings);

/// How the shade pass computes each light's transmittance volume (docs/illumination.md §2).
///
/// A resource of the main world, extracted to the render world. Both methods give the same
/// volume (up to f32 rounding); the brute force exists to measure what the incremental pass saves
/// (`cargo run --example benchmark -- --illumination`). A change takes effect the next time a
/// light is shaded (when a light, the density or the extinction changes).
#[derive(Resource, Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Reflect)]
#[reflect(Resource, Default, Debug, PartialEq)]
pub enum ShadingMethod {
    /// The paper's Algorithm 4: one invocation per column along the light, each slice the
    /// previous one times one step's attenuation: `n²` invocations of `n` steps.
    #[default]
    Incremental,
    /// Every voxel marches to the light on its own: `n³` invocations of up to `n` steps.
    BruteForce,
}
