//! What the interactive examples (`clouds`, `multiple_lights`, `animated`, `snow_bunny`) share:
//! the command line, the windowed and the headless runner, an orbiting camera, lights turned with
//! the keyboard, and the on-screen text (settings, frame time, GPU time and runs of each pass).
//!
//! Every example accepts
//!
//! ```text
//! --frames N                  exit (AppExit::Success) after N frames; headless: render at least N
//! --window-screenshot PATH    with --frames: save the window's last frame as PNG, then exit
//! --screenshot PATH.png       render headlessly (no window, no display) and write the picture
//! --sun-turn-gif PATH.gif     render headlessly, the key lights turned once around the sky in
//!                             --sun-turn-frames steps (default 24), each re-lit; an animated GIF
//! --size WxH                  window or picture size in pixels (default 1280x720 / 800x450)
//! ```
//!
//! parsed with clap ([`Options`], flattened into each example's own arguments): `--help` lists
//! them, and a bad value or an unknown flag is an error naming it.

#![allow(dead_code)]

use std::{path::PathBuf, process::ExitCode, time::Instant};

use bevy::{
    camera::{Exposure, Hdr, RenderTarget},
    core_pipeline::tonemapping::{DebandDither, Tonemapping},
    diagnostic::{DiagnosticsStore, FrameTimeDiagnosticsPlugin},
    input::mouse::{AccumulatedMouseMotion, AccumulatedMouseScroll, MouseScrollUnit},
    prelude::*,
    render::{
        diagnostic::RenderDiagnosticsPlugin,
        view::screenshot::{Screenshot, ScreenshotCaptured},
    },
};
mod sun_turn;

use bevy_particle_clouds::{
    CloudGround, CloudPass, CloudPassCounters, CloudShadowMaps, CloudSkyLight, CloudTargetScale,
    PASSES, ParticleCloud, ParticleCloudsPlugin, Particles,
    cloud_shadowed_material::{CloudShadowReceiver, CloudShadowedMaterial},
    headless::{self, FrameRecorder},
    image_io,
    lit_object::{LitObjectMaterial, LitObjectPlugin, LitSurface},
};

/// The options every example accepts (see the module documentation); flatten them into the
/// example's own `clap::Parser`.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct Options {
    /// Window: exit after N frames. Headless: render at least N frames.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..))]
    pub frames: Option<u32>,
    /// Render headlessly (no window, no display) into this picture (.png or .exr).
    #[arg(long, value_name = "PATH", value_parser = output_path, conflicts_with = "window_screenshot")]
    pub screenshot: Option<PathBuf>,
    /// With --frames: save the window's last frame as PNG, then exit.
    #[arg(long, value_name = "PATH.png", requires = "frames")]
    pub window_screenshot: Option<PathBuf>,
    /// Render headlessly an animated GIF: every key light turned once around the sky (azimuth),
    /// one picture per step, each re-lit until finished.
    #[arg(long, value_name = "PATH.gif", value_parser = gif_path, conflicts_with_all = ["screenshot", "window_screenshot"])]
    pub sun_turn_gif: Option<PathBuf>,
    /// With --sun-turn-gif: the pictures of the turn, 2..=360.
    #[arg(long, value_name = "N", default_value_t = 24, requires = "sun_turn_gif", value_parser = clap::value_parser!(u32).range(2..=360))]
    pub sun_turn_frames: u32,
    /// Window or picture size in pixels (default 1280x720 / 800x450), each in 16..=8192.
    #[arg(long, value_name = "WxH", value_parser = parse_size)]
    pub size: Option<UVec2>,
}

fn output_path(text: &str) -> Result<PathBuf, String> {
    let path = PathBuf::from(text);
    image_io::check_output_path(&path).map_err(|e| e.to_string())?;
    Ok(path)
}

fn gif_path(text: &str) -> Result<PathBuf, String> {
    let path = PathBuf::from(text);
    let gif = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("gif"));
    gif.then_some(path)
        .ok_or(format!("--sun-turn-gif is {text}; it must end in .gif"))
}

