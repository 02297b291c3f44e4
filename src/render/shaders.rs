//! The crate's WGSL, beside the Rust of each pass in `src/render/`, embedded into the binary as
//! `embedded://bevy_particle_clouds/render/<file>.wgsl` assets (with Bevy's `embedded_watcher`
//! feature they hot-reload from the source tree while developing).

use bevy::{
    asset::{embedded_asset, load_embedded_asset},
    prelude::*,
    shader::Shader,
};

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

impl CloudShaders {
    /// Embeds every shader into the app's asset sources and loads it.
    pub(crate) fn load(app: &mut App) -> Self {
        embedded_asset!(app, "types.wgsl");
        embedded_asset!(app, "voxelize.wgsl");
        embedded_asset!(app, "density.wgsl");
        embedded_asset!(app, "shade.wgsl");
        embedded_asset!(app, "cast.wgsl");
        embedded_asset!(app, "sky_map.wgsl");
        embedded_asset!(app, "gather.wgsl");
        embedded_asset!(app, "overlap.wgsl");
        embedded_asset!(app, "ground.wgsl");
        embedded_asset!(app, "scatter.wgsl");
        embedded_asset!(app, "closure.wgsl");
        embedded_asset!(app, "coarse_grid.wgsl");
        embedded_asset!(app, "sort.wgsl");
        embedded_asset!(app, "view_volume.wgsl");
        embedded_asset!(app, "fog.wgsl");
        embedded_asset!(app, "billboard.wgsl");
        embedded_asset!(app, "cloud_target.wgsl");
        Self {
            types: load_embedded_asset!(&*app, "types.wgsl"),
            voxelize: load_embedded_asset!(&*app, "voxelize.wgsl"),
            density: load_embedded_asset!(&*app, "density.wgsl"),
            shade: load_embedded_asset!(&*app, "shade.wgsl"),
            cast: load_embedded_asset!(&*app, "cast.wgsl"),
            sky_map: load_embedded_asset!(&*app, "sky_map.wgsl"),
            gather: load_embedded_asset!(&*app, "gather.wgsl"),
            overlap: load_embedded_asset!(&*app, "overlap.wgsl"),
            ground: load_embedded_asset!(&*app, "ground.wgsl"),
            scatter: load_embedded_asset!(&*app, "scatter.wgsl"),
            closure: load_embedded_asset!(&*app, "closure.wgsl"),
            coarse_grid: load_embedded_asset!(&*app, "coarse_grid.wgsl"),
            sort: load_embedded_asset!(&*app, "sort.wgsl"),
            view_volume: load_embedded_asset!(&*app, "view_volume.wgsl"),
            fog: load_embedded_asset!(&*app, "fog.wgsl"),
            billboard: load_embedded_asset!(&*app, "billboard.wgsl"),
            cloud_target: load_embedded_asset!(&*app, "cloud_target.wgsl"),
        }
    }
}
