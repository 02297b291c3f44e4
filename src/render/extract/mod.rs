//! Main world → render world: clouds (with their validity) and the lights that illuminate them.

pub mod particles;

use bevy::{
    camera::visibility::ViewVisibility,
    light::{NotShadowCaster, NotShadowReceiver},
    math::Affine3A,
    platform::collections::HashMap,
    prelude::*,
    render::{Extract, sync_world::RenderEntity},
};

use crate::{
    atmosphere::{AtmosphereLight, TransmittanceCache},
    cloud::{CloudSkyLight, InvalidCloud, ParticleCloud, Particles, ParticlesValidity},
    ground::CloudGround,
    lod::{CloudLevelOfDetail, CloudLod},
    settings::{CloudQualitySettings, DefaultCloudQuality},
    shadow_maps::CloudLights,
};

pub use crate::shadow_maps::CloudLight;

/// A cloud as the render world sees it; only valid clouds are extracted.
#[derive(Component, Clone, Debug)]
pub struct ExtractedCloud {
    /// The cloud's particle asset.
    pub particles: AssetId<Particles>,
    /// Extinction per world metre at density 1.
    pub extinction: f32,
    /// Single-scattering albedo in `[0, 1]`.
    pub albedo: f32,
    /// Henyey–Greenstein anisotropy `g` in `(-1, 1)`.
    pub anisotropy: f32,
    /// World from cloud-local; the scale used for optical lengths is its largest factor.
    pub world_from_local: Affine3A,
    /// The cloud's quality knobs (its component, else the default resource).
    pub settings: CloudQualitySettings,
    /// The volume resolution its level of detail asks for (`settings.volume_resolution` when
    /// level of detail is off); the renderer moves to it when the cloud is next re-lit.
    pub lod_resolution: u32,
    /// Voxels per side of its fine density grid and light volumes: `settings`' own
    /// ([`CloudQualitySettings::light_resolution`]) until the cloud is prepared at the resolution
    /// it is illuminated at this frame, where it is lowered, if need be, to fit the adapter's
    /// storage binding.
    pub light_resolution: u32,
    /// Whether `lod_resolution` comes from the level of detail (the `CloudLevelOfDetail`
    /// resource is enabled and the cloud has a `CloudLod`): only its changes wait for a re-light.
    pub lod_enabled: bool,
    /// Visible in at least one view: such clouds, and those that shadow them, do illumination
    /// work.
    pub visible: bool,
    /// It shadows other clouds (no [`NotShadowCaster`]).
    pub casts_shadows: bool,
    /// Other clouds shadow it (no [`NotShadowReceiver`]).
    pub receives_shadows: bool,
    /// Per light of [`ExtractedCloudLights::lights`], the linear RGB part of its irradiance that
    /// reaches the cloud's centre through Bevy's `Atmosphere` ([`crate::atmosphere`]); empty
    /// (all of it) where the world has none.
    pub atmosphere_transmittance: Vec<Vec3>,
}

impl ExtractedCloud {
    /// Uniform scale of the cloud (the largest axis factor for a non-uniform transform).
    pub fn scale(&self) -> f32 {
        let m = self.world_from_local.matrix3;
        m.x_axis
            .length()
            .max(m.y_axis.length())
            .max(m.z_axis.length())
    }

    /// Whether its scattering volumes hold angular moments beside their means: an anisotropic
    /// medium (docs/illumination.md §4).
    pub fn has_moments(&self) -> bool {
        self.anisotropy != 0.0
    }

    /// A visible, isotropic, white cloud of unit extinction at the origin (unit tests).
    #[cfg(test)]
    pub(crate) fn for_test(settings: crate::settings::CloudQualitySettings) -> Self {
        Self {
            particles: AssetId::default(),
            extinction: 1.0,
            albedo: 1.0,
            anisotropy: 0.0,
            world_from_local: default(),
            lod_resolution: settings.volume_resolution,
            light_resolution: settings.light_resolution(),
            settings,
            lod_enabled: false,
            visible: true,
            casts_shadows: true,
            receives_shadows: true,
            atmosphere_transmittance: Vec::new(),
        }
    }

    /// The part of light `index`'s irradiance that reaches the cloud through the atmosphere.
    pub fn light_transmittance(&self, index: usize) -> Vec3 {
        self.atmosphere_transmittance
            .get(index)
            .copied()
            .unwrap_or(Vec3::ONE)
    }

    /// Rotation part, world from local.
    pub fn rotation(&self) -> Quat {
        let (_, rotation, _) = self.world_from_local.to_scale_rotation_translation();
        rotation
    }
}

/// Every directional light that lights clouds this frame (non-zero irradiance, not opted out),
/// and the sky's radiance.
#[derive(Resource, Clone, Debug, Default)]
pub struct ExtractedCloudLights {
    /// The directional lights.
    pub lights: Vec<CloudLight>,
    /// Linear RGB radiance of the sky ([`CloudSkyLight`]), black when refused.
    pub sky: Vec3,
    /// The ground that lights the clouds from below ([`CloudGround`]), if any and valid.
    pub ground: Option<CloudGround>,
}

