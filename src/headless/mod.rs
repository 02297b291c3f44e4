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

fn count_of(counts: &[(CloudPass, u32)], pass: CloudPass) -> u32 {
    counts
        .iter()
        .find(|(p, _)| *p == pass)
        .map_or(0, |(_, n)| *n)
}

/// What one frame did.
#[derive(Clone, Debug, Default)]
pub struct FrameStats {
    /// Wall-clock time of the frame's `app.update()` and GPU poll, milliseconds.
    pub wall_ms: f64,
    /// Runs of each pass this frame.
    pub passes: Vec<(CloudPass, u32)>,
    /// Compute dispatches of each pass this frame.
    pub dispatches: Vec<(CloudPass, u32)>,
    /// GPU time of each pass that ran, when the adapter reported it.
    pub gpu_ms: HashMap<CloudPass, f64>,
}

impl FrameStats {
    /// Runs of `pass` this frame.
    pub fn runs(&self, pass: CloudPass) -> u32 {
        count_of(&self.passes, pass)
    }

    /// Compute dispatches of `pass` this frame.
    pub fn dispatches(&self, pass: CloudPass) -> u32 {
        count_of(&self.dispatches, pass)
    }

    /// Runs of the illumination and sort passes (everything but the draw).
    pub fn work(&self) -> u32 {
        self.passes
            .iter()
            .filter(|(p, _)| *p != CloudPass::Draw)
            .map(|(_, n)| n)
            .sum()
    }
}

/// Renders frames and attributes GPU times (which arrive a few frames late) to the frames whose
/// passes produced them.
#[derive(Default)]
pub struct FrameRecorder {
    /// Every recorded frame, in order.
    pub frames: Vec<FrameStats>,
    counted: [u32; PASSES],
    dispatched: [u32; PASSES],
    last_seen: HashMap<DiagnosticPath, Instant>,
    waiting: HashMap<CloudPass, VecDeque<usize>>,
}

impl FrameRecorder {
    /// Renders one frame and records it.
    pub fn frame(&mut self, app: &mut App) -> Result<&FrameStats, HeadlessError> {
        let start = Instant::now();
        update(app)?;
        let wall_ms = start.elapsed().as_secs_f64() * 1e3;
        let counters = app.world().resource::<CloudPassCounters>();
        let passes = counters.since(&mut self.counted).to_vec();
        let dispatches = counters.dispatches_since(&mut self.dispatched).to_vec();
        let index = self.frames.len();
        for &(pass, runs) in &passes {
            if runs > 0 {
                self.waiting.entry(pass).or_default().push_back(index);
            }
        }
        self.frames.push(FrameStats {
            wall_ms,
            passes,
            dispatches,
            gpu_ms: HashMap::new(),
        });
        self.collect_gpu_times(app);
        Ok(&self.frames[index])
    }

    /// Runs of `pass` over every recorded frame.
    pub fn total(&self, pass: CloudPass) -> u32 {
        self.frames.iter().map(|f| f.runs(pass)).sum()
    }

    /// Updates without recording (to let late GPU times and screenshots arrive).
    pub fn drain(&mut self, app: &mut App) -> Result<(), HeadlessError> {
        update(app)?;
        let counters = app.world().resource::<CloudPassCounters>();
        counters.since(&mut self.counted);
        counters.dispatches_since(&mut self.dispatched);
        self.collect_gpu_times(app);
        Ok(())
    }

    fn collect_gpu_times(&mut self, app: &App) {
        let Some(store) = app.world().get_resource::<DiagnosticsStore>() else {
            return;
        };
        for pass in CloudPass::ALL {
            for path in pass.diagnostic_paths() {
                self.collect_gpu_time(store, pass, &path);
            }
        }
    }
}

impl FrameRecorder {
    /// The GPU time of `pass` under `path`, if a new measurement arrived: the frame waiting longest
    /// for that pass's time gets it (added to what it holds from the pass's other paths).
    fn collect_gpu_time(
        &mut self,
        store: &DiagnosticsStore,
        pass: CloudPass,
        path: &DiagnosticPath,
    ) {
        let Some(diagnostic) = store.get(path) else {
            return;
        };
        let Some(latest) = diagnostic.measurement().map(|m| m.time) else {
            return;
        };
        if self.last_seen.get(path) == Some(&latest) {
            return;
        }
        self.last_seen.insert(path.clone(), latest);
        // One frame's spans of a pass (e.g. one per cloud and view) share the sync instant.
        let total: f64 = diagnostic
            .measurements()
            .filter(|m| m.time == latest)
            .map(|m| m.value)
            .sum();
        if let Some(frame) = self.waiting.get_mut(&pass).and_then(VecDeque::pop_front) {
            *self.frames[frame].gpu_ms.entry(pass).or_default() += total;
        }
    }
}

