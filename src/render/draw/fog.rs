//! Distance fog on the billboards (docs/physics.md, "Fog"): each view's fog (Bevy's
//! `DistanceFog` with the `distance_fog` feature) as a dynamic uniform of the billboards' group 0,
//! its falloff a pipeline key (`FogMode`, shader defs) and its values in [`CloudFogParams`].
//! `fog.wgsl` fogs every piece of every chord at its own distance, as Bevy fogs a mesh fragment.

use bevy::{
    prelude::*,
    render::{
        render_resource::{DynamicUniformBuffer, ShaderType},
        renderer::{RenderDevice, RenderQueue},
        view::ExtractedView,
    },
};

use crate::fog::{Falloff, Fog};
use crate::render::extract::ExtractedCloudLights;

/// Directional lights whose glow the fog shows (Bevy's `MAX_DIRECTIONAL_LIGHTS`); the rest
/// are left out. `fog.wgsl`'s arrays have this length (checked by the layout test).
pub const MAX_FOG_LIGHTS: usize = 10;

/// A view's fog, extracted from its camera's `DistanceFog` (valid ones only).
#[derive(Component, Clone, Copy, Debug, PartialEq)]
pub struct ExtractedCloudFog(pub Fog);

/// The falloff the billboard pipeline is specialized for (shader defs `FOG_*`).
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum FogMode {
    /// `FOG_LINEAR`.
    Linear,
    /// `FOG_EXPONENTIAL`.
    Exponential,
    /// `FOG_EXPONENTIAL_SQUARED`.
    ExponentialSquared,
    /// `FOG_ATMOSPHERIC`.
    Atmospheric,
}

impl FogMode {
    /// The mode of a falloff.
    pub fn of(falloff: &Falloff) -> Self {
        match falloff {
            Falloff::Linear { .. } => Self::Linear,
            Falloff::Exponential { .. } => Self::Exponential,
            Falloff::ExponentialSquared { .. } => Self::ExponentialSquared,
            Falloff::Atmospheric { .. } => Self::Atmospheric,
        }
    }

    /// Its shader defs: `DISTANCE_FOG` and the falloff's own.
    pub fn shader_defs(self) -> [&'static str; 2] {
        let falloff = match self {
            Self::Linear => "FOG_LINEAR",
            Self::Exponential => "FOG_EXPONENTIAL",
            Self::ExponentialSquared => "FOG_EXPONENTIAL_SQUARED",
            Self::Atmospheric => "FOG_ATMOSPHERIC",
        };
        ["DISTANCE_FOG", falloff]
    }
}

/// Mirror of `CloudFog` in `fog.wgsl`.
#[derive(ShaderType, Clone, Copy, Debug, Default)]
pub struct CloudFogParams {
    /// The fog's colour (linear RGB) and alpha.
    pub color: Vec4,
    /// The glow's colour about each light (linear RGB, its alpha multiplied in).
    pub directional_light_color: Vec3,
    /// `max(cos θ, 0)^exponent` about each light.
    pub directional_light_exponent: f32,
    /// `Linear`: (start, end, 0) metres; the exponentials: (density, 0, 0) per metre;
    /// `Atmospheric`: extinction per metre.
    pub falloff: Vec3,
    /// Lights in `to_light` and `irradiance`.
    pub light_count: u32,
    /// `Atmospheric`: in-scattering per metre.
    pub inscattering: Vec3,
    /// Uniform-buffer padding.
    pub _padding: u32,
    /// World unit direction towards each light (xyz).
    pub to_light: [Vec4; MAX_FOG_LIGHTS],
    /// Each light's irradiance, linear RGB (xyz).
    pub irradiance: [Vec4; MAX_FOG_LIGHTS],
}

impl CloudFogParams {
    /// The uniform of `fog` glowing about `lights`.
    pub fn new(fog: &Fog, lights: &ExtractedCloudLights) -> Self {
        let (falloff, inscattering) = match fog.falloff {
            Falloff::Linear { start, end } => (Vec3::new(start, end, 0.0), Vec3::ZERO),
            Falloff::Exponential { density } | Falloff::ExponentialSquared { density } => {
                (Vec3::new(density, 0.0, 0.0), Vec3::ZERO)
            }
            Falloff::Atmospheric {
                extinction,
                inscattering,
            } => (extinction, inscattering),
        };
        let mut params = Self {
            color: fog.color.extend(fog.alpha),
            directional_light_color: fog.directional_light_color,
            directional_light_exponent: fog.directional_light_exponent,
            falloff,
            inscattering,
            ..default()
        };
        if fog.directional_light_color != Vec3::ZERO {
            for (i, light) in lights.lights.iter().take(MAX_FOG_LIGHTS).enumerate() {
                params.to_light[i] = (-light.direction).extend(0.0);
                params.irradiance[i] = light.irradiance.extend(0.0);
                params.light_count = i as u32 + 1;
            }
        }
        params
    }
}

/// Every view's fog uniform, at its [`ViewCloudFogOffset`]; views without fog get an unused one.
#[derive(Resource, Default)]
pub struct CloudFogUniforms(pub DynamicUniformBuffer<CloudFogParams>);

/// Where a view's fog uniform is in [`CloudFogUniforms`].
#[derive(Component, Clone, Copy, Debug)]
pub struct ViewCloudFogOffset(pub u32);

