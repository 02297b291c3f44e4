//! Lit objects (feature `lit_object`, which `headless` enables; docs/physics.md, "Lit objects"):
//! the Lambertian surfaces of scene files' objects with a `reflectance`, shaded as the physics
//! says, lit by the cloud-lighting directional lights through the cloud shadow maps
//! ([`CloudShadowMaps`]) and by the sky ([`CloudSkyLight`], through the maps' sky map), fogged
//! by the view's `DistanceFog`. Bevy's `StandardMaterial` is not Lambertian (its diffuse lobe is
//! Burley's, with a specular lobe beside it), so these objects have their own material,
//! `lit_object.wgsl`. A game may use it for a mesh that should take the clouds' shadows (add
//! [`LitObjectPlugin`] and turn the shadow maps on), as the `clouds` example's ground does; for
//! its own `StandardMaterial` meshes there is [`CloudShadowedMaterial`], which the same plugin
//! keeps up to date.

use bevy::{
    asset::embedded_asset,
    prelude::*,
    render::{
        render_resource::{AsBindGroup, ShaderType},
        storage::ShaderBuffer,
    },
    shader::{ShaderRef, load_shader_library},
};

use crate::{
    CloudSkyLight,
    cloud_shadowed_material::{CloudShadowReceiver, CloudShadowedMaterial},
    shadow_maps::{CloudLight, CloudLights, CloudShadowMaps, ShadowMapPlacement},
};

/// The most lights a lit object takes.
pub const MAX_LIT_OBJECT_LIGHTS: usize = 8;

/// A Lambertian surface that takes the clouds' shadows: it shows `color`, plus `reflectance / π`
/// times the irradiance of the cloud-lighting lights (through the cloud shadow maps) and of the
/// sky (through the sky map, as an upward-facing surface on its plane would take it). The plugin
/// keeps its lights up to date every frame.
#[derive(Asset, AsBindGroup, Clone, Debug, Reflect)]
#[reflect(Clone, Debug)]
pub struct LitObjectMaterial {
    /// What it emits and reflects.
    #[uniform(0)]
    pub surface: LitSurface,
    /// The lights and the sky (written by the plugin).
    #[uniform(100)]
    pub lights: LitObjectLights,
    /// The cloud shadow maps ([`CloudShadowMaps::buffer`]).
    #[storage(101, read_only)]
    pub shadow_maps: Handle<ShaderBuffer>,
}

/// Mirror of `LitSurface` in `lit_object.wgsl`.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq, Reflect)]
#[reflect(Clone, Debug, Default, PartialEq)]
pub struct LitSurface {
    /// Linear RGB radiance emitted.
    pub color: Vec3,
    /// Linear RGB Lambertian reflectance in `[0, 1]`.
    pub reflectance: Vec3,
}

/// Mirror of `LitLight` in `cloud_shadow_maps.wgsl`: one directional light and its shadow map.
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq, Reflect)]
#[reflect(Clone, Debug, Default, PartialEq)]
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

/// Mirror of `LitObjectLights` in `cloud_shadow_maps.wgsl`: what a surface under the clouds
/// takes of them (bound at 100, the maps at 101, in [`LitObjectMaterial`] and
/// [`CloudShadowReceiver`]).
#[derive(ShaderType, Clone, Copy, Debug, Default, PartialEq, Reflect)]
#[reflect(Clone, Debug, Default, PartialEq)]
pub struct LitObjectLights {
    /// Linear RGB radiance of the sky.
    pub sky: Vec3,
    /// Lights in use.
    pub count: u32,
    /// The sky map ([`CloudShadowMaps::sky`]); `size` 0 without one (the sky unhidden).
    pub sky_map: ShadowMapPlacement,
    /// The lights.
    pub lights: [LitLight; MAX_LIT_OBJECT_LIGHTS],
}

impl Material for LitObjectMaterial {
    fn fragment_shader() -> ShaderRef {
        "embedded://bevy_particle_clouds/lit_object.wgsl".into()
    }
}

/// The materials that take the clouds' shadows ([`LitObjectMaterial`], [`CloudShadowedMaterial`])
/// and the system that keeps their lights up to date.
pub struct LitObjectPlugin;

impl Plugin for LitObjectPlugin {
    fn build(&self, app: &mut App) {
        load_shader_library!(app, "cloud_shadow_maps.wgsl");
        embedded_asset!(app, "lit_object.wgsl");
        embedded_asset!(app, "cloud_shadowed_material.wgsl");
        let placed = crate::shadow_maps::place_cloud_shadow_maps;
        app.add_plugins((
            MaterialPlugin::<LitObjectMaterial>::default(),
            MaterialPlugin::<CloudShadowedMaterial>::default(),
        ))
        .register_asset_reflect::<LitObjectMaterial>()
        .register_asset_reflect::<CloudShadowedMaterial>()
        .add_systems(
            PostUpdate,
            (
                update_cloud_lights::<LitObjectMaterial>.after(placed),
                update_cloud_lights::<CloudShadowedMaterial>.after(placed),
            ),
        );
    }
}

/// A material that reads the clouds' lights and shadow maps ([`LitObjectLights`] at binding 100,
/// the maps at 101), kept up to date by [`LitObjectPlugin`].
pub trait TakesCloudShadows: Asset {
    /// Its lights, and its maps' buffer.
    fn cloud_lights(&self) -> (&LitObjectLights, &Handle<ShaderBuffer>);
    /// Sets its lights and its maps' buffer.
    fn set_cloud_lights(&mut self, lights: LitObjectLights, maps: Handle<ShaderBuffer>);
}