/// Why headless rendering could not go on.
#[derive(Debug, thiserror::Error)]
pub enum HeadlessError {
    /// Waiting for the GPU failed (a lost device, for example).
    #[error("waiting for the GPU failed: {0}")]
    Poll(String),
    /// The app asked to exit (Bevy's render error handler does after a GPU error).
    #[error("the renderer asked to exit: {0:?}")]
    Exited(AppExit),
    /// The illumination was still being computed after the given number of frames.
    #[error("the scene did not reach a finished image within {max_frames} frames")]
    NotSteady {
        /// The frames rendered.
        max_frames: usize,
    },
    /// The screenshot did not come back from the GPU.
    #[error("the screenshot did not arrive within {frames} frames")]
    NoScreenshot {
        /// The frames waited.
        frames: usize,
    },
    /// A captured image is not in the format [`decode_rgba16f`] reads.
    #[error("expected an Rgba16Float image with data, got {format:?}")]
    Format {
        /// The image's format.
        format: TextureFormat,
    },
}

/// One `app.update()` plus a blocking GPU poll, so readbacks and timings arrive deterministically.
pub fn update(app: &mut App) -> Result<(), HeadlessError> {
    app.update();
    if let Some(device) = app
        .sub_app(RenderApp)
        .world()
        .get_resource::<RenderDevice>()
    {
        device
            .poll(PollType::wait_indefinitely())
            .map_err(|e| HeadlessError::Poll(e.to_string()))?;
    }
    match app.should_exit() {
        Some(exit) => Err(HeadlessError::Exited(exit)),
        None => Ok(()),
    }
}

/// Renders until the clouds are drawn with finished illumination: a frame that does no
/// illumination or sort work and draws all `drawable_clouds` (for a scene,
/// [`SceneTarget::drawable_clouds`]), or, when some cloud is out of view, the second frame in a
/// row without work. Returns the frames it took.
pub fn render_until_steady(
    app: &mut App,
    recorder: &mut FrameRecorder,
    drawable_clouds: u32,
    max_frames: usize,
) -> Result<usize, HeadlessError> {
    let mut idle_before = false;
    for n in 1..=max_frames {
        let stats = recorder.frame(app)?;
        let idle = stats.work() == 0;
        if n > 1 && idle && (stats.runs(CloudPass::Draw) >= drawable_clouds || idle_before) {
            return Ok(n);
        }
        idle_before = idle && n > 1;
    }
    Err(HeadlessError::NotSteady { max_frames })
}

/// Captures the next rendered frame of the `Rgba16Float` render target `image` (for a scene,
/// [`SceneTarget::image`]) as linear RGBA floats.
pub fn capture(
    app: &mut App,
    recorder: &mut FrameRecorder,
    image: &Handle<Image>,
) -> Result<LinearImage, HeadlessError> {
    let shot: Arc<Mutex<Option<Image>>> = Arc::default();
    let sink = shot.clone();
    app.world_mut()
        .spawn(Screenshot::image(image.clone()))
        .observe(move |captured: On<ScreenshotCaptured>| {
            *sink.lock().unwrap() = Some(captured.image.clone())
        });
    recorder.frame(app)?;
    const FRAMES: usize = 10;
    for _ in 0..FRAMES {
        if let Some(image) = shot.lock().unwrap().take() {
            return decode_rgba16f(&image);
        }
        recorder.drain(app)?;
    }
    Err(HeadlessError::NoScreenshot { frames: FRAMES })
}

/// Converts an `Rgba16Float` image into linear floats.
pub fn decode_rgba16f(image: &Image) -> Result<LinearImage, HeadlessError> {
    let format = image.texture_descriptor.format;
    let (TextureFormat::Rgba16Float, Some(data)) = (format, image.data.as_ref()) else {
        return Err(HeadlessError::Format { format });
    };
    let pixels = data
        .chunks_exact(8)
        .map(|px| {
            std::array::from_fn(|c| f16_to_f32(u16::from_le_bytes([px[2 * c], px[2 * c + 1]])))
        })
        .collect();
    Ok(LinearImage {
        width: image.width(),
        height: image.height(),
        pixels,
    })
}

