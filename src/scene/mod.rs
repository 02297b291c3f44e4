//! Scene files (`docs/scene-format.md`): one still image of particle clouds, lights and opaque objects.
//!
//! [`SceneFile`] mirrors the RON text exactly (unknown fields are refused); [`Scene::load`] reads
//! a file, resolves particle files relative to it, validates every value and returns a [`Scene`]
//! ready for the real-time renderer, the CPU reference or the path tracer.

mod particle_paths;
mod validate;

use bevy::math::Vec3;
use serde::Deserialize;

pub use particle_paths::ParticlePaths;
pub use validate::apply_setting;
use validate::*;

use crate::fog::Fog;
use crate::particle::{LightSample, MAX_PARTICLE_EXTENT, Medium, Particle};
use crate::settings::CloudQualitySettings;

/// The pinhole camera of a scene.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneCamera {
    /// Eye position, world metres.
    pub position: Vec3,
    /// Point the camera looks at, world metres; must differ from `position`.
    pub look_at: Vec3,
    /// Up hint; default +Y. Must not be parallel to the viewing direction.
    #[serde(default = "default_up")]
    pub up: Vec3,
    /// Full vertical field of view in degrees, in (0, 180).
    pub vertical_fov_degrees: f32,
    /// Image width in pixels, > 0.
    pub width: u32,
    /// Image height in pixels, > 0.
    pub height: u32,
}

fn default_up() -> Vec3 {
    Vec3::Y
}

/// Where a cloud's particles come from.
#[derive(Clone, Debug, PartialEq, Deserialize)]
pub enum ParticleSource {
    /// Particles written in the scene file.
    Inline(Vec<Particle>),
    /// A PLY file (vertex properties `x y z radius density`), relative to the scene file.
    Ply(String),
    /// A CSV file with header `x,y,z,radius,density`, relative to the scene file.
    Csv(String),
}

/// One cloud entry of a scene file.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneCloud {
    /// World translation of the cloud's local origin, metres; default origin.
    #[serde(default)]
    pub translation: Vec3,
    /// The cloud's medium (extinction 1/m at density 1, albedo).
    pub medium: Medium,
    /// Its particles, in cloud-local metres.
    pub particles: ParticleSource,
}

/// Shape of an opaque object, in metres.
#[derive(Clone, Copy, Debug, PartialEq, Deserialize)]
pub enum ObjectShape {
    /// Axis-aligned box with these full extents.
    Cuboid(Vec3),
    /// Sphere of this radius.
    Sphere(f32),
}

/// An opaque object: it shows a constant radiance `color`, plus, with a `reflectance`, the light
/// it reflects as a Lambertian surface (docs/physics.md, "Lit objects").
#[derive(Clone, Copy, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneObject {
    /// The shape, metres.
    pub shape: ObjectShape,
    /// World position of the shape's centre, metres; default origin.
    #[serde(default)]
    pub translation: Vec3,
    /// Linear RGB radiance the object emits.
    pub color: Vec3,
    /// Linear RGB Lambertian reflectance in `[0, 1]`: the surface reflects `reflectance / π`
    /// times the irradiance of the lights and the sky that reaches it through the clouds.
    /// Default black: an unlit object.
    #[serde(default)]
    pub reflectance: Vec3,
}

/// A scene file as written (docs/scene-format.md).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneFile {
    /// The camera and image size.
    pub camera: SceneCamera,
    /// Linear RGB radiance behind everything; default black.
    #[serde(default)]
    pub background: Vec3,
    /// Read through a private mirror of `LightSample` that refuses unknown fields.
    #[serde(deserialize_with = "deserialize_lights")]
    pub lights: Vec<LightSample>,
    /// The clouds; may be empty.
    pub clouds: Vec<SceneCloud>,
    /// Opaque unlit objects; default none.
    #[serde(default)]
    pub objects: Vec<SceneObject>,
    /// Distance fog of the camera (Bevy's `DistanceFog`), written `fog: (color: …, falloff: …)`;
    /// default none.
    #[serde(default, deserialize_with = "deserialize_fog")]
    pub fog: Option<Fog>,
    /// Texels per side of the cloud shadow maps that lit objects take (real-time renderer only),
    /// in [`SHADOW_MAP_RESOLUTIONS`]; default [`DEFAULT_SHADOW_MAP_RESOLUTION`].
    #[serde(default = "default_shadow_map_resolution")]
    pub shadow_map_resolution: u32,
    /// Quality knobs for every cloud; missing fields take [`CloudQualitySettings`]' defaults.
    #[serde(default)]
    pub settings: CloudQualitySettings,
}

/// Texels per side of a scene's cloud shadow maps when it does not say.
pub const DEFAULT_SHADOW_MAP_RESOLUTION: u32 = 512;

/// The shadow-map resolutions a scene may ask for: up to 16 MiB of map per light.
pub const SHADOW_MAP_RESOLUTIONS: std::ops::RangeInclusive<u32> = 16..=2048;

fn default_shadow_map_resolution() -> u32 {
    DEFAULT_SHADOW_MAP_RESOLUTION
}

