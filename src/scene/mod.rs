//! Scene files (`docs/scene-format.md`): one still image of particle clouds, lights and opaque objects.
//!
//! [`SceneFile`] mirrors the RON text exactly (unknown fields are refused); [`Scene::load`] reads
//! a file, resolves particle files relative to it, validates every value and returns a [`Scene`]
//! ready for the real-time renderer, the CPU reference or the path tracer.

mod particle_paths;

use bevy::math::Vec3;
use serde::Deserialize;

pub use particle_paths::ParticlePaths;

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

fn invalid(
    path: impl Into<String>,
    value: impl std::fmt::Display,
    allowed: impl Into<String>,
) -> SceneError {
    SceneError::Invalid {
        path: path.into(),
        value: value.to_string(),
        allowed: allowed.into(),
    }
}

/// `(x, y, z)` with Rust's shortest round-tripping float formatting.
fn fmt_vec3(v: Vec3) -> String {
    format!("({}, {}, {})", v.x, v.y, v.z)
}

fn check_finite(path: &str, v: Vec3) -> Result<(), SceneError> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(invalid(
            path,
            fmt_vec3(v),
            "every coordinate must be finite",
        ))
    }
}

fn check_radiance(path: &str, v: Vec3) -> Result<(), SceneError> {
    if v.is_finite() && v.cmpge(Vec3::ZERO).all() {
        Ok(())
    } else {
        Err(invalid(
            path,
            fmt_vec3(v),
            "every component must be finite and >= 0",
        ))
    }
}

/// Maps a medium or particle error of cloud `cloud` to its field path; `note` (e.g. the particle
/// file) is appended to the message.
fn medium_error(cloud: usize, error: InvalidMedium, note: &str) -> SceneError {
    let p = format!("clouds[{cloud}]");
    match error {
        InvalidMedium::Position { index, value } => invalid(
            format!("{p}.particles[{index}].position"),
            fmt_vec3(value),
            format!("every coordinate must be finite and within ±{MAX_PARTICLE_EXTENT:e} m{note}"),
        ),
        InvalidMedium::Radius { index, value } => invalid(
            format!("{p}.particles[{index}].radius"),
            value,
            format!("it must be > 0 and at most {MAX_PARTICLE_EXTENT:e} m{note}"),
        ),
        InvalidMedium::Density { index, value } => invalid(
            format!("{p}.particles[{index}].density"),
            value,
            format!("it must be finite and >= 0{note}"),
        ),
        InvalidMedium::Extinction(value) => invalid(
            format!("{p}.medium.extinction"),
            value,
            "it must be finite and >= 0",
        ),
        InvalidMedium::Albedo(value) => {
            invalid(format!("{p}.medium.albedo"), value, "it must lie in [0, 1]")
        }
        InvalidMedium::Anisotropy(value) => invalid(
            format!("{p}.medium.anisotropy"),
            value,
            "it must lie in (-1, 1)",
        ),
    }
}

/// Sets one field of `settings` from a `field=value` assignment written as in a scene file's
/// `settings` (for example `volume_resolution=64` or `compositing=Sorted`), as the tools' `--set`
/// does, then checks every knob's range.
pub fn apply_setting(
    settings: &mut CloudQualitySettings,
    assignment: &str,
) -> Result<(), SceneError> {
    use bevy::reflect::GetPath;
    let Some((field, value)) = assignment.split_once('=') else {
        return Err(invalid(
            "--set",
            assignment,
            "it must be field=value, e.g. volume_resolution=64",
        ));
    };
    let field = field.trim();
    // RON checks the field's name and the value's type, with the scene file's messages.
    let parsed: CloudQualitySettings = ron::from_str(&format!("({field}: {})", value.trim()))
        .map_err(|error| SceneError::Parse {
            origin: format!("--set {assignment}"),
            error: Box::new(error),
        })?;
    let unknown = || invalid("--set", assignment, "the field is not a settings field");
    let source = parsed.reflect_path(field).map_err(|_| unknown())?;
    settings
        .reflect_path_mut(field)
        .map_err(|_| unknown())?
        .apply(source);
    settings.validate().map_err(SceneError::Settings)
}

fn validate_shadow_map_resolution(resolution: u32) -> Result<(), SceneError> {
    if SHADOW_MAP_RESOLUTIONS.contains(&resolution) {
        return Ok(());
    }
    let (lo, hi) = (SHADOW_MAP_RESOLUTIONS.start(), SHADOW_MAP_RESOLUTIONS.end());
    Err(invalid(
        "shadow_map_resolution",
        resolution,
        format!("allowed: {lo}..={hi}"),
    ))
}

fn validate_fog(fog: Option<&Fog>) -> Result<(), SceneError> {
    fog.map_or(Ok(()), |f| {
        f.validate()
            .map_err(|e| invalid(format!("fog.{}", e.field), e.value, e.allowed))
    })
}

