//! The user-facing components and the [`Particles`] asset.

use bevy::{
    asset::Asset,
    camera::{
        primitives::Aabb,
        visibility::{VisibilityClass, add_visibility_class},
    },
    prelude::*,
};

use bevy::{math::Affine3A, platform::collections::HashMap};

use crate::particle::{InvalidMedium, Medium, Particle};
use crate::settings::InvalidSettings;

/// A set of particles: the shape and density of a cloud, in cloud-local metres.
///
/// Shared between clouds through its handle; uploaded to the GPU once per change.
#[derive(Asset, Reflect, Clone, Debug, Default, PartialEq)]
#[reflect(Default, Debug, PartialEq)]
pub struct Particles {
    /// The particles (positions and radii in cloud-local metres). Default: none.
    pub particles: Vec<Particle>,
}

impl Particles {
    /// Wraps a particle list.
    pub fn new(particles: Vec<Particle>) -> Self {
        Self { particles }
    }

    /// Local bounds `(min, max)` of the particles' supports (centre ± radius) that carry density,
    /// or `None` when no particle does.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        self.particles
            .iter()
            .filter(|p| p.density > 0.0)
            .map(|p| (p.position - p.radius, p.position + p.radius))
            .reduce(|(lo, hi), (a, b)| (lo.min(a), hi.max(b)))
    }

    /// Checks every particle (docs/physics.md ranges).
    pub fn validate(&self) -> Result<(), InvalidMedium> {
        self.particles
            .iter()
            .enumerate()
            .try_for_each(|(i, p)| p.validate(i))
    }
}

/// A participating medium made of particles: a cloud, smoke, fog, snow.
///
/// Lit by every [`DirectionalLight`] (without [`NotCloudLight`]), self-shadowed, multiply
/// scattered. Quality knobs: [`CloudQualitySettings`](crate::CloudQualitySettings) on the
/// same entity, else the [`DefaultCloudQuality`](crate::DefaultCloudQuality) resource.
///
/// The [`Transform`] may rotate, translate and scale uniformly (a non-uniform scale uses its
/// largest factor).
#[derive(Component, Clone, Debug, Reflect)]
#[reflect(Component, Default, Debug)]
#[require(Transform, Visibility, VisibilityClass)]
#[component(on_add = add_visibility_class::<ParticleCloud>)]
pub struct ParticleCloud {
    /// The particles, in cloud-local metres.
    pub particles: Handle<Particles>,
    /// Extinction per world metre at density 1 (`K`, 1/m), finite and `>= 0`. Default 10.
    pub extinction: f32,
    /// Single-scattering albedo in `[0, 1]`. Default 0.99.
    pub albedo: f32,
    /// Henyey–Greenstein anisotropy `g` in `(-1, 1)`: the mean cosine of the scattering angle
    /// (dimensionless). `0` (the default) scatters isotropically; `g > 0` scatters forward, so the
    /// cloud's edges glow with the sun behind it (water clouds: about 0.85). Non-zero, the
    /// multiple scattering carries the light's angular moments (docs/illumination.md §4): more
    /// memory and time than an isotropic cloud.
    pub anisotropy: f32,
}

impl Default for ParticleCloud {
    fn default() -> Self {
        Self::new(Handle::default())
    }
}

impl ParticleCloud {
    /// A cloud of the given particles with the default medium (extinction 10 /m, albedo 0.99,
    /// isotropic).
    pub fn new(particles: Handle<Particles>) -> Self {
        let medium = Medium::default();
        Self {
            particles,
            extinction: medium.extinction,
            albedo: medium.albedo,
            anisotropy: medium.anisotropy,
        }
    }

    /// Sets the medium.
    pub fn with_medium(mut self, medium: Medium) -> Self {
        self.extinction = medium.extinction;
        self.albedo = medium.albedo;
        self.anisotropy = medium.anisotropy;
        self
    }

    /// The medium of this cloud.
    pub fn medium(&self) -> Medium {
        Medium {
            extinction: self.extinction,
            albedo: self.albedo,
            anisotropy: self.anisotropy,
        }
    }
}

/// The sky that lights every cloud: a uniform radiance arriving from every direction
/// (docs/physics.md, "Transport"), `color` (linear) × `brightness`, in the units of a
/// `DirectionalLight`'s illuminance per steradian (cd/m² for lux), like Bevy's `AmbientLight`.
/// It enters the multiple-scattering grid from every side, so the clouds take the sky's colour
/// in their shadows. Default: black (off, and it then costs nothing). A value that is negative or
/// not finite is refused with a warning and the sky taken as black.
///
/// Bevy's `AmbientLight` is not used: it lights meshes per camera and defaults to non-black,
/// while a cloud's illumination is shared by every camera. To light clouds and meshes alike,
/// give both the same colour and brightness.
#[derive(Resource, Clone, Copy, Debug, PartialEq, Reflect)]
#[reflect(Resource, Default, Debug, PartialEq)]
pub struct CloudSkyLight {
    /// The sky's colour.
    pub color: Color,
    /// Multiplies `color`: radiance in cd/m² (the units of `E` per steradian). Default 0.
    pub brightness: f32,
}