/// A scene's `fog` is written without RON's `Some(…)`.
fn deserialize_fog<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<Fog>, D::Error> {
    Fog::deserialize(d).map(Some)
}

/// A cloud with its particles loaded and validated.
#[derive(Clone, Debug, PartialEq)]
pub struct ResolvedCloud {
    /// World translation of the cloud's local origin, metres.
    pub translation: Vec3,
    /// The validated medium.
    pub medium: Medium,
    /// The validated particles, cloud-local metres.
    pub particles: Vec<Particle>,
}

/// A validated scene, particle files loaded: what every renderer consumes.
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    /// The camera and image size.
    pub camera: SceneCamera,
    /// Linear RGB radiance behind everything.
    pub background: Vec3,
    /// Directional lights: unit travel direction and irradiance (linear RGB).
    pub lights: Vec<LightSample>,
    /// The clouds, particles loaded.
    pub clouds: Vec<ResolvedCloud>,
    /// Opaque unlit objects.
    pub objects: Vec<SceneObject>,
    /// Distance fog of the camera, if any.
    pub fog: Option<Fog>,
    /// Texels per side of the cloud shadow maps that lit objects take.
    pub shadow_map_resolution: u32,
    /// Quality knobs for every cloud.
    pub settings: CloudQualitySettings,
}

// ---------------------------------------------------------------------------------------------
// Loading and validation
// ---------------------------------------------------------------------------------------------

use std::path::{Path, PathBuf};

use bevy::math::DVec3;

use crate::particle::InvalidMedium;
use crate::particle_files::{ParticleFileError, read_csv, read_ply};
use crate::settings::InvalidSettings;

/// Largest allowed `camera.width` and `camera.height`, pixels (the usual GPU texture limit).
pub const MAX_IMAGE_SIZE: u32 = 16384;

/// A light as written in a scene file: `(direction: (x, y, z), irradiance: (r, g, b))`.
/// Mirrors [`LightSample`] but refuses unknown fields.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneLight {
    direction: Vec3,
    irradiance: Vec3,
}

fn deserialize_lights<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<Vec<LightSample>, D::Error> {
    let lights = Vec::<SceneLight>::deserialize(d)?;
    Ok(lights
        .into_iter()
        .map(|l| LightSample {
            direction: l.direction,
            irradiance: l.irradiance,
        })
        .collect())
}

/// Why a scene cannot be used. Every message names the field (as a path like
/// `clouds[1].medium.albedo`), its value and what is allowed, or the file and position.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The scene file itself could not be read.
    #[error("cannot read scene file '{}': {error}", path.display())]
    Io {
        /// The scene file.
        path: PathBuf,
        /// The operating system's error.
        error: std::io::Error,
    },
    /// The RON text does not parse or does not match the format (syntax error, unknown or missing
    /// field, unknown variant, wrong type). Displayed as `origin:line:col: message`.
    #[error("{origin}:{error}")]
    Parse {
        /// The scene file's path, or `scene` for text given to `Scene::from_ron_str`.
        origin: String,
        /// RON's error with its line and column.
        error: Box<ron::error::SpannedError>,
    },
    /// A value is out of range: `path is value; allowed`.
    #[error("{path} is {value}; {allowed}")]
    Invalid {
        /// The field, e.g. `clouds[1].medium.albedo`.
        path: String,
        /// Its value as written.
        value: String,
        /// What is allowed.
        allowed: String,
    },
    /// A `settings` knob is out of range.
    #[error("settings.{} is {}; {}", .0.field(), .0.value(), .0.allowed())]
    Settings(InvalidSettings),
    /// A particle file could not be read or parsed. The message quotes none of the file's text:
    /// a scene file may name a file that is not particles, and its text must not reach a log.
    #[error("{field}: cannot read '{written}' (resolved to {}): {}", resolved.display(), error.detail_without_content())]
    ParticleFile {
        /// The field, e.g. `clouds[0].particles`.
        field: String,
        /// The path as written in the scene file.
        written: String,
        /// The path resolved against the scene file's directory.
        resolved: PathBuf,
        /// What went wrong, with the line.
        error: Box<ParticleFileError>,
    },
}

impl Scene {
    /// The ground that lights its clouds from below in the real-time renderer (docs/scene-format.md,
    /// "Lit objects"): the top face of its widest lit cuboid (its `reflectance` not black), as
    /// the horizontal plane [`CloudGround`](crate::CloudGround); `None` without one. The path
    /// tracer needs none: its light reflects off every lit object as it is.
    pub fn cloud_ground(&self) -> Option<crate::CloudGround> {
        let lit_cuboids = self.objects.iter().filter_map(|o| match o.shape {
            ObjectShape::Cuboid(size) if o.reflectance.max_element() > 0.0 => Some((size, o)),
            _ => None,
        });
        let (size, widest) =
            lit_cuboids.max_by(|(a, _), (b, _)| (a.x * a.z).total_cmp(&(b.x * b.z)))?;
        Some(crate::CloudGround {
            height: widest.translation.y + 0.5 * size.y,
            reflectance: widest.reflectance,
        })
    }

