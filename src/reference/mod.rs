//! CPU references, for validation (like `bevy_solari`'s reference path tracer beside its
//! real-time path):
//!
//! - [`illumination`] and [`composite`]: the real-time renderer's exact discretization in f64
//!   (`docs/illumination.md`); the GPU passes are tested voxel by voxel against it.
//! - [`path_tracer`]: ground truth of the physical model itself (docs/physics.md), with no voxels and
//!   no billboards; the time–error benchmark measures the real-time renderer against it.
//! - [`cloud_target`]: the depth-aware upsample of a reduced-resolution cloud target.
//! - [`ground`]: the ground's radiance under a cloud, which its multiple scattering takes in.
//! - [`metrics`]: the error metrics of docs/physics.md.

pub mod camera;
pub mod cloud_target;
pub mod composite;
pub mod geometry;
pub mod ground;
pub mod illumination;
pub mod metrics;
pub mod path_tracer;
pub mod view_volume;