impl Default for CloudSkyLight {
    fn default() -> Self {
        Self {
            color: Color::WHITE,
            brightness: 0.0,
        }
    }
}

impl CloudSkyLight {
    /// A sky of linear RGB radiance `radiance`.
    pub fn from_radiance(radiance: Vec3) -> Self {
        Self {
            color: Color::LinearRgba(LinearRgba::rgb(radiance.x, radiance.y, radiance.z)),
            brightness: 1.0,
        }
    }

    /// Linear RGB radiance, or why it is refused.
    pub fn radiance(&self) -> Result<Vec3, String> {
        let radiance = self.color.to_linear().to_vec3() * self.brightness;
        if radiance.is_finite() && radiance.min_element() >= 0.0 {
            Ok(radiance)
        } else {
            Err(format!(
                "`CloudSkyLight` radiance is {radiance}; every component must be finite and >= 0"
            ))
        }
    }
}

/// Put on a [`DirectionalLight`] to keep it from lighting particle clouds.
#[derive(Component, Clone, Copy, Debug, Default, Reflect)]
#[reflect(Component, Default, Debug)]
pub struct NotCloudLight;

/// The validation result of every loaded [`Particles`] asset, refreshed only when an asset is
/// added or modified, so that extraction does not re-check millions of particles each frame.
#[derive(Resource, Default, Debug)]
pub struct ParticlesValidity(pub HashMap<AssetId<Particles>, Result<(), InvalidMedium>>);

/// Why a cloud is not drawn (it is skipped with a warning; every other cloud still renders).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum InvalidCloud {
    /// Its medium or one of its particles is out of range.
    #[error(transparent)]
    Medium(#[from] InvalidMedium),
    /// Its `CloudQualitySettings` (or the `DefaultCloudQuality`) is out of range.
    #[error("CloudQualitySettings: {0}")]
    Settings(#[from] InvalidSettings),
    /// Its `GlobalTransform` is not finite or not invertible.
    #[error("`GlobalTransform` is {0:?}; it must be finite and invertible")]
    Transform(Affine3A),
}

/// The plugin's systems in the main world, to order your own systems against.
#[derive(SystemSet, Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum CloudSystems {
    /// Validates the `Particles` assets added or changed this frame (after Bevy's asset events).
    ValidateParticles,
    /// Sets each cloud's `Aabb` from its particles (in `VisibilitySystems::CalculateBounds`).
    CalculateBounds,
    /// Sets each cloud's `CloudLod` from the cameras (after the transforms and the bounds).
    LevelOfDetail,
}

/// Validates the particle assets that changed this frame (after Bevy wrote the asset events).
pub(crate) fn validate_changed_particles(
    mut events: MessageReader<AssetEvent<Particles>>,
    assets: Res<Assets<Particles>>,
    mut validity: ResMut<ParticlesValidity>,
) {
    for event in events.read() {
        match *event {
            AssetEvent::Added { id } | AssetEvent::Modified { id } => {
                if let Some(particles) = assets.get(id) {
                    validity.0.insert(id, particles.validate());
                }
            }
            AssetEvent::Removed { id } | AssetEvent::Unused { id } => {
                validity.0.remove(&id);
            }
            AssetEvent::LoadedWithDependencies { .. } => {}
        }
    }
}

/// Keeps each cloud's [`Aabb`] equal to its particles' bounds, so clouds are frustum-culled like
/// meshes. Runs when the cloud or its asset changes.
pub(crate) fn update_cloud_aabbs(
    mut commands: Commands,
    mut events: MessageReader<AssetEvent<Particles>>,
    clouds: Query<(Entity, Ref<ParticleCloud>)>,
    assets: Res<Assets<Particles>>,
) {
    let changed: Vec<AssetId<Particles>> = events
        .read()
        .filter_map(|e| match e {
            AssetEvent::Added { id }
            | AssetEvent::Modified { id }
            | AssetEvent::LoadedWithDependencies { id } => Some(*id),
            _ => None,
        })
        .collect();
    for (entity, cloud) in &clouds {
        if !cloud.is_changed() && !changed.contains(&cloud.particles.id()) {
            continue;
        }
        let Some(bounds) = assets.get(&cloud.particles).and_then(Particles::bounds) else {
            continue;
        };
        commands
            .entity(entity)
            .try_insert(Aabb::from_min_max(bounds.0, bounds.1));
    }
}