/// Writes every view's fog uniform (a few hundred bytes per view).
pub(crate) fn prepare_cloud_fog(
    mut commands: Commands,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
    mut uniforms: ResMut<CloudFogUniforms>,
    lights: Res<ExtractedCloudLights>,
    views: Query<(Entity, Option<&ExtractedCloudFog>), With<ExtractedView>>,
) {
    let Some(mut writer) = uniforms.0.get_writer(views.iter().len(), &device, &queue) else {
        return;
    };
    for (entity, fog) in &views {
        let params = fog.map_or_else(default, |f| CloudFogParams::new(&f.0, &lights));
        commands
            .entity(entity)
            .insert(ViewCloudFogOffset(writer.write(&params)));
    }
}

/// A camera, its render entity and its fog.
#[cfg(feature = "distance_fog")]
type FoggedCamera = (
    Entity,
    bevy::render::sync_world::RenderEntity,
    Option<&'static bevy::pbr::DistanceFog>,
);

/// The fog of each camera with a valid `DistanceFog`; an invalid one is reported once and its
/// clouds are drawn unfogged.
#[cfg(feature = "distance_fog")]
pub(crate) fn extract_cloud_fog(
    mut commands: Commands,
    cameras: bevy::render::Extract<Query<FoggedCamera, With<Camera>>>,
    mut refused: Local<bevy::platform::collections::HashMap<Entity, String>>,
) {
    for (entity, render_entity, distance_fog) in &cameras {
        let fog = distance_fog
            .map(fog_of)
            .map(|fog| fog.validate().map(|()| fog).map_err(|e| e.to_string()));
        let mut target = commands.entity(render_entity);
        match fog {
            Some(Ok(fog)) => {
                refused.remove(&entity);
                target.insert(ExtractedCloudFog(fog));
            }
            Some(Err(problem)) => {
                if refused.get(&entity) != Some(&problem) {
                    warn!("camera {entity}: its clouds are drawn without fog: {problem}");
                    refused.insert(entity, problem);
                }
                target.remove::<ExtractedCloudFog>();
            }
            None => {
                target.remove::<ExtractedCloudFog>();
            }
        }
    }
}

/// Bevy's `DistanceFog` in linear RGB, the glow colour's alpha multiplied in.
#[cfg(feature = "distance_fog")]
pub fn fog_of(fog: &bevy::pbr::DistanceFog) -> Fog {
    use bevy::pbr::FogFalloff;
    let color = fog.color.to_linear();
    let glow = fog.directional_light_color.to_linear();
    Fog {
        color: color.to_vec3(),
        alpha: color.alpha,
        falloff: match fog.falloff {
            FogFalloff::Linear { start, end } => Falloff::Linear { start, end },
            FogFalloff::Exponential { density } => Falloff::Exponential { density },
            FogFalloff::ExponentialSquared { density } => Falloff::ExponentialSquared { density },
            FogFalloff::Atmospheric {
                extinction,
                inscattering,
            } => Falloff::Atmospheric {
                extinction,
                inscattering,
            },
        },
        directional_light_color: glow.to_vec3() * glow.alpha,
        directional_light_exponent: fog.directional_light_exponent,
    }
}

/// The `DistanceFog` that [`fog_of`] reads back as `fog` (a scene file's fog on its camera).
#[cfg(feature = "distance_fog")]
pub fn distance_fog(fog: &Fog) -> bevy::pbr::DistanceFog {
    use bevy::pbr::FogFalloff;
    let [r, g, b] = fog.color.to_array();
    let glow = fog.directional_light_color;
    bevy::pbr::DistanceFog {
        color: Color::linear_rgba(r, g, b, fog.alpha),
        directional_light_color: Color::linear_rgb(glow.x, glow.y, glow.z),
        directional_light_exponent: fog.directional_light_exponent,
        falloff: match fog.falloff {
            Falloff::Linear { start, end } => FogFalloff::Linear { start, end },
            Falloff::Exponential { density } => FogFalloff::Exponential { density },
            Falloff::ExponentialSquared { density } => FogFalloff::ExponentialSquared { density },
            Falloff::Atmospheric {
                extinction,
                inscattering,
            } => FogFalloff::Atmospheric {
                extinction,
                inscattering,
            },
        },
    }
}

#[cfg(all(test, feature = "distance_fog"))]
mod tests {
    use super::*;

    #[test]
    fn a_fog_survives_the_trip_through_distance_fog() {
        let fog = Fog {
            color: Vec3::new(0.2, 0.3, 0.4),
            alpha: 0.75,
            falloff: Falloff::Atmospheric {
                extinction: Vec3::new(0.1, 0.2, 0.3),
                inscattering: Vec3::new(0.3, 0.2, 0.1),
            },
            directional_light_color: Vec3::new(1.0, 0.5, 0.25),
            directional_light_exponent: 4.0,
        };
        assert_eq!(fog_of(&distance_fog(&fog)), fog);
        let lights = ExtractedCloudLights {
            lights: vec![crate::render::extract::CloudLight {
                entity: Entity::PLACEHOLDER,
                direction: Vec3::NEG_Y,
                irradiance: Vec3::splat(2.0),
            }],
            ..default()
        };
        let params = CloudFogParams::new(&fog, &lights);
        assert_eq!(params.light_count, 1);
        assert_eq!(params.to_light[0], Vec4::new(0.0, 1.0, 0.0, 0.0));
        assert_eq!(params.falloff, Vec3::new(0.1, 0.2, 0.3));
        assert_eq!(params.color.w, 0.75);
        // Without a glow colour, no light is sent.
        let plain = Fog {
            directional_light_color: Vec3::ZERO,
            ..fog
        };
        assert_eq!(CloudFogParams::new(&plain, &lights).light_count, 0);
    }
}