    /// Reads, parses and validates a scene file; particle files are resolved relative to its
    /// directory, and must lie inside it ([`ParticlePaths::InsideSceneFolder`]). Nothing invalid
    /// gets through: see [`SceneError`].
    pub fn load(path: &Path) -> Result<Scene, SceneError> {
        Scene::load_with(path, ParticlePaths::default())
    }

    /// [`Scene::load`], with the particle files `paths` allows.
    pub fn load_with(path: &Path, paths: ParticlePaths) -> Result<Scene, SceneError> {
        let text = std::fs::read_to_string(path).map_err(|error| SceneError::Io {
            path: path.to_path_buf(),
            error,
        })?;
        let base_dir = match path.parent() {
            Some(dir) if !dir.as_os_str().is_empty() => dir,
            _ => Path::new("."),
        };
        let file = parse_scene_file(&text, &path.display().to_string())?;
        Scene::from_scene_file_with(file, base_dir, paths)
    }

    /// Parses and validates scene text; particle files are resolved relative to `base_dir`.
    pub fn from_ron_str(text: &str, base_dir: &Path) -> Result<Scene, SceneError> {
        let file = parse_scene_file(text, "scene")?;
        Scene::from_scene_file(file, base_dir)
    }

    /// Validates a parsed scene file and loads its particle files (relative to `base_dir`, and
    /// inside it). Cheap checks (camera, lights, objects, settings, media) run before any
    /// particle file is read.
    pub fn from_scene_file(file: SceneFile, base_dir: &Path) -> Result<Scene, SceneError> {
        Scene::from_scene_file_with(file, base_dir, ParticlePaths::default())
    }

    /// [`Scene::from_scene_file`], with the particle files `paths` allows.
    pub fn from_scene_file_with(
        file: SceneFile,
        base_dir: &Path,
        paths: ParticlePaths,
    ) -> Result<Scene, SceneError> {
        validate_globals(
            &file.camera,
            file.background,
            &file.lights,
            &file.objects,
            &file.settings,
        )?;
        validate_fog(file.fog.as_ref())?;
        validate_shadow_map_resolution(file.shadow_map_resolution)?;
        for (i, cloud) in file.clouds.iter().enumerate() {
            validate_cloud_header(i, cloud.translation, &cloud.medium)?;
        }
        let mut clouds = Vec::with_capacity(file.clouds.len());
        for (i, cloud) in file.clouds.into_iter().enumerate() {
            let particles = load_particles(i, cloud.particles, base_dir, paths)?;
            clouds.push(ResolvedCloud {
                translation: cloud.translation,
                medium: cloud.medium,
                particles,
            });
        }
        Ok(Scene {
            camera: file.camera,
            background: file.background,
            lights: file.lights,
            clouds,
            objects: file.objects,
            fog: file.fog,
            shadow_map_resolution: file.shadow_map_resolution,
            settings: file.settings,
        })
    }

    /// Checks every value of a scene built in code by the same rules as [`Scene::load`].
    pub fn validate(&self) -> Result<(), SceneError> {
        validate_globals(
            &self.camera,
            self.background,
            &self.lights,
            &self.objects,
            &self.settings,
        )?;
        validate_fog(self.fog.as_ref())?;
        validate_shadow_map_resolution(self.shadow_map_resolution)?;
        for (i, cloud) in self.clouds.iter().enumerate() {
            validate_cloud_header(i, cloud.translation, &cloud.medium)?;
            validate_particles(i, &cloud.particles, "")?;
        }
        Ok(())
    }
}

/// Reads (for files) and validates the particles of cloud `i`.
fn load_particles(
    i: usize,
    source: ParticleSource,
    base_dir: &Path,
    paths: ParticlePaths,
) -> Result<Vec<Particle>, SceneError> {
    let (written, ply) = match source {
        ParticleSource::Inline(particles) => {
            validate_particles(i, &particles, "")?;
            return Ok(particles);
        }
        ParticleSource::Ply(written) => (written, true),
        ParticleSource::Csv(written) => (written, false),
    };
    if written.trim().is_empty() {
        return Err(invalid(
            format!("clouds[{i}].particles"),
            format!("{written:?}"),
            "the file name must not be empty",
        ));
    }
    let field = format!("clouds[{i}].particles");
    let (resolved, file) = particle_paths::resolve(&field, &written, base_dir, paths)?;
    let read = if ply {
        read_ply(&file)
    } else {
        read_csv(&file)
    };
    let particles = read.map_err(|error| SceneError::ParticleFile {
        field,
        written: written.clone(),
        resolved: resolved.clone(),
        error: Box::new(error),
    })?;
    let note = format!(
        " (particle file '{written}', resolved to {})",
        resolved.display()
    );
    validate_particles(i, &particles, &note)?;
    Ok(particles)
}

/// Parses RON into a [`SceneFile`] without validating values; `origin` names the text in errors.
fn parse_scene_file(text: &str, origin: &str) -> Result<SceneFile, SceneError> {
    ron::from_str(text).map_err(|error| SceneError::Parse {
        origin: origin.to_string(),
        error: Box::new(error),
    })
}

#[cfg(test)]
mod tests;
