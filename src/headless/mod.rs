//! Rendering without a window (feature `headless`): make the app, spawn a [`Scene`] as entities,
//! render until the illumination is finished, capture the image as linear radiance and record
//! what each frame did. No window, no display server; any adapter, Mesa's lavapipe included.
//! Pipelines compile synchronously, so the first frames are deterministic.
//!
//! ```no_run
//! # use bevy_particle_clouds::{headless, scene::Scene};
//! let scene = Scene::load(std::path::Path::new("scene.ron")).unwrap();
//! let mut app = headless::app();
//! let target = headless::spawn_scene(&mut app, &scene);
//! let mut recorder = headless::FrameRecorder::default();
//! headless::render_until_steady(&mut app, &mut recorder, target.drawable_clouds, 100).unwrap();
//! let image = headless::capture(&mut app, &mut recorder, &target.image).unwrap();
//! ```
//!
//! A build that enables Bevy's `bevy_winit` feature must leave `WinitPlugin` out, since its event
//! loop needs a display: `headless::app_with(headless::plugins().disable::<WinitPlugin>())`.

use std::{
    collections::{HashMap, VecDeque},
    sync::{Arc, Mutex},
    time::Instant,
};

use bevy::app::PluginGroupBuilder;
use bevy::asset::RenderAssetUsages;
use bevy::{
    camera::{Exposure, Hdr, RenderTarget},
    core_pipeline::tonemapping::{DebandDither, Tonemapping},
    diagnostic::{DiagnosticPath, DiagnosticsStore},
    log::{Level, LogPlugin},
    prelude::*,
    render::{
        RenderApp, RenderPlugin,
        diagnostic::RenderDiagnosticsPlugin,
        pipelined_rendering::PipelinedRenderingPlugin,
        render_resource::{PollType, TextureFormat, TextureUsages},
        renderer::{RenderAdapterInfo, RenderDevice},
        settings::{Backends, RenderCreation, WgpuSettings},
        storage::ShaderBuffer,
        view::screenshot::{Screenshot, ScreenshotCaptured},
    },
    window::ExitCondition,
};

mod frames;
mod readback;

pub use frames::{FrameRecorder, FrameStats, HeadlessError, render_until_steady, update};
pub use readback::{
    capture, decode_rgba16f, f16_to_f32, floats, read_buffer, read_buffer_range, read_texture,
};

use crate::{
    CloudPass, CloudPassCounters, CloudQualitySettings, CloudSkyLight, Medium, PASSES, Particle,
    ParticleCloud, ParticleCloudsPlugin, Particles,
    linear_image::LinearImage,
    lit_object::{LitObjectMaterial, LitObjectPlugin, LitSurface},
    scene::{ObjectShape, Scene, SceneObject},
    shadow_maps::CloudShadowMaps,
};

/// `ev100` for which Bevy's exposure factor `1 / (1.2 * 2^ev100)` is exactly 1: images hold
/// radiance in the units of the lights' irradiance (docs/physics.md, "Output units").
pub const UNIT_EXPOSURE_EV100: f32 = -0.263_034_4;

/// Bevy's default plugins set up for rendering without a window: no primary window, warnings
/// only in the log, Vulkan, synchronous pipeline compilation, no pipelined rendering.
pub fn plugins() -> PluginGroupBuilder {
    DefaultPlugins
        .set(WindowPlugin {
            primary_window: None,
            exit_condition: ExitCondition::DontExit,
            ..default()
        })
        // Warnings (refused clouds, wgpu problems) matter; per-app info lines are noise.
        .set(LogPlugin {
            level: Level::WARN,
            ..default()
        })
        .set(RenderPlugin {
            render_creation: RenderCreation::Automatic(Box::new(WgpuSettings {
                backends: Some(Backends::VULKAN),
                ..default()
            })),
            synchronous_pipeline_compilation: true,
            ..default()
        })
        .disable::<PipelinedRenderingPlugin>()
}

/// An app built from [`plugins`] with the cloud plugin and GPU timing added, ready to render
/// inside `app.update()`.
pub fn app() -> App {
    app_with(plugins())
}

