//! Renders a scene file headlessly: the project's main job, and the driver of its tests and
//! benchmarks.
//!
//! ```text
//! cargo run --example render -- SCENE.ron --out IMAGE.(exr|png) [--stats STATS.json] [--frames N]
//!                                [--size WxH] [--set FIELD=VALUE]... [--allow-outside-paths]
//! cargo run --example render -- SCENE.ron --reference [--spp N] [--seed S] [--time-limit SECONDS] --out ref.exr
//! cargo run --example render                      # built-in cumulus → clouds.png
//! cargo run --example render -- --help            # every flag
//! ```
//!
//! `.exr` holds linear radiance at exposure 1 (docs/physics.md units) and the render's metadata
//! (software, adapter, settings, samples and seed, render time, camera); `.png` the same image,
//! tonemapped. `--reference` renders with the CPU ground-truth path tracer instead of the GPU.

use std::{
    path::PathBuf,
    process::ExitCode,
    time::{Duration, Instant},
};

use bevy::{
    math::{UVec2, Vec3},
    render::{RenderApp, renderer::RenderDevice},
};
use bevy_particle_clouds::{
    CloudPass, CloudQualitySettings, generators,
    headless::{self, FrameRecorder, FrameStats},
    image_io::{ImageMetadata, LinearImage, write_exr_with_metadata, write_image},
    particle::{LightSample, Medium},
    reference::path_tracer::{self, PathTracerSettings, Progress},
    render::pools::VolumeShape,
    scene::{MAX_IMAGE_SIZE, ParticlePaths, ResolvedCloud, Scene, SceneCamera, apply_setting},
};
use clap::Parser;
use indicatif::{ProgressBar, ProgressStyle};

/// Renders a scene file on the GPU (or with the CPU path tracer) into an EXR or PNG image.
#[derive(Parser, Debug)]
#[command(
    version,
    after_help = "Without SCENE, renders a built-in cumulus into clouds.png."
)]
struct Args {
    /// The scene file (RON, docs/scene-format.md).
    #[arg(requires = "out")]
    scene: Option<PathBuf>,
    /// The image to write: .exr (linear radiance, with metadata) or .png (tonemapped).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write per-frame pass runs and GPU times to this JSON file.
    #[arg(long, value_name = "STATS.json")]
    stats: Option<PathBuf>,
    /// Frames to render and time once the illumination is finished.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    frames: u32,
    /// Render with the CPU path tracer (the ground truth) instead of the GPU.
    #[arg(long)]
    reference: bool,
    /// Path-traced samples per pixel.
    #[arg(long, requires = "reference", value_parser = clap::value_parser!(u32).range(1..))]
    spp: Option<u32>,
    /// Seed of the path tracer's random numbers.
    #[arg(long, requires = "reference")]
    seed: Option<u64>,
    /// Stop the path tracer after about this many seconds (at most about twice it), with the
    /// samples per pixel it finished, written to the image's metadata.
    #[arg(long, value_name = "SECONDS", requires = "reference", value_parser = parse_seconds)]
    time_limit: Option<Duration>,
    /// Image size in pixels, replacing the scene camera's.
    #[arg(long, value_name = "WxH", value_parser = parse_size)]
    size: Option<UVec2>,
    /// Override a quality setting as in a scene file's `settings`, e.g. volume_resolution=64.
    /// Repeatable.
    #[arg(long = "set", value_name = "FIELD=VALUE")]
    settings: Vec<String>,
    /// Let the scene file read particle files outside its own folder (absolute paths, `..`,
    /// symbolic links out of it). Without it a scene file reads only files inside its folder.
    #[arg(long, requires = "scene")]
    allow_outside_paths: bool,
}

/// Seconds, finite and > 0.
fn parse_seconds(text: &str) -> Result<Duration, String> {
    text.parse::<f64>()
        .ok()
        .and_then(|s| Duration::try_from_secs_f64(s).ok())
        .filter(|d| !d.is_zero())
        .ok_or(format!(
            "--time-limit is {text}; it must be a number of seconds > 0"
        ))
}

