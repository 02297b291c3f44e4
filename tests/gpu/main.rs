//! The tests that render on the GPU (lavapipe on CI), linked as one binary. Each module compares
//! what the GPU computed with a CPU reference, or counts the passes a scene runs.

mod atmosphere;
mod batching;
mod between_clouds;
mod budget;
mod churn;
mod cloud_target;
mod coarse_cycles;
mod common;
mod determinism;
mod draw;
mod ground;
mod illumination;
mod lit_objects;
mod loader;
mod lod;
mod overlap;
mod plugin;
mod redraw;
mod seen_multiple;
mod shading_method;
mod sky;
mod splat;
mod stress;
mod sweep_march;
mod warm_start;