fn parse_size(text: &str) -> Result<UVec2, String> {
    text.split_once('x')
        .and_then(|(w, h)| Some(UVec2::new(w.parse().ok()?, h.parse().ok()?)))
        .filter(|s| (16..=8192).contains(&s.x) && (16..=8192).contains(&s.y))
        .ok_or(format!("--size is {text}; it must be WxH, 16..=8192 each"))
}

/// Parses the example's command line (exiting with a message and code 2 on a bad one, 0 after
/// `--help`). Call it first in `main`: it also points Bevy at this crate's `assets/`.
pub fn parse_args<A: clap::Parser>() -> A {
    // Bevy finds `assets/` through `CARGO_MANIFEST_DIR` under `cargo run`; a binary started
    // directly (e.g. `target/debug/examples/snow_bunny`) looks next to itself instead. Point it at
    // this crate's `assets/`.
    if std::env::var_os("BEVY_ASSET_ROOT").is_none()
        && std::env::var_os("CARGO_MANIFEST_DIR").is_none()
    {
        // SAFETY: no other thread exists yet (`parse_args` is the first thing each example's
        // `main` calls).
        unsafe { std::env::set_var("BEVY_ASSET_ROOT", env!("CARGO_MANIFEST_DIR")) };
    }
    A::parse()
}

/// Describes an example to the runner.
pub struct Example {
    /// Window title and first line of the on-screen text.
    pub title: &'static str,
    /// The key bindings, shown on screen.
    pub controls: &'static str,
    /// Headless: whether to wait until every cloud's illumination is finished (a frame with no
    /// illumination or sort work). `false` for scenes that change every frame.
    pub steady: bool,
}

/// The camera the examples look through (and the headless runner redirects to a picture).
#[derive(Component)]
pub struct MainCamera;

/// A camera orbiting `target`: drag with the left mouse button or A/D (yaw), W/S (pitch); zoom
/// with the wheel or +/-.
#[derive(Component, Clone, Copy, Debug)]
pub struct OrbitCamera {
    /// The point looked at, metres.
    pub target: Vec3,
    /// Distance from `target`, metres.
    pub distance: f32,
    /// Radians around +Y; 0 looks along −Z.
    pub yaw: f32,
    /// Radians above the horizon of `target`.
    pub pitch: f32,
}

impl OrbitCamera {
    /// The camera's transform.
    pub fn transform(&self) -> Transform {
        let offset =
            Quat::from_euler(EulerRot::YXZ, self.yaw, -self.pitch, 0.0) * Vec3::Z * self.distance;
        Transform::from_translation(self.target + offset).looking_at(self.target, Vec3::Y)
    }
}

/// Everything of the examples' camera: HDR, ACES tonemapping (the same curve the headless
/// pictures get), a fixed exposure `ev100` (Bevy's exposure factor is `1 / (1.2 · 2^ev100)`),
/// `sky` as the clear colour (display-referred: the clear colour is not exposed).
pub fn camera(orbit: OrbitCamera, ev100: f32, sky: Color) -> impl Bundle {
    (
        Camera3d::default(),
        Camera {
            clear_color: ClearColorConfig::Custom(sky),
            ..default()
        },
        Projection::Perspective(PerspectiveProjection {
            fov: 45f32.to_radians(),
            far: 3000.0,
            ..default()
        }),
        Hdr,
        Tonemapping::AcesFitted,
        Exposure { ev100 },
        orbit.transform(),
        orbit,
        IsDefaultUiCamera,
        MainCamera,
    )
}

/// A directional light turned with four keys: azimuth −/+, elevation −/+ (60°/s).
#[derive(Component, Clone, Copy, Debug)]
pub struct KeyLight {
    /// Shown on screen, e.g. "sun".
    pub name: &'static str,
    /// Radians around +Y of the direction the light comes *from* (0 = from +X).
    pub azimuth: f32,
    /// Radians above the horizon of the direction the light comes from.
    pub elevation: f32,
    /// Azimuth −, azimuth +, elevation −, elevation +.
    pub keys: [KeyCode; 4],
}

impl KeyLight {
    /// Azimuth on ←/→, elevation on ↓/↑.
    pub const ARROWS: [KeyCode; 4] = [
        KeyCode::ArrowLeft,
        KeyCode::ArrowRight,
        KeyCode::ArrowDown,
        KeyCode::ArrowUp,
    ];

