//! The illumination passes (the paper's Algorithm 1, lines 2–6): voxelize, shade per light,
//! gather and multiple scattering. Only the stages planned for this frame run
//! ([`plan`](crate::render::plan)). Every pass is batched: one dispatch covers every cloud of a volume
//! pool ([`pools`](crate::render::plan::pools)), its z workgroups walking a work list (voxelize first copies
//! the clouds' particles into one buffer, [`voxelize`]). Their bind groups and
//! work lists are made in `PrepareBindGroups`; the system in the `RenderGraph` schedule, once per
//! frame before any camera, only records.

pub mod batches;
pub mod cast;
pub mod node;
pub mod pipelines;
pub mod scatter;
pub mod shadow_maps;
pub mod sky_map;
pub mod voxelize;

// The batches lived here before `batches.rs`; their public paths stay.
pub use batches::{IlluminationBatches, SweepPairVolumes};