impl TakesCloudShadows for LitObjectMaterial {
    fn cloud_lights(&self) -> (&LitObjectLights, &Handle<ShaderBuffer>) {
        (&self.lights, &self.shadow_maps)
    }
    fn set_cloud_lights(&mut self, lights: LitObjectLights, maps: Handle<ShaderBuffer>) {
        (self.lights, self.shadow_maps) = (lights, maps);
    }
}

impl TakesCloudShadows for CloudShadowedMaterial {
    fn cloud_lights(&self) -> (&LitObjectLights, &Handle<ShaderBuffer>) {
        (&self.extension.lights, &self.extension.shadow_maps)
    }
    fn set_cloud_lights(&mut self, lights: LitObjectLights, maps: Handle<ShaderBuffer>) {
        let CloudShadowReceiver {
            lights: l,
            shadow_maps,
        } = &mut self.extension;
        (*l, *shadow_maps) = (lights, maps);
    }
}

/// The lights and the sky every lit object takes this frame.
fn lit_object_lights(maps: &CloudShadowMaps, sky: Vec3, lights: &[CloudLight]) -> LitObjectLights {
    let mut lit = LitObjectLights {
        sky,
        sky_map: maps.sky.unwrap_or_default(),
        ..default()
    };
    for &CloudLight {
        entity,
        direction,
        irradiance,
    } in lights.iter().take(MAX_LIT_OBJECT_LIGHTS)
    {
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

/// Writes this frame's lights, sky and shadow maps into every material of type `M`, when they
/// changed (a material changed is uploaded again).
fn update_cloud_lights<M: TakesCloudShadows>(
    maps: Res<CloudShadowMaps>,
    sky: Res<CloudSkyLight>,
    lights: Res<CloudLights>,
    mut materials: ResMut<Assets<M>>,
) {
    let sky = sky.radiance().unwrap_or(Vec3::ZERO);
    let lit = lit_object_lights(&maps, sky, &lights.0);
    let stale: Vec<AssetId<M>> = materials
        .iter()
        .filter(|(_, m)| m.cloud_lights() != (&lit, &maps.buffer))
        .map(|(id, _)| id)
        .collect();
    for id in stale {
        if let Some(mut material) = materials.get_mut(id) {
            material.set_cloud_lights(lit, maps.buffer.clone());
        }
    }
}

#[cfg(test)]
mod tests {
    use bevy::render::render_resource::ShaderType;

    use super::*;

    /// Size and member names of the structs of `cloud_shadow_maps.wgsl`, as naga lays them out.
    fn wgsl_layouts() -> Vec<(String, u32, Vec<String>)> {
        let source: String = include_str!("cloud_shadow_maps.wgsl")
            .lines()
            .filter(|l| !l.starts_with('#'))
            .map(|l| l.replace("#{MATERIAL_BIND_GROUP}", "2") + "\n")
            .collect();
        let module = naga::front::wgsl::parse_str(&source).expect("the module parses");
        module
            .types
            .iter()
            .filter_map(|(_, t)| {
                let naga::TypeInner::Struct { members, span } = &t.inner else {
                    return None;
                };
                let names = members.iter().map(|m| m.name.clone().unwrap()).collect();
                Some((t.name.clone()?, *span, names))
            })
            .collect()
    }

    #[test]
    fn the_lights_have_the_wgsl_layout() {
        let layouts = wgsl_layouts();
        let of = |name: &str| {
            let (_, size, fields) = layouts.iter().find(|(n, ..)| n == name).unwrap();
            (*size as u64, fields.clone())
        };
        let names = |fields: &[&str]| fields.iter().map(|f| f.to_string()).collect::<Vec<_>>();
        assert_eq!(
            of("LitObjectLights"),
            (
                LitObjectLights::min_size().get(),
                names(&["sky", "count", "sky_map", "lights"])
            )
        );
        assert_eq!(
            of("LitLight"),
            (
                LitLight::min_size().get(),
                names(&["to_light", "mapped", "irradiance", "map"])
            )
        );
        assert_eq!(
            of("ShadowMapPlacement"),
            (
                ShadowMapPlacement::min_size().get(),
                names(&[
                    "u", "texel", "v", "w_begin", "d", "w_end", "corner", "size", "first"
                ])
            )
        );
    }

    /// The material and what it holds reflect (inspectors and scenes edit them by path), and the
    /// reflected clone is the material.
    #[test]
    fn the_material_reflects_by_path() {
        use bevy::reflect::GetPath;
        let mut material = LitObjectMaterial {
            surface: LitSurface {
                color: Vec3::ZERO,
                reflectance: Vec3::new(0.25, 0.5, 0.75),
            },
            lights: LitObjectLights::default(),
            shadow_maps: Handle::default(),
        };
        *material
            .path_mut::<f32>("surface.reflectance.y")
            .expect("a reflected field") = 0.375;
        material.lights.lights[2].map.size = 7;
        assert_eq!(material.surface.reflectance, Vec3::new(0.25, 0.375, 0.75));
        assert_eq!(
            *material.path::<u32>("lights.lights[2].map.size").unwrap(),
            7
        );
        let clone = material.reflect_clone().expect("a clonable material");
        let clone = clone.take::<LitObjectMaterial>().expect("the same type");
        assert_eq!(clone.surface, material.surface);
        assert_eq!(clone.lights, material.lights);
    }
}