    /// The unit vector towards the light.
    pub fn towards(&self) -> Vec3 {
        let (s, c) = self.elevation.sin_cos();
        Vec3::new(c * self.azimuth.cos(), s, c * self.azimuth.sin())
    }

    /// The light's transform (its forward is the travel direction, away from the light).
    pub fn transform(&self) -> Transform {
        let up = if self.elevation.abs() > 1.5 {
            Vec3::X
        } else {
            Vec3::Y
        };
        Transform::default().looking_to(-self.towards(), up)
    }

    /// `"sun: azimuth 40 deg, elevation 25 deg"` (the default font has no degree sign).
    pub fn describe(&self) -> String {
        format!(
            "{}: azimuth {:.0} deg, elevation {:.0} deg",
            self.name,
            self.azimuth.to_degrees().rem_euclid(360.0),
            self.elevation.to_degrees()
        )
    }
}

/// A directional light of `illuminance` lux and `color`, turned by `key`. No shadow maps: clouds
/// are not meshes and cast none.
pub fn key_light(key: KeyLight, color: Color, illuminance: f32) -> impl Bundle {
    (
        DirectionalLight {
            color,
            illuminance,
            shadow_maps_enabled: false,
            ..default()
        },
        key.transform(),
        key,
    )
}

/// Sun illuminance of the outdoor examples, lux.
pub const SUN_LUX: f32 = 10_000.0;

/// The outdoor examples' sky colour as displayed (the camera's clear colour, not exposed).
const SKY_COLOR: Vec3 = Vec3::new(0.22, 0.38, 0.75);

/// The sky's radiance that lights clouds and meshes, cd/m²: half of what the exposure
/// (1 / 750) would show as `SKY_COLOR`, about 1/35 of the sun's illuminance per steradian, as in
/// a clear sky.
const SKY_NITS: f32 = 375.0;

/// Bevy's ambient light as bright as the outdoor sky on a rough ground. Under a uniform sky of
/// radiance `L` a Lambertian surface of albedo `R` shows `R L`, as the lit objects do; Bevy's
/// `StandardMaterial` shows ambient radiance `L` at perceptual roughness 1 as
/// `0.452 R L - 0.0024 L` (its split-sum approximation, `EnvBRDFApprox`). So the ground's cloud
/// shadows are lit by the sky about as a lit object's would be.
pub fn sky_ambient_on_rough_ground() -> GlobalAmbientLight {
    GlobalAmbientLight {
        color: sky_color(),
        brightness: SKY_NITS / 0.452,
        ..default()
    }
}

/// The outdoor examples' ground albedo, linear RGB: grass.
pub const GROUND_ALBEDO: Vec3 = Vec3::new(0.03, 0.055, 0.02);

/// The outdoor set of the sky examples: `ground` (a green plane at `y = 0` of
/// [`GROUND_ALBEDO`], which lights the clouds from below: `CloudGround`), a sun of [`SUN_LUX`]
/// turned with the arrow keys from `azimuth` and `elevation` (radians), a blue sky that lights
/// the clouds (`CloudSkyLight`) and, with the same radiance, the meshes (Bevy's
/// `GlobalAmbientLight`), and the camera on `orbit` (exposure ev100 9.3), drawing its clouds at
/// half its size as a game would. Returns the camera.
pub fn spawn_outdoor(
    commands: &mut Commands,
    ground: impl Bundle,
    (azimuth, elevation): (f32, f32),
    orbit: OrbitCamera,
) -> Entity {
    commands.spawn(ground);
    commands.spawn(key_light(
        KeyLight {
            name: "sun",
            azimuth,
            elevation,
            keys: [
                KeyCode::ArrowLeft,
                KeyCode::ArrowRight,
                KeyCode::ArrowDown,
                KeyCode::ArrowUp,
            ],
        },
        Color::linear_rgb(1.0, 0.95, 0.85),
        SUN_LUX,
    ));
    let sky = Color::linear_rgb(SKY_COLOR.x, SKY_COLOR.y, SKY_COLOR.z);
    commands.insert_resource(CloudSkyLight {
        color: sky,
        brightness: SKY_NITS,
    });
    commands.insert_resource(CloudGround {
        height: 0.0,
        reflectance: GROUND_ALBEDO,
    });
    commands.insert_resource(GlobalAmbientLight {
        color: sky,
        brightness: SKY_NITS,
        ..default()
    });
    commands
        .spawn((camera(orbit, 9.3, sky), CloudTargetScale(0.5)))
        .id()
}

