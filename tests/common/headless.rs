//! Headless rendering of scenes with Bevy's renderer: the harness shared by the tests and the
//! `render` example (which includes this file). No window, no display server; any adapter,
//! Mesa's lavapipe included. Pipelines compile synchronously and any wgpu validation error
//! panics, so a broken pass fails loudly instead of rendering garbage.

#![allow(dead_code)]

use std::{
    collections::{HashMap, VecDeque},
    sync::{Arc, Mutex},
    time::Instant,
};

use bevy::{
    camera::{Exposure, Hdr, RenderTarget},
    core_pipeline::tonemapping::{DebandDither, Tonemapping},
    diagnostic::DiagnosticsStore,
    log::{Level, LogPlugin},
    prelude::*,
    render::{
        RenderApp, RenderPlugin,
        diagnostic::RenderDiagnosticsPlugin,
        error_handler::RenderErrorHandler,
        pipelined_rendering::PipelinedRenderingPlugin,
        render_resource::{PollType, TextureFormat, TextureUsages},
        renderer::{RenderAdapterInfo, RenderDevice},
        settings::{Backends, RenderCreation, WgpuSettings},
        view::screenshot::{Screenshot, ScreenshotCaptured},
    },
    window::ExitCondition,
};
use bevy_particle_clouds::{
    CloudPass, CloudPassCounters, CloudQualitySettings, ParticleCloud, ParticleCloudsPlugin,
    Particles,
    image_io::LinearImage,
    scene::{ObjectShape, Scene},
};

/// What to do when no adapter exists: say how to get one (tests fail, never skip).
pub const NO_ADAPTER: &str = "no Vulkan adapter found: install Mesa's software driver with \
`apt-get update && apt-get install -y mesa-vulkan-drivers` (lavapipe), or a GPU driver";

/// `ev100` for which Bevy's exposure factor `1 / (1.2 * 2^ev100)` is exactly 1: images hold
/// radiance in the units of the lights' irradiance (PHYSICS.md, "Output units").
pub const UNIT_EXPOSURE_EV100: f32 = -0.263_034_4;

/// Panics with [`NO_ADAPTER`] unless wgpu finds a Vulkan adapter.
pub fn assert_adapter() {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = Backends::VULKAN;
    desc.flags = wgpu::InstanceFlags::default().with_env();
    let instance = wgpu::Instance::new(desc);
    let adapter = bevy::tasks::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
        power_preference: wgpu::PowerPreference::HighPerformance,
        force_fallback_adapter: false,
        compatible_surface: None,
    }));
    assert!(adapter.is_ok(), "{NO_ADAPTER}");
}

/// A Bevy app that renders headlessly inside `app.update()`, with the plugin added.
pub fn headless_app() -> App {
    assert_adapter();
    let mut app = App::new();
    app.add_plugins(
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
            // The dev build enables winit for the windowed examples; its event loop needs a
            // display and can be created once per process, so headless apps leave it out.
            .disable::<bevy::winit::WinitPlugin>(),
    )
    .add_plugins((RenderDiagnosticsPlugin, ParticleCloudsPlugin));
    // The default handler only logs and stops rendering; a test must fail instead.
    app.insert_resource(RenderErrorHandler(|error, _, _| {
        panic!("render error {:?}: {}", error.ty, error.description)
    }));
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
    pub image: Handle<Image>,
    pub width: u32,
    pub height: u32,
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

/// Spawns everything of a scene file and returns its target.
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
    for light in &scene.lights {
        spawn_light(app, light.direction, light.irradiance);
    }
    let mut drawable_clouds = 0;
    for cloud in &scene.clouds {
        let handle = app
            .world_mut()
            .resource_mut::<Assets<Particles>>()
            .add(Particles::new(cloud.particles.clone()));
        if cloud.medium.extinction > 0.0 && cloud.particles.iter().any(|p| p.density > 0.0) {
            drawable_clouds += 1;
        }
        app.world_mut().spawn((
            ParticleCloud::new(handle).with_medium(cloud.medium),
            scene.settings,
            Transform::from_translation(cloud.translation),
        ));
    }
    for object in &scene.objects {
        spawn_object(app, object.shape, object.translation, object.color);
    }
    SceneTarget {
        image,
        width: camera.width,
        height: camera.height,
        camera: camera_entity,
        drawable_clouds,
    }
}

