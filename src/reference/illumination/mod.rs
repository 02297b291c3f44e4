//! f64 CPU reference of the illumination discretization (`docs/illumination.md`).
//!
//! Every stage follows the contract literally so that the GPU passes can be compared with it voxel by
//! voxel: [`voxelize()`] (section 1), [`shade()`] (section 2), [`gather()`] (section 3),
//! [`scatter()`] (section 4) and [`CloudIllumination::scattered_at`] (section 5). [`illuminate`] runs them all.
//!
//! All positions and lengths are in cloud-local space (metres of the particle file); extinctions passed
//! in are *local* extinctions `K_local = K * s` (1 per local metre). Radiance-like quantities (`S`,
//! `A`, colours) are in the units of the lights' irradiance `E`.
//!
//! One file per stage, as the GPU passes are laid out: `voxelize`, `shade`, `gather`, `scatter`,
//! `illuminate` (every stage for a cloud or a scene, and the illumination at a shading point) and
//! `shadow_maps` (section 10); `interpolation` holds the trilinear lookups they share.
//! `coarse_cycles` accelerates the scattering series with a grid of half the resolution; the GPU
//! does not run it yet.

mod coarse_cycles;
mod gather;
mod illuminate;
mod interpolation;
mod scatter;
mod shade;
mod shadow_maps;
#[cfg(test)]
mod test_support;
mod voxelize;

pub use coarse_cycles::{CoarseCycles, restrict_by_density, scatter_coarse_cycles};
pub use gather::{
    Flux, Moments, Quadrupole, gather, gather_source, quadrupole_basis, single_scattering_at,
    single_scattering_towards,
};
pub use illuminate::{
    CloudIllumination, LocalLight, PlacedCloud, SeenIllumination, illuminate,
    illuminate_at_light_resolution, illuminate_clouds_over_ground, illuminate_clouds_under_sky,
    illuminate_scene, illuminate_scene_cloud, illuminate_under_sky,
};
pub use scatter::{
    CONDITIONING, CONDITIONING_FULL, FAST_RATIO_FULL, MAX_ORDER_RATIO, MODE_SEPARATION,
    MODE_SEPARATION_FULL, MultipleScattering, ORDER_RATIO_FULL, SERIES_BELOW, SeriesClosure,
    TwoModes, curvature_weight, energy_bound, lattice_directions, lebedev_weight, order_ratio,
    order_size, scatter, scatter_medium, scatter_under_sky, scatter_warm, scatter_warm_medium,
    segment_weights, sweep_mode_gain, two_mode_weight,
};
pub use shade::{LightVolume, ShadeInputs, shade, shade_brute_force};
pub use shadow_maps::{
    cloud_shadow_map, grid_optical_depth, shadow_map_depth_at, sky_occlusion_at, sky_occlusion_map,
};
pub use voxelize::{DensityGrid, voxelize};
