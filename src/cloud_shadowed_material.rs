//! A game's `StandardMaterial` meshes under the clouds (feature `lit_object`; docs/illumination.md
//! §10): [`CloudShadowedMaterial`] is Bevy's `StandardMaterial` extended with
//! [`CloudShadowReceiver`], which sees every cloud-lighting directional light through the cloud
//! shadow maps ([`CloudShadowMaps`](crate::CloudShadowMaps)), and Bevy's ambient light through
//! their sky map. Everything else is Bevy's PBR: its shadow maps, environment light, fog.
//!
//! Add [`LitObjectPlugin`](crate::lit_object::LitObjectPlugin) (it keeps the extension's lights
//! and maps up to date every frame) and turn the shadow maps on; then wrap a mesh's material:
//!
//! ```no_run
//! # use bevy::prelude::*;
//! # use bevy_particle_clouds::cloud_shadowed_material::{CloudShadowedMaterial, CloudShadowReceiver};
//! fn ground(
//!     mut commands: Commands,
//!     mut meshes: ResMut<Assets<Mesh>>,
//!     mut materials: ResMut<Assets<CloudShadowedMaterial>>,
//! ) {
//!     commands.spawn((
//!         Mesh3d(meshes.add(Plane3d::default().mesh().size(100.0, 100.0))),
//!         MeshMaterial3d(materials.add(CloudShadowedMaterial {
//!             base: StandardMaterial::from_color(Color::srgb(0.3, 0.5, 0.3)),
//!             extension: CloudShadowReceiver::default(),
//!         })),
//!     ));
//! }
//! ```
//!
//! Bevy's lighting has no per-light hook, so the shader lights the surface as Bevy does and then
//! takes away `(1 - T)` of each cloud-lighting light's contribution (Bevy's own
//! `directional_light` and shadow), `T` the clouds' transmittance towards that light: exact,
//! since lighting is linear in each light, for one more evaluation of each such light per
//! fragment. Bevy's ambient light stands for the sky: under a `CloudSkyLight` (which makes the
//! sky map) the shader takes away `(1 - V)` of Bevy's own `ambient_light`, `V` what the clouds
//! leave of the sky there. Not shadowed by the clouds: the environment map's light, the
//! diffuse-transmission lobe's light from behind, and meshes drawn with the deferred renderer
//! (Bevy lights its G-buffer in a pass of its own). Bevy 0.19's directional light textures
//! (`DirectionalLightTexture`) could carry the shadow to unmodified `StandardMaterial`s, but they
//! need binding arrays, which the software adapter our tests run on lacks.

use bevy::{
    pbr::{ExtendedMaterial, MaterialExtension},
    prelude::*,
    render::{render_resource::AsBindGroup, storage::ShaderBuffer},
    shader::ShaderRef,
};

use crate::lit_object::LitObjectLights;

/// Bevy's `StandardMaterial` that takes the clouds' shadows from the cloud-lighting directional
/// lights.
pub type CloudShadowedMaterial = ExtendedMaterial<StandardMaterial, CloudShadowReceiver>;

/// The extension that makes a `StandardMaterial` take the clouds' shadows. Its fields are written
/// by [`LitObjectPlugin`](crate::lit_object::LitObjectPlugin) every frame they change; create it
/// with `default()`.
#[derive(Asset, AsBindGroup, Clone, Debug, Default, Reflect)]
#[reflect(Clone, Debug, Default)]
pub struct CloudShadowReceiver {
    /// The cloud-lighting lights and their maps' placements (written by the plugin).
    #[uniform(100)]
    pub lights: LitObjectLights,
    /// The cloud shadow maps ([`CloudShadowMaps::buffer`](crate::CloudShadowMaps::buffer);
    /// written by the plugin).
    #[storage(101, read_only)]
    pub shadow_maps: Handle<ShaderBuffer>,
}

impl MaterialExtension for CloudShadowReceiver {
    fn fragment_shader() -> ShaderRef {
        "embedded://bevy_particle_clouds/cloud_shadowed_material.wgsl".into()
    }

    fn deferred_fragment_shader() -> ShaderRef {
        "embedded://bevy_particle_clouds/cloud_shadowed_material.wgsl".into()
    }
}