/// An opaque, unlit object showing the constant linear radiance `color`.
pub fn spawn_object(app: &mut App, shape: ObjectShape, translation: Vec3, color: Vec3) -> Entity {
    let mesh = match shape {
        ObjectShape::Cuboid(extents) => Mesh::from(Cuboid::new(extents.x, extents.y, extents.z)),
        ObjectShape::Sphere(radius) => Sphere::new(radius).mesh().ico(5).expect("ico sphere"),
    };
    let mesh = app.world_mut().resource_mut::<Assets<Mesh>>().add(mesh);
    let material = app
        .world_mut()
        .resource_mut::<Assets<StandardMaterial>>()
        .add(StandardMaterial {
            base_color: Color::linear_rgb(color.x, color.y, color.z),
            unlit: true,
            ..default()
        });
    app.world_mut()
        .spawn((
            Mesh3d(mesh),
            MeshMaterial3d(material),
            Transform::from_translation(translation),
        ))
        .id()
}

/// What one frame did.
#[derive(Clone, Debug, Default)]
pub struct FrameStats {
    pub wall_ms: f64,
    /// Runs of each pass this frame.
    pub passes: Vec<(CloudPass, u32)>,
    /// GPU time of each pass that ran, when the adapter reported it.
    pub gpu_ms: HashMap<CloudPass, f64>,
}

impl FrameStats {
    pub fn runs(&self, pass: CloudPass) -> u32 {
        self.passes
            .iter()
            .find(|(p, _)| *p == pass)
            .map_or(0, |(_, n)| *n)
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
    pub frames: Vec<FrameStats>,
    last_seen: HashMap<CloudPass, Instant>,
    waiting: HashMap<CloudPass, VecDeque<usize>>,
}

impl FrameRecorder {
    /// Renders one frame and records it.
    pub fn frame(&mut self, app: &mut App) -> &FrameStats {
        let start = Instant::now();
        update(app);
        let wall_ms = start.elapsed().as_secs_f64() * 1e3;
        let passes = app.world().resource::<CloudPassCounters>().take().to_vec();
        let index = self.frames.len();
        for &(pass, runs) in &passes {
            if runs > 0 {
                self.waiting.entry(pass).or_default().push_back(index);
            }
        }
        self.frames.push(FrameStats {
            wall_ms,
            passes,
            gpu_ms: HashMap::new(),
        });
        self.collect_gpu_times(app);
        &self.frames[index]
    }

    /// Runs of `pass` over every recorded frame.
    pub fn total(&self, pass: CloudPass) -> u32 {
        self.frames.iter().map(|f| f.runs(pass)).sum()
    }

    /// Updates without recording (to let late GPU times and screenshots arrive).
    pub fn drain(&mut self, app: &mut App) {
        update(app);
        app.world().resource::<CloudPassCounters>().take();
        self.collect_gpu_times(app);
    }