/// IEEE 754 half to single precision.
pub fn f16_to_f32(bits: u16) -> f32 {
    let sign = if bits & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exponent = ((bits >> 10) & 0x1f) as i32;
    let mantissa = (bits & 0x3ff) as f32;
    sign * match exponent {
        0 => mantissa * 2f32.powi(-24),
        31 if mantissa == 0.0 => f32::INFINITY,
        31 => f32::NAN,
        e => (1.0 + mantissa / 1024.0) * 2f32.powi(e - 15),
    }
}

/// Copies a GPU buffer back to the CPU (blocking): for comparing what a pass wrote with the CPU
/// reference.
pub fn read_buffer(
    app: &mut App,
    buffer: &bevy::render::render_resource::Buffer,
) -> Result<Vec<u8>, HeadlessError> {
    read_back(app, buffer.size(), |encoder, staging| {
        encoder.copy_buffer_to_buffer(buffer, 0, staging, 0, buffer.size());
    })
}

/// The bytes of a part of a GPU buffer (a cloud's slot in a volume pool, for example).
pub fn read_buffer_range(
    app: &mut App,
    range: &crate::render::plan::pools::BufferRange,
) -> Result<Vec<u8>, HeadlessError> {
    read_back(app, range.size, |encoder, staging| {
        encoder.copy_buffer_to_buffer(&range.buffer, range.offset, staging, 0, range.size);
    })
}

/// Records `copy` of `size` bytes into a mappable staging buffer, submits it, waits and returns
/// the bytes.
fn read_back(
    app: &mut App,
    size: u64,
    copy: impl FnOnce(
        &mut bevy::render::render_resource::CommandEncoder,
        &bevy::render::render_resource::Buffer,
    ),
) -> Result<Vec<u8>, HeadlessError> {
    use bevy::render::{
        render_resource::{BufferDescriptor, BufferUsages, CommandEncoderDescriptor, MapMode},
        renderer::RenderQueue,
    };
    let world = app.sub_app(RenderApp).world();
    let device = world.resource::<RenderDevice>();
    let staging = device.create_buffer(&BufferDescriptor {
        label: Some("headless_readback"),
        size,
        usage: BufferUsages::MAP_READ | BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = device.create_command_encoder(&CommandEncoderDescriptor::default());
    copy(&mut encoder, &staging);
    world.resource::<RenderQueue>().submit([encoder.finish()]);
    let slice = staging.slice(..);
    let mapped: Arc<Mutex<Option<String>>> = Arc::default();
    let sink = mapped.clone();
    slice.map_async(MapMode::Read, move |result| {
        *sink.lock().unwrap() = result.err().map(|e| e.to_string());
    });
    device
        .poll(PollType::wait_indefinitely())
        .map_err(|e| HeadlessError::Poll(e.to_string()))?;
    if let Some(error) = mapped.lock().unwrap().take() {
        return Err(HeadlessError::Poll(error));
    }
    let data = slice.get_mapped_range().to_vec();
    staging.unmap();
    Ok(data)
}

/// Copies a 2D texture (its first mip level; the depth aspect of a depth texture) back to the
/// CPU (blocking), rows tightly packed: for comparing what a render pass wrote with the CPU
/// reference. The texture needs `COPY_SRC` usage.
pub fn read_texture(
    app: &mut App,
    texture: &bevy::render::render_resource::Texture,
) -> Result<Vec<u8>, HeadlessError> {
    use bevy::render::render_resource::{
        TexelCopyBufferInfo, TexelCopyBufferLayout, TextureAspect,
    };
    let aspect = if texture.format().is_depth_stencil_format() {
        TextureAspect::DepthOnly
    } else {
        TextureAspect::All
    };
    let texel = texture
        .format()
        .block_copy_size(Some(aspect))
        .ok_or(HeadlessError::Format {
            format: texture.format(),
        })?;
    let (width, height) = (texture.width(), texture.height());
    let row = width * texel;
    // Buffer copies need rows aligned to 256 bytes.
    let padded = row.next_multiple_of(256);
    let bytes = read_back(app, u64::from(padded * height), |encoder, staging| {
        let mut source = texture.as_image_copy();
        source.aspect = aspect;
        encoder.copy_texture_to_buffer(
            source,
            TexelCopyBufferInfo {
                buffer: staging,
                layout: TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(padded),
                    rows_per_image: Some(height),
                },
            },
            texture.size(),
        );
    })?;
    Ok(bytes
        .chunks_exact(padded as usize)
        .flat_map(|r| &r[..row as usize])
        .copied()
        .collect())
}

/// Little-endian f32s of a byte buffer.
pub fn floats(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}