/// The outdoor examples' sky colour: the camera's clear colour, and a fog's that fades into it.
pub fn sky_color() -> Color {
    Color::linear_rgb(SKY_COLOR.x, SKY_COLOR.y, SKY_COLOR.z)
}

/// A Lambertian ground plane of `size` metres and linear `albedo` at `y = 0` that takes the
/// clouds' shadows ([`LitObjectMaterial`] through the [`CloudShadowMaps`], which must be on):
/// lit by the clouds' lights through the clouds, and by their sky.
pub fn shadowed_ground(
    meshes: &mut Assets<Mesh>,
    materials: &mut Assets<LitObjectMaterial>,
    shadow_maps: &CloudShadowMaps,
    size: f32,
    albedo: Vec3,
) -> impl Bundle {
    (
        Mesh3d(meshes.add(Plane3d::default().mesh().size(size, size))),
        MeshMaterial3d(materials.add(LitObjectMaterial {
            surface: LitSurface {
                color: Vec3::ZERO,
                reflectance: albedo,
            },
            lights: default(),
            shadow_maps: shadow_maps.buffer.clone(),
        })),
    )
}

/// A game's ground as [`ground`] makes it (Bevy's `StandardMaterial`), extended to take the
/// clouds' shadows ([`CloudShadowedMaterial`]; the [`CloudShadowMaps`] must be on).
pub fn cloud_shadowed_ground(
    meshes: &mut Assets<Mesh>,
    materials: &mut Assets<CloudShadowedMaterial>,
    size: f32,
    color: Color,
) -> impl Bundle {
    (
        Mesh3d(meshes.add(Plane3d::default().mesh().size(size, size))),
        MeshMaterial3d(materials.add(CloudShadowedMaterial {
            base: ground_material(color),
            extension: CloudShadowReceiver::default(),
        })),
    )
}

/// The ground's `StandardMaterial`: rough, little specular.
fn ground_material(color: Color) -> StandardMaterial {
    StandardMaterial {
        base_color: color,
        perceptual_roughness: 0.95,
        reflectance: 0.1,
        ..default()
    }
}

/// A large lit ground plane of `size` metres and linear albedo `color`, at `y = 0`.
pub fn ground(
    meshes: &mut Assets<Mesh>,
    materials: &mut Assets<StandardMaterial>,
    size: f32,
    color: Color,
) -> impl Bundle {
    (
        Mesh3d(meshes.add(Plane3d::default().mesh().size(size, size))),
        MeshMaterial3d(materials.add(ground_material(color))),
    )
}

/// The example's lines of on-screen text, rewritten by its systems every frame (in [`HudLines`]).
#[derive(Resource, Default)]
pub struct Hud {
    pub lines: Vec<String>,
}

/// Systems that write [`Hud::lines`] run in this set (the text is composed after it).
#[derive(SystemSet, Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct HudLines;

/// Runs of each pass during the last rendered frame, and in total.
#[derive(Resource, Default, Clone, Debug)]
pub struct PassCounts {
    pub last: [u32; PASSES],
    /// Compute dispatches of the last frame, every pass together.
    pub dispatches_last: u32,
    pub total: [u64; PASSES],
    /// Frames counted.
    pub frames: u64,
}

impl PassCounts {
    pub fn last(&self, pass: CloudPass) -> u32 {
        self.last[pass as usize]
    }
}

#[derive(Component)]
struct HudText;

#[derive(Resource)]
struct ExampleInfo {
    title: &'static str,
    controls: &'static str,
    headless: bool,
}