/// An app built from `plugins` (normally [`plugins`], adjusted) with the cloud plugin and GPU
/// timing added, finished and cleaned up, ready to render inside `app.update()`.
pub fn app_with(plugins: impl PluginGroup) -> App {
    let mut app = App::new();
    app.add_plugins(plugins).add_plugins((
        RenderDiagnosticsPlugin,
        ParticleCloudsPlugin,
        LitObjectPlugin,
    ));
    app.finish();
    app.cleanup();
    app
}

/// The adapter's name, e.g. `llvmpipe (LLVM 15.0.6, 256 bits)`.
pub fn adapter_name(app: &mut App) -> String {
    app.sub_app(RenderApp)
        .world()
        .resource::<RenderAdapterInfo>()
        .name
        .clone()
}

/// The render target of a spawned scene.
#[derive(Clone, Debug)]
pub struct SceneTarget {
    /// The HDR float image the camera renders into.
    pub image: Handle<Image>,
    /// Its width, pixels.
    pub width: u32,
    /// Its height, pixels.
    pub height: u32,
    /// The camera entity.
    pub camera: Entity,
    /// Clouds expected to be drawn (valid, non-empty, with extinction).
    pub drawable_clouds: u32,
}

/// An HDR float target: linear radiance survives unclamped.
pub fn float_target(app: &mut App, width: u32, height: u32) -> Handle<Image> {
    let mut image = Image::new_target_texture(width, height, TextureFormat::Rgba16Float, None);
    image.texture_descriptor.usage |= TextureUsages::COPY_SRC;
    app.world_mut().resource_mut::<Assets<Image>>().add(image)
}

/// A camera rendering linear radiance at exposure 1 into `target`: HDR, no tonemapping, no
/// dithering, no MSAA (so pixels are exact), clear colour = background.
pub fn spawn_linear_camera(
    app: &mut App,
    target: Handle<Image>,
    transform: Transform,
    fov_degrees: f32,
    background: Vec3,
) -> Entity {
    app.world_mut()
        .spawn((
            Camera3d::default(),
            Camera {
                clear_color: ClearColorConfig::Custom(Color::linear_rgb(
                    background.x,
                    background.y,
                    background.z,
                )),
                ..default()
            },
            RenderTarget::Image(target.into()),
            Projection::Perspective(PerspectiveProjection {
                fov: fov_degrees.to_radians(),
                ..default()
            }),
            Hdr,
            Tonemapping::None,
            DebandDither::Disabled,
            Msaa::Off,
            Exposure {
                ev100: UNIT_EXPOSURE_EV100,
            },
            transform,
        ))
        .id()
}

/// A directional light with irradiance `E` (linear RGB) travelling along `direction`.
pub fn spawn_light(app: &mut App, direction: Vec3, irradiance: Vec3) -> Entity {
    let direction = direction.normalize();
    let up = if direction.cross(Vec3::Y).length_squared() < 1e-6 {
        Vec3::X
    } else {
        Vec3::Y
    };
    app.world_mut()
        .spawn((
            DirectionalLight {
                color: Color::linear_rgb(irradiance.x, irradiance.y, irradiance.z),
                illuminance: 1.0,
                shadow_maps_enabled: false,
                ..default()
            },
            Transform::default().looking_to(direction, up),
        ))
        .id()
}

/// Spawns everything of a scene file and returns its target; its background also lights the
/// clouds ([`CloudSkyLight`]), and its widest lit object is their ground ([`Scene::cloud_ground`]).
pub fn spawn_scene(app: &mut App, scene: &Scene) -> SceneTarget {
    let camera = &scene.camera;
    let image = float_target(app, camera.width, camera.height);
    let transform =
        Transform::from_translation(camera.position).looking_at(camera.look_at, camera.up);
    let camera_entity = spawn_linear_camera(
        app,
        image.clone(),
        transform,
        camera.vertical_fov_degrees,
        scene.background,
    );
    if let Some(fog) = &scene.fog {
        app.world_mut()
            .entity_mut(camera_entity)
            .insert(crate::render::draw::fog::distance_fog(fog));
    }
    for light in &scene.lights {
        spawn_light(app, light.direction, light.irradiance);
    }
    // The background is a uniform sky that lights the clouds (docs/physics.md), and the widest
    // lit object their ground (docs/illumination.md §4).
    app.insert_resource(CloudSkyLight::from_radiance(scene.background));
    match scene.cloud_ground() {
        Some(ground) => {
            app.insert_resource(ground);
        }
        None => {
            app.world_mut().remove_resource::<crate::CloudGround>();
        }
    }
    let mut drawable_clouds = 0;
    for cloud in &scene.clouds {
        if cloud.medium.extinction > 0.0 && cloud.particles.iter().any(|p| p.density > 0.0) {
            drawable_clouds += 1;
        }
        spawn_cloud(
            app,
            cloud.particles.clone(),
            cloud.medium,
            scene.settings,
            Transform::from_translation(cloud.translation),
        );
    }
    // Lit objects take the clouds' shadows through the shadow maps: at the resolution the app's
    // maps already have, else at the scene's.
    if scene.objects.iter().any(|o| o.reflectance != Vec3::ZERO) {
        let resolution = match app.world().resource::<CloudShadowMaps>().resolution {
            0 => scene.shadow_map_resolution,
            chosen => chosen,
        };
        enable_cloud_shadow_maps(app, resolution, scene.lights.len());
    }
    for object in &scene.objects {
        spawn_object(app, object);
    }
    SceneTarget {
        image,
        width: camera.width,
        height: camera.height,
        camera: camera_entity,
        drawable_clouds,
    }
}