/// `WxH`, each in `1..=MAX_IMAGE_SIZE`.
fn parse_size(text: &str) -> Result<UVec2, String> {
    let allowed = format!("it must be WxH with each in 1..={MAX_IMAGE_SIZE}, e.g. 640x480");
    let (w, h) = text
        .split_once(['x', 'X'])
        .ok_or(format!("--size is {text}; {allowed}"))?;
    let size = UVec2::new(
        w.parse()
            .map_err(|_| format!("--size is {text}; {allowed}"))?,
        h.parse()
            .map_err(|_| format!("--size is {text}; {allowed}"))?,
    );
    if size.min_element() == 0 || size.max_element() > MAX_IMAGE_SIZE {
        return Err(format!("--size is {text}; {allowed}"));
    }
    Ok(size)
}

/// The built-in scene: a cumulus lit by a low, warm sun against a blue sky.
fn default_scene() -> Scene {
    Scene {
        camera: SceneCamera {
            position: Vec3::new(0.0, 0.4, 5.5),
            look_at: Vec3::new(0.0, 0.25, 0.0),
            up: Vec3::Y,
            vertical_fov_degrees: 40.0,
            width: 480,
            height: 320,
        },
        background: Vec3::new(0.18, 0.3, 0.55),
        lights: vec![LightSample {
            direction: Vec3::new(-0.8, -0.35, -0.6),
            irradiance: Vec3::new(9.0, 8.2, 7.0),
        }],
        clouds: vec![ResolvedCloud {
            translation: Vec3::ZERO,
            medium: Medium {
                extinction: 8.0,
                albedo: 0.99,
                ..Default::default()
            },
            particles: generators::cumulus(2.5, 3000, 7).particles,
        }],
        objects: vec![],
        fog: None,
        shadow_map_resolution: bevy_particle_clouds::scene::DEFAULT_SHADOW_MAP_RESOLUTION,
        settings: CloudQualitySettings {
            volume_resolution: 64,
            scatter_iterations: 16,
            ..Default::default()
        },
    }
}

fn main() -> ExitCode {
    let args = Args::parse();
    match run(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("error: {message}");
            ExitCode::from(2)
        }
    }
}