impl ExtractedCloudLights {
    /// Whether anything lights the clouds.
    pub fn any(&self) -> bool {
        !self.lights.is_empty() || self.sky.max_element() > 0.0
    }
}

/// Remembers which clouds were refused and why (the message: a NaN in a problem never equals
/// itself), so each problem is reported once.
#[derive(Default)]
pub(crate) struct RefusedClouds(HashMap<Entity, String>);

/// A cloud as the main world has it.
type MainWorldCloud = (
    Entity,
    RenderEntity,
    &'static ParticleCloud,
    &'static GlobalTransform,
    &'static ViewVisibility,
    Option<&'static CloudQualitySettings>,
    Option<&'static CloudLod>,
    Option<&'static Name>,
    Has<NotShadowCaster>,
    Has<NotShadowReceiver>,
);

#[allow(clippy::too_many_arguments)] // a system's parameters
pub(crate) fn extract_clouds(
    mut commands: Commands,
    clouds: Extract<Query<MainWorldCloud>>,
    assets: Extract<Res<Assets<Particles>>>,
    validity: Extract<Res<ParticlesValidity>>,
    default_quality: Extract<Res<DefaultCloudQuality>>,
    level_of_detail: Extract<Res<CloudLevelOfDetail>>,
    air: Extract<AtmosphereLight>,
    mut transmittances: Local<TransmittanceCache>,
    mut refused: Local<RefusedClouds>,
) {
    transmittances.retain(|cloud| clouds.contains(cloud));
    for item in &clouds {
        let (entity, render_entity, cloud, transform, visibility, settings, lod, name, ..) = item;
        let (.., not_caster, not_receiver) = item;
        let settings = settings.copied().unwrap_or(default_quality.0);
        let lod_resolution = lod
            .filter(|_| level_of_detail.enabled())
            .map_or(settings.volume_resolution, |l| {
                l.resolution.min(settings.volume_resolution)
            });
        // Particles are validated once per asset change; an asset without a verdict yet (added
        // this frame before the events were written) is checked here.
        let particles = match validity.0.get(&cloud.particles.id()) {
            Some(verdict) => verdict.clone(),
            None => assets
                .get(&cloud.particles)
                .map_or(Ok(()), Particles::validate),
        };
        let verdict = validate(cloud, transform, &settings).and(particles.map_err(Into::into));
        let mut target = commands.entity(render_entity);
        match verdict.err() {
            Some(problem) => {
                let problem = problem.to_string();
                if refused.0.get(&entity) != Some(&problem) {
                    let label =
                        name.map_or_else(|| format!("{entity}"), |n| format!("{entity} ({n})"));
                    warn!("particle cloud {label} is not drawn: {problem}");
                    refused.0.insert(entity, problem);
                }
                target.remove::<ExtractedCloud>();
            }
            None => {
                refused.0.remove(&entity);
                target.insert(ExtractedCloud {
                    particles: cloud.particles.id(),
                    extinction: cloud.extinction,
                    albedo: cloud.albedo,
                    anisotropy: cloud.anisotropy,
                    world_from_local: transform.affine(),
                    settings,
                    lod_resolution,
                    light_resolution: settings.light_resolution(),
                    lod_enabled: lod.is_some() && level_of_detail.enabled(),
                    visible: visibility.get(),
                    casts_shadows: !not_caster,
                    receives_shadows: !not_receiver,
                    atmosphere_transmittance: air.transmittances(
                        entity,
                        transform.translation(),
                        &mut transmittances,
                    ),
                });
            }
        }
    }
}

/// Why a cloud cannot be rendered, naming the field and its value.
fn validate(
    cloud: &ParticleCloud,
    transform: &GlobalTransform,
    settings: &CloudQualitySettings,
) -> Result<(), InvalidCloud> {
    cloud.medium().validate()?;
    settings.validate()?;
    let affine = transform.affine();
    if !affine.is_finite() || affine.matrix3.determinant() == 0.0 {
        return Err(InvalidCloud::Transform(affine));
    }
    Ok(())
}

pub(crate) fn extract_cloud_lights(
    mut lights: ResMut<ExtractedCloudLights>,
    cloud_lights: Extract<Res<CloudLights>>,
    sky: Extract<Res<CloudSkyLight>>,
    ground: Extract<Option<Res<CloudGround>>>,
    mut refused: Local<[Option<String>; 2]>,
) {
    let [refused_sky, refused_ground] = &mut *refused;
    lights.sky = match sky.radiance() {
        Ok(radiance) => {
            *refused_sky = None;
            radiance
        }
        Err(problem) => {
            if refused_sky.as_ref() != Some(&problem) {
                warn!("{problem}; the clouds are lit as under a black sky");
                *refused_sky = Some(problem);
            }
            Vec3::ZERO
        }
    };
    lights.ground = match ground.as_deref().map(CloudGround::validate) {
        Some(Err(problem)) => {
            if refused_ground.as_ref() != Some(&problem) {
                warn!("{problem}; the clouds are lit as if there were no ground");
                *refused_ground = Some(problem);
            }
            None
        }
        valid => {
            *refused_ground = None;
            valid.and_then(Result::ok)
        }
    };
    // Hidden, dark or broken lights cost nothing: they are not among them.
    lights.lights.clone_from(&cloud_lights.0);
}