/// A cloud of `particles` (cloud-local metres) with `medium` and `settings`, placed by
/// `transform`; its `Particles` asset is added here.
pub fn spawn_cloud(
    app: &mut App,
    particles: Vec<Particle>,
    medium: Medium,
    settings: CloudQualitySettings,
    transform: Transform,
) -> Entity {
    let handle = app
        .world_mut()
        .resource_mut::<Assets<Particles>>()
        .add(Particles::new(particles));
    app.world_mut()
        .spawn((
            ParticleCloud::new(handle).with_medium(medium),
            settings,
            transform,
        ))
        .id()
}

/// Turns the cloud shadow maps on at `resolution` texels per side for `lights` cloud-lighting
/// lights, their buffer made at once: lit objects spawned afterwards bind it from the first
/// frame (a buffer made later reaches their materials only a frame or two after the clouds are
/// finished).
pub fn enable_cloud_shadow_maps(app: &mut App, resolution: u32, lights: usize) {
    let bytes = CloudShadowMaps::buffer_bytes(lights, resolution);
    let buffer = ShaderBuffer::with_size(bytes, RenderAssetUsages::default());
    let buffer = app
        .world_mut()
        .resource_mut::<Assets<ShaderBuffer>>()
        .add(buffer);
    app.insert_resource(CloudShadowMaps {
        buffer,
        ..CloudShadowMaps::with_resolution(resolution)
    });
}

/// Spawns a scene object: a mesh showing its `color`, and, with a `reflectance`, a Lambertian
/// surface lit through the clouds ([`LitObjectMaterial`]; turn the [`CloudShadowMaps`] on for its
/// shadows, as [`spawn_scene`] does).
pub fn spawn_object(app: &mut App, object: &SceneObject) -> Entity {
    let mesh = match object.shape {
        ObjectShape::Cuboid(extents) => Mesh::from(Cuboid::new(extents.x, extents.y, extents.z)),
        ObjectShape::Sphere(radius) => Sphere::new(radius).mesh().ico(5).expect("ico sphere"),
    };
    let mesh = Mesh3d(app.world_mut().resource_mut::<Assets<Mesh>>().add(mesh));
    let transform = Transform::from_translation(object.translation);
    let color = object.color;
    if object.reflectance == Vec3::ZERO {
        let material = app
            .world_mut()
            .resource_mut::<Assets<StandardMaterial>>()
            .add(StandardMaterial {
                base_color: Color::linear_rgb(color.x, color.y, color.z),
                unlit: true,
                ..default()
            });
        return app
            .world_mut()
            .spawn((mesh, MeshMaterial3d(material), transform))
            .id();
    }
    let shadow_maps = app.world().resource::<CloudShadowMaps>().buffer.clone();
    let material = LitObjectMaterial {
        surface: LitSurface {
            color,
            reflectance: object.reflectance,
        },
        lights: default(),
        shadow_maps,
    };
    let material = app
        .world_mut()
        .resource_mut::<Assets<LitObjectMaterial>>()
        .add(material);
    app.world_mut()
        .spawn((mesh, MeshMaterial3d(material), transform))
        .id()
}
