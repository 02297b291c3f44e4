//! Lit objects (feature `lit_object`, which `headless` enables; docs/physics.md, "Lit objects"):
//! the Lambertian surfaces of scene files' objects with a `reflectance`, shaded as the physics
//! says, lit by the cloud-lighting directional lights through the cloud shadow maps
//! ([`CloudShadowMaps`]) and by the sky ([`CloudSkyLight`], unshadowed by clouds), fogged by the
//! view's `DistanceFog`. Bevy's `StandardMaterial` is not Lambertian (its diffuse lobe is
//! Burley's, with a specular lobe beside it), so these objects have their own material,
//! `lit_object.wgsl`. A game may use it for a mesh that should take the clouds' shadows (add
//! [`LitObjectPlugin`] and turn the shadow maps on), as the `clouds` example's ground does.

use bevy::{
    asset::embedded_asset,
    prelude::*,
    render::{
        render_resource::{AsBindGroup, ShaderType},
        storage::ShaderBuffer,
    },
    shader::ShaderRef,
};

use crate::{
    CloudSkyLight,
    shadow_maps::{CloudLightQuery, CloudShadowMaps, ShadowMapPlacement, cloud_lights},
};

/// The most lights a lit object takes.
pub const MAX_LIT_OBJECT_LIGHTS: usize = 8;

/// A Lambertian surface that takes the clouds' shadows: it shows `color`, plus `reflectance / π`
/// times the irradiance of the cloud-lighting lights (through the cloud shadow maps) and of the
/// sky. The plugin keeps its lights up to date every frame.
#[derive(Asset, AsBindGroup, Clone, Debug, TypePath)]
pub struct LitObjectMaterial {
    /// What it emits and reflects.
    #[uniform(0)]
    pub surface: LitSurface,
    /// The lights and the sky (written by the plugin).
    #[uniform(1)]
    pub lights: LitObjectLights,
    /// The cloud shadow maps ([`CloudShadowMaps::buffer`]).
    #[storage(2, read_only)]
    pub shadow_maps: Handle<ShaderBuffer>,
}

/// Mirror of `LitSurface` in `lit_object.wgsl`.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct LitSurface {
    /// Linear RGB radiance emitted.
    pub color: Vec3,
    /// Linear RGB Lambertian reflectance in `[0, 1]`.
    pub reflectance: Vec3,
}

/// Mirror of `LitLight` in `lit_object.wgsl`: one directional light and its shadow map.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct LitLight {
    /// Unit direction towards the light.
    pub to_light: Vec3,
    /// 1 when the light has a shadow map.
    pub mapped: u32,
    /// Linear RGB irradiance.
    pub irradiance: Vec3,
    /// Its shadow map (unread without one).
    pub map: ShadowMapPlacement,
}

/// Mirror of `LitObjectLights` in `lit_object.wgsl`.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq)]
pub struct LitObjectLights {
    /// Linear RGB radiance of the sky.
    pub sky: Vec3,
    /// Lights in use.
    pub count: u32,
    /// The lights.
    pub lights: [LitLight; MAX_LIT_OBJECT_LIGHTS],
}

impl Material for LitObjectMaterial {
    fn fragment_shader() -> ShaderRef {
        "embedded://bevy_particle_clouds/lit_object.wgsl".into()
    }
}

/// The lit objects' material and the system that keeps their lights up to date.
pub struct LitObjectPlugin;

impl Plugin for LitObjectPlugin {
    fn build(&self, app: &mut App) {
        embedded_asset!(app, "lit_object.wgsl");
        app.add_plugins(MaterialPlugin::<LitObjectMaterial>::default())
            .add_systems(
                PostUpdate,
                update_lit_objects.after(crate::shadow_maps::place_cloud_shadow_maps),
            );
    }
}

/// The lights and the sky every lit object takes this frame.
fn lit_object_lights(
    maps: &CloudShadowMaps,
    sky: Vec3,
    lights: impl Iterator<Item = (Entity, Vec3, Vec3)>,
) -> LitObjectLights {
    let mut lit = LitObjectLights { sky, ..default() };
    for (entity, direction, irradiance) in lights.take(MAX_LIT_OBJECT_LIGHTS) {
        let map = maps.map_of(entity);
        lit.lights[lit.count as usize] = LitLight {
            to_light: -direction,
            mapped: map.is_some() as u32,
            irradiance,
            map: map.copied().unwrap_or_default(),
        };
        lit.count += 1;
    }
    lit
}

/// Writes this frame's lights, sky and shadow maps into every lit object's material, when they
/// changed.
fn update_lit_objects(
    maps: Res<CloudShadowMaps>,
    sky: Res<CloudSkyLight>,
    lights: CloudLightQuery,
    mut materials: ResMut<Assets<LitObjectMaterial>>,
) {
    let sky = sky.radiance().unwrap_or(Vec3::ZERO);
    let lit = lit_object_lights(&maps, sky, cloud_lights(&lights));
    let stale: Vec<AssetId<LitObjectMaterial>> = materials
        .iter()
        .filter(|(_, m)| m.lights != lit || m.shadow_maps != maps.buffer)
        .map(|(id, _)| id)
        .collect();
    for id in stale {
        if let Some(mut material) = materials.get_mut(id) {
            material.lights = lit;
            material.shadow_maps = maps.buffer.clone();
        }
    }
}
