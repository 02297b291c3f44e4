//! Scene files (`SCENE_FORMAT.md`): one still image of particle clouds, lights and opaque objects.
//!
//! [`SceneFile`] mirrors the RON text exactly (unknown fields are refused); [`Scene::load`] reads
//! a file, resolves particle files relative to it, validates every value and returns a [`Scene`]
//! ready for the real-time renderer, the CPU reference or the path tracer.

use bevy::math::Vec3;
use serde::Deserialize;

use crate::particle::{LightSample, Medium, Particle};
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
    pub medium: Medium,
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

/// An opaque, unlit occluder showing a constant radiance.
#[derive(Clone, Copy, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneObject {
    pub shape: ObjectShape,
    /// World position of the shape's centre, metres; default origin.
    #[serde(default)]
    pub translation: Vec3,
    /// Linear RGB radiance the object shows.
    pub color: Vec3,
}

/// A scene file as written (SCENE_FORMAT.md).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneFile {
    pub camera: SceneCamera,
    /// Linear RGB radiance behind everything; default black.
    #[serde(default)]
    pub background: Vec3,
    pub lights: Vec<LightSample>,
    pub clouds: Vec<SceneCloud>,
    #[serde(default)]
    pub objects: Vec<SceneObject>,
    #[serde(default)]
    pub settings: CloudQualitySettings,
}

/// A cloud with its particles loaded and validated.
#[derive(Clone, Debug, PartialEq)]
pub struct ResolvedCloud {
    pub translation: Vec3,
    pub medium: Medium,
    pub particles: Vec<Particle>,
}

/// A validated scene, particle files loaded: what every renderer consumes.
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    pub camera: SceneCamera,
    pub background: Vec3,
    pub lights: Vec<LightSample>,
    pub clouds: Vec<ResolvedCloud>,
    pub objects: Vec<SceneObject>,
    pub settings: CloudQualitySettings,
}
