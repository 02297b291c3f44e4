//! The leaves of the render world: nothing here imports another part of `render/`. GPU buffers and
//! recorded stages (`gpu`), workgroup sizes shared with the WGSL (`workgroups`), the shader handles
//! (`shaders`), the adapter's capability check (`adapter`), and the stages' cache keys. The WGSL
//! every pass imports sits here too: `types.wgsl` (mirrored in Rust by the passes' uniform
//! structs) and `density.wgsl`.

pub mod adapter;
pub mod gpu;
pub mod shaders;
pub mod types;
pub mod workgroups;

/// A cache key of a stage's inputs: a stage reruns only when its key changes.
pub(crate) fn key_of(value: impl std::hash::Hash) -> u64 {
    use std::hash::{BuildHasher, BuildHasherDefault, DefaultHasher};
    BuildHasherDefault::<DefaultHasher>::default().hash_one(value)
}