/// Builds the app (a window, or headless with `--screenshot`), lets `build` add the example's
/// systems, and runs it. Exit code 0 on success, 1 on a failure, 2 on a bad command line.
pub fn run(example: Example, options: Options, build: impl FnOnce(&mut App)) -> ExitCode {
    let headless = options.screenshot.is_some() || options.sun_turn_gif.is_some();
    let mut app = if headless {
        // Already finished: plugins are added, only systems and resources may follow. The dev
        // build enables winit, whose event loop needs a display: leave it out.
        headless::app_with(headless::plugins().disable::<bevy::winit::WinitPlugin>())
    } else {
        let size = options.size.unwrap_or(UVec2::new(1280, 720));
        let mut app = App::new();
        app.add_plugins((
            DefaultPlugins.set(WindowPlugin {
                primary_window: Some(Window {
                    title: example.title.into(),
                    resolution: (size.x, size.y).into(),
                    ..default()
                }),
                ..default()
            }),
            ParticleCloudsPlugin,
            LitObjectPlugin,
            RenderDiagnosticsPlugin,
            FrameTimeDiagnosticsPlugin::default(),
        ));
        app
    };
    app.insert_resource(ExampleInfo {
        title: example.title,
        controls: example.controls,
        headless,
    })
    .init_resource::<Hud>()
    .init_resource::<PassCounts>()
    .add_systems(Startup, spawn_hud)
    .add_systems(First, count_passes)
    .add_systems(Update, (orbit_camera, turn_lights))
    .add_systems(Update, compose_hud.after(HudLines));
    build(&mut app);
    if let Some(path) = options.sun_turn_gif.clone() {
        return match sun_turn::run(app, &example, &options, &path) {
            Ok(()) => ExitCode::SUCCESS,
            Err(message) => {
                eprintln!("error: {message}");
                ExitCode::FAILURE
            }
        };
    }
    if let Some(path) = options.screenshot.clone() {
        return match run_headless(app, &example, &options, &path) {
            Ok(()) => ExitCode::SUCCESS,
            Err(message) => {
                eprintln!("error: {message}");
                ExitCode::FAILURE
            }
        };
    }
    if let Some(frames) = options.frames {
        let path = options.window_screenshot.clone();
        app.add_systems(Last, move |mut n: Local<u32>, mut commands: Commands, mut exit: MessageWriter<AppExit>| {
            *n += 1;
            if *n == frames {
                match &path {
                    None => {
                        eprintln!("{frames} frames rendered; exiting");
                        exit.write(AppExit::Success);
                    }
                    Some(path) => {
                        let path = path.clone();
                        commands.spawn(Screenshot::primary_window()).observe(
                            move |shot: On<ScreenshotCaptured>, mut exit: MessageWriter<AppExit>| {
                                let saved = shot.image.clone().try_into_dynamic().map_err(|e| e.to_string()).and_then(
                                    |image| image.to_rgb8().save(&path).map_err(|e| e.to_string()),
                                );
                                match saved {
                                    Ok(()) => {
                                        eprintln!("{frames} frames rendered; window saved to {}", path.display());
                                        exit.write(AppExit::Success);
                                    }
                                    Err(e) => {
                                        eprintln!("error: cannot save the window to {}: {e}", path.display());
                                        exit.write(AppExit::error());
                                    }
                                }
                            },
                        );
                    }
                }
            }
        });
    }
    match app.run() {
        AppExit::Success => ExitCode::SUCCESS,
        AppExit::Error(code) => ExitCode::from(code.get()),
    }
}

/// Points the example's camera at a new float image of `size`: linear radiance, exposed but not
/// tonemapped (`image_io` applies the same ACES curve when writing a PNG).
fn render_to_image(app: &mut App, size: UVec2) -> Handle<Image> {
    let target = headless::float_target(app, size.x, size.y);
    let image = target.clone();
    app.add_systems(
        PostStartup,
        move |mut commands: Commands, cameras: Query<Entity, With<MainCamera>>| {
            for camera in &cameras {
                commands.entity(camera).insert((
                    RenderTarget::Image(image.clone().into()),
                    Tonemapping::None,
                    DebandDither::Disabled,
                    Msaa::Off,
                ));
            }
        },
    );
    target
}

/// Renders `frames` frames, then, for an example whose clouds settle, until they are finished.
fn render_finished(
    app: &mut App,
    example: &Example,
    recorder: &mut FrameRecorder,
    frames: u32,
) -> Result<(), String> {
    for _ in 0..frames {
        recorder.frame(app).map_err(|e| e.to_string())?;
    }
    if example.steady {
        let clouds = drawable_clouds(app.world_mut());
        if clouds == 0 {
            return Err("the example has no drawable cloud".into());
        }
        headless::render_until_steady(app, recorder, clouds, 300).map_err(|e| e.to_string())?;
    }
    Ok(())
}