fn run(args: &Args) -> Result<(), String> {
    let start = Instant::now();
    let mut scene = match &args.scene {
        Some(path) => {
            let paths = if args.allow_outside_paths {
                ParticlePaths::Anywhere
            } else {
                ParticlePaths::InsideSceneFolder
            };
            Scene::load_with(path, paths).map_err(|e| e.to_string())?
        }
        None => default_scene(),
    };
    for assignment in &args.settings {
        apply_setting(&mut scene.settings, assignment).map_err(|e| e.to_string())?;
    }
    if let Some(size) = args.size {
        (scene.camera.width, scene.camera.height) = (size.x, size.y);
    }
    let out = args.out.clone().unwrap_or_else(|| "clouds.png".into());
    let particles: usize = scene.clouds.iter().map(|c| c.particles.len()).sum();
    let scene_name = args
        .scene
        .as_ref()
        .map_or("<built-in cumulus>".into(), |p| p.display().to_string());
    eprintln!(
        "render: scene {scene_name} ({} clouds, {particles} particles, {} lights, {}x{}) loaded in {:.0} ms",
        scene.clouds.len(),
        scene.lights.len(),
        scene.camera.width,
        scene.camera.height,
        start.elapsed().as_secs_f64() * 1e3
    );
    // Refuse before rendering anything: the output must be writable as asked.
    bevy_particle_clouds::image_io::check_output_path(&out).map_err(|e| e.to_string())?;
    let metadata = ImageMetadata::software()
        .with("scene", &scene_name)
        .with("camera", format!("{:?}", scene.camera));
    let (image, metadata) = if args.reference {
        reference(&scene, args, metadata)
    } else {
        real_time(&scene, args, metadata)?
    };
    let metadata = metadata.with(
        "render_time_s",
        format!("{:.3}", start.elapsed().as_secs_f64()),
    );
    let exr = out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("exr"));
    if exr {
        write_exr_with_metadata(&image, &out, &metadata)
    } else {
        write_image(&image, &out)
    }
    .map_err(|e| e.to_string())?;
    eprintln!(
        "render: wrote {} in {:.1} s total",
        out.display(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

fn reference(scene: &Scene, args: &Args, metadata: ImageMetadata) -> (LinearImage, ImageMetadata) {
    let start = Instant::now();
    let (spp, seed) = (args.spp.unwrap_or(256), args.seed.unwrap_or(1));
    eprintln!("render: path tracer at {spp} samples per pixel (seed {seed})");
    let bar = ProgressBar::new(scene.camera.height as u64).with_style(
        ProgressStyle::with_template("path tracer {bar:40} {pos}/{len} rows, {eta} left")
            .expect("progress template"),
    );
    let rows = bar.clone();
    let (pixels, spp_done) = path_tracer::render_within_limit(
        scene,
        &PathTracerSettings {
            samples_per_pixel: spp,
            seed,
            progress: Some(Progress::new(move |done, all| {
                rows.set_length(all as u64);
                rows.set_position(done as u64)
            })),
            time_limit: args.time_limit,
        },
    );
    bar.finish_and_clear();
    if spp_done < spp {
        eprintln!(
            "render: the time limit stopped the path tracer at {spp_done} of {spp} samples per pixel"
        );
    }
    eprintln!(
        "render: path traced in {:.1} s",
        start.elapsed().as_secs_f64()
    );
    let spp = spp_done;
    let image = LinearImage {
        width: scene.camera.width,
        height: scene.camera.height,
        pixels,
    };
    let metadata = metadata
        .with("renderer", "path tracer")
        .with("spp", spp)
        .with("seed", seed);
    (image, metadata)
}

fn real_time(
    scene: &Scene,
    args: &Args,
    metadata: ImageMetadata,
) -> Result<(LinearImage, ImageMetadata), String> {
    let start = Instant::now();
    // The dev build enables winit, whose event loop needs a display: leave it out.
    let mut app = headless::app_with(headless::plugins().disable::<bevy::winit::WinitPlugin>());
    let adapter = headless::adapter_name(&mut app);
    check_volume_fits(&mut app, scene, &adapter)?;
    eprintln!(
        "render: adapter {adapter}, started in {:.0} ms",
        start.elapsed().as_secs_f64() * 1e3
    );
    let target = headless::spawn_scene(&mut app, scene);
    let mut recorder = FrameRecorder::default();
    let warmup =
        headless::render_until_steady(&mut app, &mut recorder, target.drawable_clouds, 100)
            .map_err(|e| e.to_string())?;
    eprintln!(
        "render: illumination finished and drawn after {warmup} frames ({:.0} ms)",
        start.elapsed().as_secs_f64() * 1e3
    );
    for i in 1..args.frames {
        let frame = recorder.frame(&mut app).map_err(|e| e.to_string())?;
        eprintln!(
            "render: frame {}/{}: {:.1} ms",
            i, args.frames, frame.wall_ms
        );
    }
    let image =
        headless::capture(&mut app, &mut recorder, &target.image).map_err(|e| e.to_string())?;
    for _ in 0..3 {
        recorder.drain(&mut app).map_err(|e| e.to_string())?; // late GPU timestamps
    }
    if let Some(path) = &args.stats {
        write_stats(path, &adapter, &recorder.frames)?;
        eprintln!(
            "render: wrote statistics of {} frames to {}",
            recorder.frames.len(),
            path.display()
        );
    }
    if image.pixels.iter().flatten().any(|v| !v.is_finite()) {
        return Err("the rendered image has non-finite pixels".into());
    }
    let metadata = metadata
        .with("renderer", "real-time")
        .with("adapter", &adapter)
        .with("settings", format!("{:?}", scene.settings));
    Ok((image, metadata))
}

/// Refuses a `volume_resolution` whose volumes the adapter cannot bind, naming the largest that
/// fits and the `light_supersampling` that would fit at this resolution. The renderer itself
/// would lower the fine grid with a warning; a scene file renders what it says, or nothing.
/// The default supersampling is "4, or the largest fine grid the adapter's binding holds"
/// (scene-format.md): at it, the fine grid is lowered as in a game, and said on stderr.
fn check_volume_fits(app: &mut bevy::app::App, scene: &Scene, adapter: &str) -> Result<(), String> {
    let limit = app
        .sub_app(RenderApp)
        .world()
        .resource::<RenderDevice>()
        .limits()
        .max_storage_buffer_binding_size;
    let resolution = scene.settings.volume_resolution;
    let lights = scene.lights.len() as u32;
    // An anisotropic medium's scattering volumes also hold the radiance's angular moments.
    let moments = scene.clouds.iter().any(|c| c.medium.anisotropy != 0.0);
    let fitting = |settings: &CloudQualitySettings| {
        VolumeShape::fitting_light_resolution(settings, lights, moments, limit)
    };
    // The scene's settings at resolution `n` fit without lowering their fine grid.
    let fits = |n: u32| {
        let settings = CloudQualitySettings {
            volume_resolution: n,
            ..scene.settings
        };
        fitting(&settings) == Some(settings.light_resolution())
    };
    if fits(resolution) {
        return Ok(());
    }
    let wanted = scene.settings.light_resolution();
    let lower = fitting(&scene.settings);
    if let Some(m) = lower.filter(|_| scene.settings.light_supersampling_is_default()) {
        eprintln!(
            "render: light volumes of {wanted}³ for {lights} lights exceed this adapter's \
             storage buffers ({limit} bytes); the default light_supersampling's fine grid is \
             lowered to {m}³"
        );
        return Ok(());
    }
    let largest = (1..=resolution).rev().find(|&n| fits(n));
    // The fine grid that fits holds a whole factor of at least 1.
    let or_lower = lower.map_or(String::new(), |m| {
        let f = m / resolution;
        format!(", or settings.light_supersampling {f} at this resolution")
    });
    Err(format!(
        "settings.volume_resolution is {resolution} (light volumes of {wanted}³ for {lights} \
         lights); this adapter ({adapter}) allows at most {}{or_lower} (its storage buffers hold \
         {limit} bytes)",
        largest.unwrap_or(0)
    ))
}

/// The `--stats` file (schema in docs/tools.md, "Statistics").
fn write_stats(path: &std::path::Path, adapter: &str, frames: &[FrameStats]) -> Result<(), String> {
    let frames: Vec<serde_json::Value> = frames
        .iter()
        .map(|f| {
            let passes: serde_json::Map<_, _> = CloudPass::ALL
                .iter()
                .map(|&p| (p.name().to_string(), f.runs(p).into()))
                .collect();
            let gpu: serde_json::Map<_, _> = CloudPass::ALL
                .iter()
                .map(|&p| {
                    (
                        p.name().to_string(),
                        f.gpu_ms
                            .get(&p)
                            .map_or(serde_json::Value::Null, |&ms| ms.into()),
                    )
                })
                .collect();
            serde_json::json!({ "wall_ms": f.wall_ms, "passes": passes, "gpu_ms": gpu })
        })
        .collect();
    let json = serde_json::json!({ "adapter": adapter, "frames": frames });
    std::fs::write(path, serde_json::to_string_pretty(&json).expect("JSON"))
        .map_err(|e| format!("cannot write --stats file {}: {e}", path.display()))
}