    fn collect_gpu_times(&mut self, app: &App) {
        let Some(store) = app.world().get_resource::<DiagnosticsStore>() else {
            return;
        };
        for pass in CloudPass::ALL {
            let Some(diagnostic) = store.get(&pass.diagnostic_path()) else {
                continue;
            };
            let Some(latest) = diagnostic.measurement().map(|m| m.time) else {
                continue;
            };
            if self.last_seen.get(&pass) == Some(&latest) {
                continue;
            }
            self.last_seen.insert(pass, latest);
            // One frame's spans of a pass (e.g. one per cloud and view) share the sync instant.
            let total: f64 = diagnostic
                .measurements()
                .filter(|m| m.time == latest)
                .map(|m| m.value)
                .sum();
            if let Some(frame) = self.waiting.get_mut(&pass).and_then(VecDeque::pop_front) {
                self.frames[frame].gpu_ms.insert(pass, total);
            }
        }
    }
}

/// One `app.update()` plus a blocking GPU poll, so readbacks and timings arrive deterministically.
pub fn update(app: &mut App) {
    app.update();
    if let Some(device) = app
        .sub_app(RenderApp)
        .world()
        .get_resource::<RenderDevice>()
    {
        device
            .poll(PollType::wait_indefinitely())
            .expect("GPU poll failed");
    }
    assert!(app.should_exit().is_none(), "the renderer asked to exit");
}

/// Renders until the clouds are drawn with finished illumination: a frame that does no
/// illumination or sort work and draws every drawable cloud, or, when some cloud is out of view,
/// the second frame in a row without work. Returns the frames it took; panics past `max_frames`.
pub fn render_until_steady(
    app: &mut App,
    recorder: &mut FrameRecorder,
    target: &SceneTarget,
    max_frames: usize,
) -> usize {
    let mut idle_before = false;
    for n in 1..=max_frames {
        let stats = recorder.frame(app);
        let idle = stats.work() == 0;
        if n > 1 && idle && (stats.runs(CloudPass::Draw) >= target.drawable_clouds || idle_before) {
            return n;
        }
        idle_before = idle && n > 1;
    }
    panic!("the scene did not reach a finished image within {max_frames} frames");
}

/// Captures the next rendered frame of `target` as linear RGBA floats.
pub fn capture(app: &mut App, recorder: &mut FrameRecorder, target: &SceneTarget) -> LinearImage {
    let shot: Arc<Mutex<Option<Image>>> = Arc::default();
    let sink = shot.clone();
    app.world_mut()
        .spawn(Screenshot::image(target.image.clone()))
        .observe(move |captured: On<ScreenshotCaptured>| {
            *sink.lock().unwrap() = Some(captured.image.clone())
        });
    recorder.frame(app);
    for _ in 0..10 {
        if let Some(image) = shot.lock().unwrap().take() {
            return decode_rgba16f(&image);
        }
        recorder.drain(app);
    }
    panic!("the screenshot did not arrive");
}

/// Converts an `Rgba16Float` image into linear floats.
pub fn decode_rgba16f(image: &Image) -> LinearImage {
    assert_eq!(
        image.texture_descriptor.format,
        TextureFormat::Rgba16Float,
        "expected an Rgba16Float target"
    );
    let data = image.data.as_ref().expect("screenshot has data");
    let pixels = data
        .chunks_exact(8)
        .map(|px| {
            std::array::from_fn(|c| f16_to_f32(u16::from_le_bytes([px[2 * c], px[2 * c + 1]])))
        })
        .collect();
    LinearImage {
        width: image.width(),
        height: image.height(),
        pixels,
    }
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

/// Quality settings helper for tests.
pub fn quality(volume_resolution: u32, scatter_iterations: u32) -> CloudQualitySettings {
    CloudQualitySettings {
        volume_resolution,
        scatter_iterations,
        ..default()
    }
}

/// Copies a GPU buffer back to the CPU (blocking).
pub fn read_buffer(app: &mut App, buffer: &bevy::render::render_resource::Buffer) -> Vec<u8> {
    use bevy::render::{
        render_resource::{BufferDescriptor, BufferUsages, CommandEncoderDescriptor, MapMode},
        renderer::RenderQueue,
    };
    let world = app.sub_app(RenderApp).world();
    let device = world.resource::<RenderDevice>();
    let queue = world.resource::<RenderQueue>();
    let staging = device.create_buffer(&BufferDescriptor {
        label: Some("test_readback"),
        size: buffer.size(),
        usage: BufferUsages::MAP_READ | BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = device.create_command_encoder(&CommandEncoderDescriptor::default());
    encoder.copy_buffer_to_buffer(buffer, 0, &staging, 0, buffer.size());
    queue.submit([encoder.finish()]);
    let slice = staging.slice(..);
    slice.map_async(MapMode::Read, |result| {
        result.expect("map the readback buffer")
    });
    device
        .poll(PollType::wait_indefinitely())
        .expect("GPU poll failed");
    let data = slice.get_mapped_range().to_vec();
    staging.unmap();
    data
}

/// Little-endian f32s of a byte buffer.
pub fn floats(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

/// Runs a closure on the render world.
pub fn with_render_world<R>(app: &mut App, f: impl FnOnce(&mut World) -> R) -> R {
    f(app.sub_app_mut(RenderApp).world_mut())
}