fn validate_camera(c: &SceneCamera) -> Result<(), SceneError> {
    check_finite("camera.position", c.position)?;
    check_finite("camera.look_at", c.look_at)?;
    check_finite("camera.up", c.up)?;
    let view = c.look_at.as_dvec3() - c.position.as_dvec3();
    if view == DVec3::ZERO {
        return Err(invalid(
            "camera.look_at",
            fmt_vec3(c.look_at),
            format!(
                "it must differ from camera.position {}",
                fmt_vec3(c.position)
            ),
        ));
    }
    let up = c.up.as_dvec3();
    if up == DVec3::ZERO {
        return Err(invalid("camera.up", fmt_vec3(c.up), "it must not be zero"));
    }
    // sine of the angle between `up` and the viewing direction
    let sine = view.normalize().cross(up.normalize()).length();
    if sine.is_nan() || sine <= 1e-6 {
        return Err(invalid(
            "camera.up",
            fmt_vec3(c.up),
            format!(
                "it must not be parallel to the viewing direction look_at - position = {}",
                fmt_vec3(view.as_vec3())
            ),
        ));
    }
    let fov = c.vertical_fov_degrees;
    if !(fov > 0.0 && fov < 180.0) {
        return Err(invalid(
            "camera.vertical_fov_degrees",
            fov,
            "it must lie in (0, 180)",
        ));
    }
    for (name, v) in [("camera.width", c.width), ("camera.height", c.height)] {
        if !(1..=MAX_IMAGE_SIZE).contains(&v) {
            return Err(invalid(
                name,
                v,
                format!("it must be > 0 and <= {MAX_IMAGE_SIZE}"),
            ));
        }
    }
    Ok(())
}

fn validate_object(i: usize, o: &SceneObject) -> Result<(), SceneError> {
    match o.shape {
        ObjectShape::Cuboid(e) => {
            if !(e.is_finite() && e.cmpgt(Vec3::ZERO).all()) {
                return Err(invalid(
                    format!("objects[{i}].shape"),
                    format!("Cuboid({})", fmt_vec3(e)),
                    "every extent must be finite and > 0",
                ));
            }
        }
        ObjectShape::Sphere(r) => {
            if !(r.is_finite() && r > 0.0) {
                return Err(invalid(
                    format!("objects[{i}].shape"),
                    format!("Sphere({r})"),
                    "the radius must be finite and > 0",
                ));
            }
        }
    }
    check_finite(&format!("objects[{i}].translation"), o.translation)?;
    check_radiance(&format!("objects[{i}].color"), o.color)?;
    let r = o.reflectance;
    if !(r.is_finite() && r.cmpge(Vec3::ZERO).all() && r.cmple(Vec3::ONE).all()) {
        return Err(invalid(
            format!("objects[{i}].reflectance"),
            fmt_vec3(r),
            "every component must lie in [0, 1]",
        ));
    }
    Ok(())
}

/// Everything but the clouds.
fn validate_globals(
    camera: &SceneCamera,
    background: Vec3,
    lights: &[LightSample],
    objects: &[SceneObject],
    settings: &CloudQualitySettings,
) -> Result<(), SceneError> {
    validate_camera(camera)?;
    check_radiance("background", background)?;
    for (i, l) in lights.iter().enumerate() {
        let path = format!("lights[{i}].direction");
        check_finite(&path, l.direction)?;
        if l.direction == Vec3::ZERO {
            return Err(invalid(path, fmt_vec3(l.direction), "it must not be zero"));
        }
        check_radiance(&format!("lights[{i}].irradiance"), l.irradiance)?;
    }
    for (i, o) in objects.iter().enumerate() {
        validate_object(i, o)?;
    }
    settings.validate().map_err(SceneError::Settings)
}

/// A cloud's translation and medium.
fn validate_cloud_header(i: usize, translation: Vec3, medium: &Medium) -> Result<(), SceneError> {
    check_finite(&format!("clouds[{i}].translation"), translation)?;
    medium.validate().map_err(|e| medium_error(i, e, ""))
}