/// Renders into a float image until the clouds are finished (or `--frames`), then writes it.
fn run_headless(
    mut app: App,
    example: &Example,
    options: &Options,
    path: &std::path::Path,
) -> Result<(), String> {
    let start = Instant::now();
    let size = options.size.unwrap_or(UVec2::new(800, 450));
    let target = render_to_image(&mut app, size);
    eprintln!(
        "{}: rendering headlessly on {}",
        example.title,
        headless::adapter_name(&mut app)
    );
    let mut recorder = FrameRecorder::default();
    let min_frames = options
        .frames
        .unwrap_or(if example.steady { 2 } else { 10 });
    render_finished(&mut app, example, &mut recorder, min_frames)?;
    eprintln!(
        "{}: {} frames in {:.1} s",
        example.title,
        recorder.frames.len(),
        start.elapsed().as_secs_f64()
    );
    let picture = headless::capture(&mut app, &mut recorder, &target).map_err(|e| e.to_string())?;
    if picture.pixels.iter().flatten().any(|v| !v.is_finite()) {
        return Err("the rendered picture has non-finite pixels".into());
    }
    image_io::write_image(&picture, path).map_err(|e| e.to_string())?;
    eprintln!("{}: {}", example.title, last_gpu_times(&recorder));
    eprintln!(
        "{}: wrote {} ({}x{}) in {:.1} s",
        example.title,
        path.display(),
        size.x,
        size.y,
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Each pass's GPU time in the last recorded frame that ran it (the on-screen text shows them
/// smoothed over frames).
fn last_gpu_times(recorder: &FrameRecorder) -> String {
    let times: Vec<String> = CloudPass::ALL
        .iter()
        .map(|&pass| {
            let ms = recorder
                .frames
                .iter()
                .rev()
                .find_map(|frame| frame.gpu_ms.get(&pass));
            let ms = ms.map_or("-".to_string(), |ms| format!("{ms:.1}"));
            format!("{} {ms}", pass.name())
        })
        .collect();
    format!("GPU ms, each pass's last run: {}", times.join(", "))
}

/// Clouds whose particles are loaded and carry density.
fn drawable_clouds(world: &mut World) -> u32 {
    let mut query = world.query::<&ParticleCloud>();
    let assets = world.resource::<Assets<Particles>>();
    query
        .iter(world)
        .filter(|c| {
            c.extinction > 0.0
                && assets
                    .get(&c.particles)
                    .is_some_and(|p| p.bounds().is_some())
        })
        .count() as u32
}

fn count_passes(
    counters: Res<CloudPassCounters>,
    mut counts: ResMut<PassCounts>,
    mut snapshot: Local<[u32; PASSES]>,
    mut dispatched: Local<[u32; PASSES]>,
) {
    counts.dispatches_last = counters
        .dispatches_since(&mut dispatched)
        .iter()
        .map(|(_, n)| n)
        .sum();
    let taken = counters.since(&mut snapshot);
    for (pass, n) in taken {
        counts.last[pass as usize] = n;
        counts.total[pass as usize] += n as u64;
    }
    counts.frames += 1;
}

fn spawn_hud(mut commands: Commands) {
    commands.spawn((
        Node {
            position_type: PositionType::Absolute,
            top: Val::Px(8.0),
            left: Val::Px(8.0),
            padding: UiRect::all(Val::Px(6.0)),
            ..default()
        },
        BackgroundColor(Color::srgba(0.0, 0.0, 0.0, 0.55)),
        Text::new(""),
        TextFont::from_font_size(12.0),
        TextColor(Color::WHITE),
        HudText,
    ));
}

fn compose_hud(
    info: Res<ExampleInfo>,
    hud: Res<Hud>,
    counts: Res<PassCounts>,
    diagnostics: Option<Res<DiagnosticsStore>>,
    mut text: Query<&mut Text, With<HudText>>,
) {
    let Ok(mut text) = text.single_mut() else {
        return;
    };
    let mut s = format!("{}\n", info.title);
    for line in &hud.lines {
        s.push_str(line);
        s.push('\n');
    }
    let store = diagnostics.as_deref();
    let frame_ms = store
        .and_then(|d| d.get(&FrameTimeDiagnosticsPlugin::FRAME_TIME))
        .and_then(|d| d.smoothed());
    match frame_ms {
        Some(ms) => s.push_str(&format!(
            "frame {ms:.1} ms ({:.0} fps)\n",
            1000.0 / ms.max(1e-3)
        )),
        None if info.headless => s.push_str("frame time: n/a (headless)\n"),
        None => s.push_str("frame time: measuring…\n"),
    }
    let runs: Vec<String> = CloudPass::ALL
        .iter()
        .map(|&p| format!("{} {}", p.name(), counts.last(p)))
        .collect();
    s.push_str(&format!("runs last frame: {}\n", runs.join(", ")));
    let gpu: Vec<String> = CloudPass::ALL
        .iter()
        .map(|&p| {
            // The draw at full size or into a cloud target, whichever this view does.
            let ms = p
                .diagnostic_paths()
                .iter()
                .filter_map(|path| store.and_then(|d| d.get(path)).and_then(|d| d.smoothed()))
                .reduce(f64::max);
            format!(
                "{} {}",
                p.name(),
                ms.map_or("-".to_string(), |ms| format!("{ms:.2}"))
            )
        })
        .collect();
    s.push_str(&format!("GPU ms: {}\n", gpu.join(", ")));
    s.push_str(info.controls);
    if text.0 != s {
        text.0 = s;
    }
}

fn orbit_camera(
    time: Res<Time>,
    keys: Res<ButtonInput<KeyCode>>,
    buttons: Res<ButtonInput<MouseButton>>,
    motion: Res<AccumulatedMouseMotion>,
    scroll: Res<AccumulatedMouseScroll>,
    mut cameras: Query<(&mut OrbitCamera, &mut Transform)>,
) {
    let dt = time.delta_secs();
    let axis = |neg: KeyCode, pos: KeyCode| {
        keys.pressed(pos) as i32 as f32 - keys.pressed(neg) as i32 as f32
    };
    let mut yaw = axis(KeyCode::KeyA, KeyCode::KeyD) * 1.2 * dt;
    let mut pitch = axis(KeyCode::KeyS, KeyCode::KeyW) * 0.8 * dt;
    if buttons.pressed(MouseButton::Left) {
        yaw -= motion.delta.x * 0.005;
        pitch += motion.delta.y * 0.005;
    }
    let wheel = match scroll.unit {
        MouseScrollUnit::Line => scroll.delta.y,
        MouseScrollUnit::Pixel => scroll.delta.y / 40.0,
    };
    let zoom_keys =
        axis(KeyCode::Equal, KeyCode::Minus) + axis(KeyCode::NumpadAdd, KeyCode::NumpadSubtract);
    let zoom = (-wheel * 0.1).exp() * (zoom_keys * dt).exp();
    for (mut orbit, mut transform) in &mut cameras {
        if yaw == 0.0 && pitch == 0.0 && zoom == 1.0 {
            continue;
        }
        orbit.yaw += yaw;
        orbit.pitch = (orbit.pitch + pitch).clamp(-1.2, 1.45);
        orbit.distance = (orbit.distance * zoom).clamp(0.5, 2000.0);
        *transform = orbit.transform();
    }
}

fn turn_lights(
    time: Res<Time>,
    keys: Res<ButtonInput<KeyCode>>,
    mut lights: Query<(&mut KeyLight, &mut Transform)>,
) {
    let rate = 60f32.to_radians() * time.delta_secs();
    for (mut light, mut transform) in &mut lights {
        let axis = |neg: KeyCode, pos: KeyCode| {
            keys.pressed(pos) as i32 as f32 - keys.pressed(neg) as i32 as f32
        };
        let azimuth = axis(light.keys[0], light.keys[1]) * rate;
        let elevation = axis(light.keys[2], light.keys[3]) * rate;
        if azimuth == 0.0 && elevation == 0.0 {
            continue;
        }
        light.azimuth += azimuth;
        light.elevation = (light.elevation + elevation).clamp(-1.5, 1.5);
        *transform = light.transform();
    }
}
