//! The handles of the crate's WGSL. Each shader sits beside the Rust of its pass, in the folder of
//! its paper step; `render/mod.rs` embeds them all into the binary as
//! `embedded://bevy_particle_clouds/render/<folder>/<file>.wgsl` assets (with Bevy's
//! `embedded_watcher` feature they hot-reload from the source tree while developing).

use bevy::{prelude::*, shader::Shader};

/// Handles of every shader of the crate (strong: they keep the shaders loaded, which the `#import`s
/// of the shared modules need).
#[derive(Resource, Clone)]
pub struct CloudShaders {
    /// `bevy_particle_clouds::types`, imported by the others.
    pub types: Handle<Shader>,
    /// `voxelize.wgsl`.
    pub voxelize: Handle<Shader>,
    /// `bevy_particle_clouds::density`, imported by shade and view_volume.
    pub density: Handle<Shader>,
    /// `shade.wgsl`.
    pub shade: Handle<Shader>,
    /// `cast.wgsl`.
    pub cast: Handle<Shader>,
    /// `sky_map.wgsl`.
    pub sky_map: Handle<Shader>,
    /// `gather.wgsl`.
    pub gather: Handle<Shader>,
    /// `overlap.wgsl`.
    pub overlap: Handle<Shader>,
    /// `ground.wgsl`.
    pub ground: Handle<Shader>,
    /// `scatter.wgsl`.
    pub scatter: Handle<Shader>,
    /// `closure.wgsl`.
    pub closure: Handle<Shader>,
    /// `coarse_grid.wgsl`.
    pub coarse_grid: Handle<Shader>,
    /// `sort.wgsl`.
    pub sort: Handle<Shader>,
    /// `view_volume.wgsl`.
    pub view_volume: Handle<Shader>,
    /// `bevy_particle_clouds::fog`, imported by billboard.
    pub fog: Handle<Shader>,
    /// `billboard.wgsl`.
    pub billboard: Handle<Shader>,
    /// `cloud_target.wgsl`.
    pub cloud_target: Handle<Shader>,
}
