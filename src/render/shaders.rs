//! The crate's WGSL, compiled into the binary from `shaders/` and registered as shader assets.

use bevy::{prelude::*, shader::Shader};

/// Handles of every shader of the crate (strong: they keep the shaders loaded).
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
    /// `gather.wgsl`.
    pub gather: Handle<Shader>,
    /// `scatter.wgsl`.
    pub scatter: Handle<Shader>,
    /// `closure.wgsl`.
    pub closure: Handle<Shader>,
    /// `sort.wgsl`.
    pub sort: Handle<Shader>,
    /// `view_volume.wgsl`.
    pub view_volume: Handle<Shader>,
    /// `billboard.wgsl`.
    pub billboard: Handle<Shader>,
}

macro_rules! shader {
    ($shaders:expr, $file:literal) => {
        $shaders.add(Shader::from_wgsl(
            include_str!(concat!("../../shaders/", $file)),
            concat!("bevy_particle_clouds/shaders/", $file),
        ))
    };
}

impl CloudShaders {
    pub(crate) fn load(shaders: &mut Assets<Shader>) -> Self {
        Self {
            types: shader!(shaders, "types.wgsl"),
            voxelize: shader!(shaders, "voxelize.wgsl"),
            density: shader!(shaders, "density.wgsl"),
            shade: shader!(shaders, "shade.wgsl"),
            gather: shader!(shaders, "gather.wgsl"),
            scatter: shader!(shaders, "scatter.wgsl"),
            closure: shader!(shaders, "closure.wgsl"),
            sort: shader!(shaders, "sort.wgsl"),
            view_volume: shader!(shaders, "view_volume.wgsl"),
            billboard: shader!(shaders, "billboard.wgsl"),
        }
    }
}