fn validate_particles(i: usize, particles: &[Particle], note: &str) -> Result<(), SceneError> {
    particles
        .iter()
        .enumerate()
        .try_for_each(|(j, p)| p.validate(j))
        .map_err(|e| medium_error(i, e, note))
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
mod tests {
    use super::*;
    use crate::particle_files::{write_csv, write_ply_ascii, write_ply_binary};
    use crate::settings::ScatterStencil;

    /// The example of docs/scene-format.md (its first RON block), read from the document itself,
    /// so that the example users copy is the one tested.
    fn example() -> &'static str {
        let doc = include_str!("../../docs/scene-format.md");
        let start = doc.find("```ron\n").expect("a RON block") + "```ron\n".len();
        &doc[start..start + doc[start..].find("```").expect("its end")]
    }

    /// The example with every optional field left out.
    const MINIMAL: &str = r#"(
    camera: (position: (0.0, 0.6, 6.0), look_at: (0.0, 0.0, 0.0), vertical_fov_degrees: 38.0, width: 160, height: 120),
    lights: [(direction: (-0.5, -0.8, -0.35), irradiance: (1.0, 0.97, 0.9))],
    clouds: [(medium: (extinction: 10, albedo: 1), particles: Inline([]))],
)"#;

    fn here() -> &'static Path {
        Path::new(".")
    }

    fn tmp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("bpc_scene_{}_{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn example_file() -> SceneFile {
        ron::from_str(example()).unwrap()
    }

    /// The clouds' ground is the top face of the widest lit cuboid: unlit objects and spheres
    /// are not grounds.
    #[test]
    fn the_widest_lit_cuboid_is_the_clouds_ground() {
        let mut scene = Scene::from_ron_str(MINIMAL, here()).unwrap();
        assert_eq!(scene.cloud_ground(), None);
        let object = |shape, y: f32, reflectance: Vec3| SceneObject {
            shape,
            translation: Vec3::new(3.0, y, -1.0),
            color: Vec3::ZERO,
            reflectance,
        };
        let lit = Vec3::new(0.3, 0.35, 0.25);
        scene.objects = vec![
            object(
                ObjectShape::Cuboid(Vec3::new(100.0, 1.0, 100.0)),
                5.0,
                Vec3::ZERO,
            ),
            object(ObjectShape::Sphere(50.0), 0.0, lit),
            object(
                ObjectShape::Cuboid(Vec3::new(2.0, 4.0, 2.0)),
                0.0,
                Vec3::ONE,
            ),
            object(ObjectShape::Cuboid(Vec3::new(30.0, 1.0, 30.0)), -0.5, lit),
        ];
        let ground = scene.cloud_ground().expect("a ground");
        assert_eq!((ground.height, ground.reflectance), (0.0, lit));
    }

    #[test]
    fn fog_is_read_with_its_defaults_and_checked() {
        use crate::fog::Falloff;
        let with_fog = |fog: &str| {
            MINIMAL.replacen(
                "    clouds: [",
                &format!("    fog: {fog},\n    clouds: ["),
                1,
            )
        };
        let scene = Scene::from_ron_str(
            &with_fog("(color: (0.2, 0.3, 0.4), falloff: Exponential(density: 0.1))"),
            here(),
        )
        .unwrap();
        let fog = scene.fog.unwrap();
        assert_eq!(fog.falloff, Falloff::Exponential { density: 0.1 });
        assert_eq!((fog.alpha, fog.directional_light_exponent), (1.0, 8.0));
        assert_eq!(fog.directional_light_color, Vec3::ZERO);
        let minimal = Scene::from_ron_str(MINIMAL, here()).unwrap();
        assert_eq!(minimal.fog, None);
        assert_eq!(minimal.shadow_map_resolution, DEFAULT_SHADOW_MAP_RESOLUTION);
        let with_maps = |n: u32| {
            MINIMAL.replacen(
                "    clouds: [",
                &format!("    shadow_map_resolution: {n},\n    clouds: ["),
                1,
            )
        };
        assert_eq!(
            Scene::from_ron_str(&with_maps(96), here())
                .unwrap()
                .shadow_map_resolution,
            96
        );
        assert_eq!(
            Scene::from_ron_str(&with_maps(8), here())
                .unwrap_err()
                .to_string(),
            "shadow_map_resolution is 8; allowed: 16..=2048"
        );
        let e = Scene::from_ron_str(
            &with_fog("(color: (0.2, 0.3, 0.4), falloff: Linear(start: 10, end: 2))"),
            here(),
        )
        .unwrap_err()
        .to_string();
        assert_eq!(
            e,
            "fog.falloff is Linear(start: 10, end: 2); start and end must be finite, start < end"
        );
        let e = Scene::from_ron_str(
            &with_fog("(color: (0.2, 0.3, 0.4), falloff: Exponential(density: 0.1), density: 2)"),
            here(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("density"), "{e}");
    }

    #[test]
    fn settings_are_set_from_assignments_and_checked() {
        let mut settings = CloudQualitySettings::default();
        apply_setting(&mut settings, "volume_resolution=64").unwrap();
        apply_setting(&mut settings, "compositing = Sorted").unwrap();
        apply_setting(&mut settings, "draw_method=Compute").unwrap();
        assert_eq!(settings.volume_resolution, 64);
        assert_eq!(settings.compositing, crate::Compositing::Sorted);
        assert_eq!(settings.draw_method, crate::DrawMethod::Compute);
        let e = apply_setting(&mut settings, "draw_method=Tiled").unwrap_err();
        assert!(matches!(e, SceneError::Parse { .. }), "{e}");
        assert!(e.to_string().contains("Raster"), "{e}");
        let e = apply_setting(&mut settings, "chord_segments=99").unwrap_err();
        assert_eq!(
            e.to_string(),
            "settings.chord_segments is 99; allowed is 1..=16"
        );
        let e = apply_setting(&mut settings, "resolution=64")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("--set resolution=64") && e.contains("resolution"),
            "{e}"
        );
        let e = apply_setting(&mut settings, "volume_resolution")
            .unwrap_err()
            .to_string();
        assert!(e.contains("field=value"), "{e}");
        let e = apply_setting(&mut settings, "volume_resolution=abc").unwrap_err();
        assert!(matches!(e, SceneError::Parse { .. }), "{e}");
    }

    #[test]
    fn example_parses_with_its_values() {
        let s = Scene::from_ron_str(example(), here()).unwrap();
        assert_eq!(s.camera.position, Vec3::new(0.0, 0.6, 6.0));
        assert_eq!(s.camera.look_at, Vec3::ZERO);
        assert_eq!(s.camera.up, Vec3::Y);
        assert_eq!(s.camera.vertical_fov_degrees, 38.0);
        assert_eq!((s.camera.width, s.camera.height), (160, 120));
        assert_eq!(s.background, Vec3::ZERO);
        assert_eq!(
            s.lights,
            vec![LightSample {
                direction: Vec3::new(-0.5, -0.8, -0.35),
                irradiance: Vec3::new(1.0, 0.97, 0.9)
            }]
        );
        assert_eq!(
            s.clouds,
            vec![ResolvedCloud {
                translation: Vec3::ZERO,
                medium: Medium {
                    extinction: 10.0,
                    albedo: 0.99,
                    ..Default::default()
                },
                particles: vec![
                    Particle {
                        position: Vec3::new(0.1, 0.2, 0.3),
                        radius: 0.2,
                        density: 0.8
                    },
                    Particle {
                        position: Vec3::new(-0.3, 0.0, 0.1),
                        radius: 0.25,
                        density: 1.0
                    },
                ],
            }]
        );
        assert_eq!(
            s.objects,
            vec![SceneObject {
                shape: ObjectShape::Cuboid(Vec3::new(0.8, 3.0, 0.3)),
                translation: Vec3::new(0.9, 0.0, 1.8),
                color: Vec3::splat(0.05),
                reflectance: Vec3::ZERO,
            }]
        );
        assert_eq!(
            s.settings,
            CloudQualitySettings {
                volume_resolution: 128,
                scatter_iterations: 16,
                ..Default::default()
            }
        );
        assert_eq!(s.settings.scatter_stencil, ScatterStencil::default());
        s.validate().unwrap();
    }

    #[test]
    fn optional_fields_take_their_defaults() {
        let s = Scene::from_ron_str(MINIMAL, here()).unwrap();
        assert_eq!(s.camera.up, Vec3::Y);
        assert_eq!(s.background, Vec3::ZERO);
        assert!(s.objects.is_empty());
        assert_eq!(s.settings, CloudQualitySettings::default());
        assert_eq!(s.clouds[0].translation, Vec3::ZERO);
        // integer literals are accepted for float fields; an empty cloud is allowed
        assert_eq!(
            s.clouds[0].medium,
            Medium {
                extinction: 10.0,
                albedo: 1.0,
                anisotropy: 0.0,
            }
        );
        assert!(s.clouds[0].particles.is_empty());
        let text = MINIMAL.replace("albedo: 1)", "albedo: 1, anisotropy: 0.7)");
        let s = Scene::from_ron_str(&text, here()).unwrap();
        assert_eq!(s.clouds[0].medium.anisotropy, 0.7);
        // a sphere object and the non-default stencil parse too
        let text = MINIMAL.replace(
            "\n)",
            "objects: [(shape: Sphere(0.5), color: (1, 2, 3))], settings: (scatter_stencil: Paper, forward_scattering: 0.5, compositing: ViewTransmittance))",
        );
        let s = Scene::from_ron_str(&text, here()).unwrap();
        assert_eq!(
            s.objects,
            vec![SceneObject {
                shape: ObjectShape::Sphere(0.5),
                translation: Vec3::ZERO,
                color: Vec3::new(1.0, 2.0, 3.0),
                reflectance: Vec3::ZERO,
            }]
        );
        assert_eq!(s.settings.scatter_stencil, ScatterStencil::Paper);
        assert_eq!(s.settings.forward_scattering, 0.5);
        assert_eq!(
            s.settings.compositing,
            crate::settings::Compositing::ViewTransmittance
        );
        assert_eq!(
            s.settings.volume_resolution,
            CloudQualitySettings::default().volume_resolution
        );
    }

    type Mutation = fn(&mut SceneFile);

    fn cloud0(f: &mut SceneFile) -> &mut SceneCloud {
        &mut f.clouds[0]
    }

    fn inline(f: &mut SceneFile, cloud: usize) -> &mut Vec<Particle> {
        match &mut f.clouds[cloud].particles {
            ParticleSource::Inline(p) => p,
            _ => unreachable!(),
        }
    }

    /// Every validation rule: (mutation of the example, the exact expected message).
    const RULES: &[(Mutation, &str)] = &[
        (
            |f| f.camera.position.x = f32::NAN,
            "camera.position is (NaN, 0.6, 6); every coordinate must be finite",
        ),
        (
            |f| f.camera.look_at.z = f32::INFINITY,
            "camera.look_at is (0, 0, inf); every coordinate must be finite",
        ),
        (
            |f| f.camera.up.y = f32::NEG_INFINITY,
            "camera.up is (0, -inf, 0); every coordinate must be finite",
        ),
        (
            |f| f.camera.look_at = f.camera.position,
            "camera.look_at is (0, 0.6, 6); it must differ from camera.position (0, 0.6, 6)",
        ),
        (
            |f| f.camera.up = Vec3::ZERO,
            "camera.up is (0, 0, 0); it must not be zero",
        ),
        (
            |f| f.camera.up = Vec3::new(0.0, -0.3, -3.0),
            "camera.up is (0, -0.3, -3); it must not be parallel to the viewing direction look_at - position = (0, -0.6, -6)",
        ),
        (
            |f| f.camera.vertical_fov_degrees = 190.0,
            "camera.vertical_fov_degrees is 190; it must lie in (0, 180)",
        ),
        (
            |f| f.camera.vertical_fov_degrees = 180.0,
            "camera.vertical_fov_degrees is 180; it must lie in (0, 180)",
        ),
        (
            |f| f.camera.vertical_fov_degrees = 0.0,
            "camera.vertical_fov_degrees is 0; it must lie in (0, 180)",
        ),
        (
            |f| f.camera.vertical_fov_degrees = f32::NAN,
            "camera.vertical_fov_degrees is NaN; it must lie in (0, 180)",
        ),
        (
            |f| f.camera.width = 0,
            "camera.width is 0; it must be > 0 and <= 16384",
        ),
        (
            |f| f.camera.height = 16385,
            "camera.height is 16385; it must be > 0 and <= 16384",
        ),
        (
            |f| f.background = Vec3::new(-1.0, 0.0, 0.0),
            "background is (-1, 0, 0); every component must be finite and >= 0",
        ),
        (
            |f| f.background.z = f32::NAN,
            "background is (0, 0, NaN); every component must be finite and >= 0",
        ),
        (
            |f| f.lights[0].direction = Vec3::ZERO,
            "lights[0].direction is (0, 0, 0); it must not be zero",
        ),
        (
            |f| f.lights[0].direction.x = f32::NAN,
            "lights[0].direction is (NaN, -0.8, -0.35); every coordinate must be finite",
        ),
        (
            |f| f.lights[0].irradiance.y = -0.5,
            "lights[0].irradiance is (1, -0.5, 0.9); every component must be finite and >= 0",
        ),
        (
            |f| {
                f.lights.push(LightSample {
                    direction: Vec3::ZERO,
                    irradiance: Vec3::ONE,
                })
            },
            "lights[1].direction is (0, 0, 0); it must not be zero",
        ),
        (
            |f| cloud0(f).translation.y = f32::INFINITY,
            "clouds[0].translation is (0, inf, 0); every coordinate must be finite",
        ),
        (
            |f| cloud0(f).medium.albedo = 1.5,
            "clouds[0].medium.albedo is 1.5; it must lie in [0, 1]",
        ),
        (
            |f| cloud0(f).medium.albedo = -0.1,
            "clouds[0].medium.albedo is -0.1; it must lie in [0, 1]",
        ),
        (
            |f| cloud0(f).medium.albedo = f32::NAN,
            "clouds[0].medium.albedo is NaN; it must lie in [0, 1]",
        ),
        (
            |f| cloud0(f).medium.anisotropy = 1.0,
            "clouds[0].medium.anisotropy is 1; it must lie in (-1, 1)",
        ),
        (
            |f| cloud0(f).medium.anisotropy = f32::NAN,
            "clouds[0].medium.anisotropy is NaN; it must lie in (-1, 1)",
        ),
        (
            |f| cloud0(f).medium.extinction = -1.0,
            "clouds[0].medium.extinction is -1; it must be finite and >= 0",
        ),
        (
            |f| cloud0(f).medium.extinction = f32::INFINITY,
            "clouds[0].medium.extinction is inf; it must be finite and >= 0",
        ),
        (
            |f| inline(f, 0)[1].radius = -0.2,
            "clouds[0].particles[1].radius is -0.2; it must be > 0 and at most 1e15 m",
        ),
        (
            |f| inline(f, 0)[0].radius = 0.0,
            "clouds[0].particles[0].radius is 0; it must be > 0 and at most 1e15 m",
        ),
        (
            |f| inline(f, 0)[1].radius = f32::NAN,
            "clouds[0].particles[1].radius is NaN; it must be > 0 and at most 1e15 m",
        ),
        (
            |f| inline(f, 0)[1].density = -1.0,
            "clouds[0].particles[1].density is -1; it must be finite and >= 0",
        ),
        (
            |f| inline(f, 0)[0].density = f32::INFINITY,
            "clouds[0].particles[0].density is inf; it must be finite and >= 0",
        ),
        (
            |f| inline(f, 0)[1].position.z = f32::NAN,
            "clouds[0].particles[1].position is (-0.3, 0, NaN); every coordinate must be finite and within ±1e15 m",
        ),
        (
            |f| inline(f, 0)[0].position.x = 3e38,
            "clouds[0].particles[0].position is (300000000000000000000000000000000000000, 0.2, 0.3); every coordinate must be finite and within ±1e15 m",
        ),
        (
            |f| inline(f, 0)[1].radius = 2e15,
            "clouds[0].particles[1].radius is 2000000000000000; it must be > 0 and at most 1e15 m",
        ),
        (
            |f| {
                let mut c = f.clouds[0].clone();
                c.medium.albedo = 2.0;
                f.clouds.push(c);
            },
            "clouds[1].medium.albedo is 2; it must lie in [0, 1]",
        ),
        (
            |f| {
                let mut c = f.clouds[0].clone();
                c.particles = ParticleSource::Inline(vec![Particle::default(); 4]);
                f.clouds.push(c);
                inline(f, 1)[3].radius = 1.0;
            },
            "clouds[1].particles[0].radius is 0; it must be > 0 and at most 1e15 m",
        ),
        (
            |f| f.objects[0].shape = ObjectShape::Cuboid(Vec3::new(0.8, 0.0, 0.3)),
            "objects[0].shape is Cuboid((0.8, 0, 0.3)); every extent must be finite and > 0",
        ),
        (
            |f| f.objects[0].shape = ObjectShape::Cuboid(Vec3::new(0.8, f32::INFINITY, 0.3)),
            "objects[0].shape is Cuboid((0.8, inf, 0.3)); every extent must be finite and > 0",
        ),
        (
            |f| f.objects[0].shape = ObjectShape::Sphere(-1.0),
            "objects[0].shape is Sphere(-1); the radius must be finite and > 0",
        ),
        (
            |f| f.objects[0].shape = ObjectShape::Sphere(f32::NAN),
            "objects[0].shape is Sphere(NaN); the radius must be finite and > 0",
        ),
        (
            |f| f.objects[0].translation.x = f32::NAN,
            "objects[0].translation is (NaN, 0, 1.8); every coordinate must be finite",
        ),
        (
            |f| f.objects[0].color.x = -0.05,
            "objects[0].color is (-0.05, 0.05, 0.05); every component must be finite and >= 0",
        ),
        (
            |f| f.objects[0].reflectance = Vec3::new(0.5, 1.2, 0.5),
            "objects[0].reflectance is (0.5, 1.2, 0.5); every component must lie in [0, 1]",
        ),
        (
            |f| f.objects[0].reflectance.z = f32::NAN,
            "objects[0].reflectance is (0, 0, NaN); every component must lie in [0, 1]",
        ),
        (
            |f| f.settings.volume_resolution = 300,
            "settings.volume_resolution is 300; allowed is 4..=256",
        ),
        (
            |f| f.settings.volume_resolution = 3,
            "settings.volume_resolution is 3; allowed is 4..=256",
        ),
        (
            |f| f.settings.scatter_iterations = 5000,
            "settings.scatter_iterations is 5000; allowed is 0..=4096",
        ),
        (
            |f| f.settings.warm_scatter_iterations = 1,
            "settings.warm_scatter_iterations is 1; allowed is 0 (off) or 2..=4096",
        ),
        (
            |f| f.settings.scatter_coarse_cycles = 65,
            "settings.scatter_coarse_cycles is 65; allowed is 0..=64",
        ),
        (
            |f| f.settings.forward_scattering = 2.0,
            "settings.forward_scattering is 2; it must lie in [0, 1]",
        ),
        (
            |f| f.settings.forward_scattering = f32::NAN,
            "settings.forward_scattering is NaN; it must lie in [0, 1]",
        ),
        (
            |f| f.settings.cloud_target_scale = 0.1,
            "settings.cloud_target_scale is 0.1; it must lie in [0.125, 1]",
        ),
        (
            |f| f.settings.cloud_target_scale = f32::NAN,
            "settings.cloud_target_scale is NaN; it must lie in [0.125, 1]",
        ),
    ];

    #[test]
    fn every_rule_refuses_with_path_value_and_allowed_range() {
        for (i, (mutate, expected)) in RULES.iter().enumerate() {
            let mut file = example_file();
            mutate(&mut file);
            let message = match Scene::from_scene_file(file.clone(), here()) {
                Ok(_) => panic!("rule {i} ({expected}) was not enforced"),
                Err(e) => e.to_string(),
            };
            assert_eq!(message, *expected, "rule {i}");
            // `Scene::validate` applies the same rules to a scene built in code.
            let mut scene = Scene::from_ron_str(example(), here()).unwrap();
            let mut file2 = example_file();
            mutate(&mut file2);
            scene.camera = file2.camera;
            scene.background = file2.background;
            scene.lights = file2.lights;
            scene.objects = file2.objects;
            scene.settings = file2.settings;
            scene.clouds = file2
                .clouds
                .into_iter()
                .map(|c| ResolvedCloud {
                    translation: c.translation,
                    medium: c.medium,
                    particles: match c.particles {
                        ParticleSource::Inline(p) => p,
                        _ => unreachable!(),
                    },
                })
                .collect();
            assert_eq!(
                scene.validate().unwrap_err().to_string(),
                *expected,
                "validate, rule {i}"
            );
        }
    }

    #[test]
    fn non_finite_values_written_in_ron_are_refused() {
        let text = example().replace("albedo: 0.99", "albedo: NaN");
        let e = Scene::from_ron_str(&text, here()).unwrap_err().to_string();
        assert_eq!(e, "clouds[0].medium.albedo is NaN; it must lie in [0, 1]");
        let text = example().replace("radius: 0.25", "radius: -inf");
        let e = Scene::from_ron_str(&text, here()).unwrap_err().to_string();
        assert_eq!(
            e,
            "clouds[0].particles[1].radius is -inf; it must be > 0 and at most 1e15 m"
        );
    }

    #[test]
    fn unknown_fields_are_refused_at_every_level() {
        let cases = [
            (
                "    settings:",
                "    bogus_top: 1,\n    settings:",
                "bogus_top",
            ),
            ("        width: 160,", "        width: 160, fov: 3,", "fov"),
            (
                "irradiance: (1.0, 0.97, 0.9)",
                "irradiance: (1.0, 0.97, 0.9), intensity: 2.0",
                "intensity",
            ),
            (
                "            translation: (0.0, 0.0, 0.0),",
                "            translation: (0.0, 0.0, 0.0), rotation: 1,",
                "rotation",
            ),
            ("albedo: 0.99", "albedo: 0.99, phase_g: 0.5", "phase_g"),
            (
                "radius: 0.2, density: 0.8",
                "radius: 0.2, density: 0.8, colour: 1",
                "colour",
            ),
            (
                "color: (0.05, 0.05, 0.05)",
                "color: (0.05, 0.05, 0.05), colour: 1",
                "colour",
            ),
            (
                "scatter_iterations: 16",
                "scatter_iterations: 16, volume_res: 3",
                "volume_res",
            ),
        ];
        for (from, to, field) in cases {
            assert!(example().contains(from), "{from}");
            let text = example().replacen(from, to, 1);
            let e = Scene::from_ron_str(&text, here()).unwrap_err();
            assert!(matches!(e, SceneError::Parse { .. }), "{e:?}");
            let message = e.to_string();
            assert!(
                message.contains(&format!("Unexpected field named `{field}`")),
                "{message}"
            );
            // origin:line:col
            assert!(message.starts_with("scene:"), "{message}");
            let SceneError::Parse { error, .. } = e else {
                unreachable!()
            };
            assert!(error.span.start.line > 1, "{message}");
        }
    }

    #[test]
    fn unknown_variants_missing_fields_and_syntax_errors_are_parse_errors() {
        let e = Scene::from_ron_str(&example().replace("Inline(", "Obj("), here())
            .unwrap_err()
            .to_string();
        assert!(e.contains("`Obj`") && e.contains("`Inline`"), "{e}");
        let e = Scene::from_ron_str(&example().replace("Cuboid(", "Box("), here())
            .unwrap_err()
            .to_string();
        assert!(e.contains("`Box`"), "{e}");
        let e = Scene::from_ron_str(&example().replace("        height: 120,\n", ""), here())
            .unwrap_err()
            .to_string();
        assert!(e.contains("`height`"), "{e}");
        let e = Scene::from_ron_str(&example().replace("width: 160", "width: -160"), here())
            .unwrap_err();
        let SceneError::Parse { error, .. } = &e else {
            panic!("{e:?}")
        };
        assert_eq!(error.span.start.line, 7, "{e}");
        let e = Scene::from_ron_str(
            &example().replace("look_at: (0.0, 0.0, 0.0),", "look_at: (0.0, 0.0 0.0),"),
            here(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.starts_with("scene:4:"), "{e}");
    }

    fn sample_particles() -> Vec<Particle> {
        vec![
            Particle {
                position: Vec3::new(0.1, 0.2, 0.3),
                radius: 0.2,
                density: 0.8,
            },
            Particle {
                position: Vec3::new(-0.3, 0.0, 0.1),
                radius: 0.25,
                density: 1.0,
            },
            Particle {
                position: Vec3::new(0.7, -0.25, 1.0 / 3.0),
                radius: 0.125,
                density: 0.0,
            },
        ]
    }

    fn scene_with_sources(sources: &str) -> String {
        example().replacen(
            "            translation: (0.0, 0.0, 0.0),  // optional, default origin\n",
            "",
            1,
        )
        .replace(
            "particles: Inline([\n                (position: (0.1, 0.2, 0.3), radius: 0.2, density: 0.8),\n                (position: (-0.3, 0.0, 0.1), radius: 0.25, density: 1.0),\n            ]),",
            sources,
        )
    }

    #[test]
    fn particle_files_load_relative_to_the_scene_file() {
        let dir = tmp_dir("files");
        std::fs::create_dir_all(dir.join("data")).unwrap();
        write_ply_binary(&dir.join("data/bin.ply"), &sample_particles()).unwrap();
        write_ply_ascii(&dir.join("ascii.ply"), &sample_particles()[1..]).unwrap();
        write_csv(&dir.join("data/c.csv"), &sample_particles()[..2]).unwrap();
        let text = scene_with_sources("particles: Ply(\"data/bin.ply\"),")
            .replace(
                "    ],\n    objects",
                "    (medium: (extinction: 1, albedo: 0.5), particles: Ply(\"ascii.ply\")),\n    \
                 (medium: (extinction: 1, albedo: 0.5), particles: Csv(\"data/c.csv\")),\n    ],\n    objects",
            );
        let scene_path = dir.join("scene.ron");
        std::fs::write(&scene_path, &text).unwrap();
        let s = Scene::load(&scene_path).unwrap();
        assert_eq!(s.clouds.len(), 3);
        assert_eq!(s.clouds[0].particles, sample_particles());
        assert_eq!(s.clouds[1].particles, sample_particles()[1..].to_vec());
        assert_eq!(s.clouds[2].particles, sample_particles()[..2].to_vec());
        // from_ron_str resolves against its base_dir
        let s2 = Scene::from_ron_str(&text, &dir).unwrap();
        assert_eq!(s, s2);
    }

    #[test]
    fn missing_particle_file_names_field_written_and_resolved_path() {
        let dir = tmp_dir("missing");
        let text = scene_with_sources("particles: Ply(\"missing.ply\"),");
        let e = Scene::from_ron_str(&text, &dir).unwrap_err();
        let message = e.to_string();
        let resolved = std::path::absolute(dir.join("missing.ply")).unwrap();
        assert!(
            message.starts_with(&format!(
                "clouds[0].particles: cannot read 'missing.ply' (resolved to {}): ",
                resolved.display()
            )),
            "{message}"
        );
        assert!(
            matches!(&e, SceneError::ParticleFile { error, .. } if matches!(**error, ParticleFileError::Io { .. }))
        );
        let e = Scene::from_ron_str(&scene_with_sources("particles: Csv(\"\"),"), &dir)
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            "clouds[0].particles is \"\"; the file name must not be empty"
        );
    }

    #[test]
    fn particle_file_errors_name_line_numbers() {
        let dir = tmp_dir("bad_files");
        std::fs::write(
            dir.join("bad.csv"),
            "x,y,z,radius,density\n0,0,0,1,1\n\n0,0,0,one,1\n",
        )
        .unwrap();
        let e = Scene::from_ron_str(&scene_with_sources("particles: Csv(\"bad.csv\"),"), &dir)
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("clouds[0].particles: cannot read 'bad.csv'"),
            "{e}"
        );
        assert!(
            e.ends_with("line 4: column `radius` is not a number"),
            "{e}"
        );
        std::fs::write(
            dir.join("bad.ply"),
            "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n\
             property float radius\nproperty float density\nend_header\n0 0 0 1 1\n0 0 0 1 x\n",
        )
        .unwrap();
        let e = Scene::from_ron_str(&scene_with_sources("particles: Ply(\"bad.ply\"),"), &dir)
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 11") && e.contains("`density`"), "{e}");
    }

    #[test]
    fn invalid_particle_in_a_file_names_the_path_and_the_file() {
        let dir = tmp_dir("invalid_in_file");
        let mut p = sample_particles();
        p[2].density = -3.0;
        write_csv(&dir.join("p.csv"), &p).unwrap();
        let e = Scene::from_ron_str(&scene_with_sources("particles: Csv(\"p.csv\"),"), &dir)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("clouds[0].particles[2].density is -3; it must be finite and >= 0 (particle file 'p.csv'"), "{e}");
    }

    #[test]
    fn scene_file_errors_name_the_path() {
        let dir = tmp_dir("scene_file");
        let path = dir.join("nope.ron");
        let e = Scene::load(&path).unwrap_err().to_string();
        assert!(
            e.starts_with(&format!("cannot read scene file '{}': ", path.display())),
            "{e}"
        );
        std::fs::write(&path, example().replace("width: 160", "widht: 160")).unwrap();
        let e = Scene::load(&path).unwrap_err().to_string();
        assert!(
            e.starts_with(&format!("{}:7:", path.display())) && e.contains("`widht`"),
            "{e}"
        );
    }
}
