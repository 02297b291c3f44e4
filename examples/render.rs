//! Renders a scene file headlessly: the project's main job, and the driver of its tests and
//! benchmarks.
//!
//! ```text
//! cargo run --example render -- SCENE.ron --out IMAGE.(exr|png) [--stats STATS.json] [--frames N]
//! cargo run --example render -- SCENE.ron --reference [--spp N] [--seed S] --out ref.exr
//! cargo run --example render                      # built-in cumulus → clouds.png
//! ```
//!
//! `.exr` holds linear radiance at exposure 1 (PHYSICS.md units); `.png` the same, tonemapped.
//! `--reference` renders with the CPU ground-truth path tracer instead of the GPU.

#[path = "../tests/common/headless.rs"]
mod headless;

use std::{path::PathBuf, process::ExitCode, time::Instant};

use bevy::{
    math::Vec3,
    render::{RenderApp, renderer::RenderDevice},
};
use bevy_particle_clouds::{
    CloudPass, CloudQualitySettings, generators,
    image_io::{LinearImage, write_image},
    particle::{LightSample, Medium},
    reference::path_tracer::{self, PathTracerSettings},
    render::volumes::largest_binding,
    scene::{ResolvedCloud, Scene, SceneCamera},
};
use headless::{FrameRecorder, FrameStats};

const USAGE: &str = "usage: render [SCENE.ron --out IMAGE.(exr|png)] [--stats STATS.json] [--frames N] \
[--reference [--spp N] [--seed S]]";

struct Args {
    scene: Option<PathBuf>,
    out: PathBuf,
    stats: Option<PathBuf>,
    frames: usize,
    reference: bool,
    spp: u32,
    seed: u64,
}

fn parse_args() -> Result<Args, String> {
    let mut args = Args {
        scene: None,
        out: PathBuf::from("clouds.png"),
        stats: None,
        frames: 1,
        reference: false,
        spp: 256,
        seed: 1,
    };
    let mut out_given = false;
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        let mut value = |name: &str| it.next().ok_or(format!("{name} needs a value\n{USAGE}"));
        match arg.as_str() {
            "--out" => {
                args.out = value("--out")?.into();
                out_given = true;
            }
            "--stats" => args.stats = Some(value("--stats")?.into()),
            "--frames" => {
                let v = value("--frames")?;
                args.frames = v
                    .parse()
                    .ok()
                    .filter(|&n| n >= 1)
                    .ok_or(format!("--frames is {v}; it must be an integer >= 1"))?;
            }
            "--spp" => {
                let v = value("--spp")?;
                args.spp = v
                    .parse()
                    .ok()
                    .filter(|&n| n >= 1)
                    .ok_or(format!("--spp is {v}; it must be an integer >= 1"))?;
            }
            "--seed" => {
                let v = value("--seed")?;
                args.seed = v
                    .parse()
                    .map_err(|_| format!("--seed is {v}; it must be an unsigned integer"))?;
            }
            "--reference" => args.reference = true,
            "-h" | "--help" => return Err(USAGE.into()),
            flag if flag.starts_with("--") => {
                return Err(format!("unknown option {flag}\n{USAGE}"));
            }
            path if args.scene.is_none() => args.scene = Some(path.into()),
            extra => return Err(format!("unexpected argument {extra}\n{USAGE}")),
        }
    }
    if args.scene.is_some() && !out_given {
        return Err(format!("--out is required with a scene file\n{USAGE}"));
    }
    Ok(args)
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
            },
            particles: generators::cumulus(2.5, 3000, 7).particles,
        }],
        objects: vec![],
        settings: CloudQualitySettings {
            volume_resolution: 64,
            scatter_iterations: 16,
            ..Default::default()
        },
    }
}

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("error: {message}");
            ExitCode::from(2)
        }
    }
}

fn run() -> Result<(), String> {
    let args = parse_args()?;
    let start = Instant::now();
    let scene = match &args.scene {
        Some(path) => Scene::load(path).map_err(|e| e.to_string())?,
        None => default_scene(),
    };
    let particles: usize = scene.clouds.iter().map(|c| c.particles.len()).sum();
    eprintln!(
        "render: scene {} ({} clouds, {particles} particles, {} lights, {}x{}) loaded in {:.0} ms",
        args.scene
            .as_ref()
            .map_or("<built-in cumulus>".into(), |p| p.display().to_string()),
        scene.clouds.len(),
        scene.lights.len(),
        scene.camera.width,
        scene.camera.height,
        start.elapsed().as_secs_f64() * 1e3
    );
    // Refuse before rendering anything: the output must be writable as asked.
    bevy_particle_clouds::image_io::check_output_path(&args.out).map_err(|e| e.to_string())?;
    let image = if args.reference {
        reference(&scene, &args)
    } else {
        real_time(&scene, &args)?
    };
    write_image(&image, &args.out).map_err(|e| e.to_string())?;
    eprintln!(
        "render: wrote {} in {:.1} s total",
        args.out.display(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

fn reference(scene: &Scene, args: &Args) -> LinearImage {
    let start = Instant::now();
    eprintln!(
        "render: path tracing at {} samples per pixel (seed {})",
        args.spp, args.seed
    );
    let pixels = path_tracer::render(
        scene,
        &PathTracerSettings {
            samples_per_pixel: args.spp,
            seed: args.seed,
            progress: true,
        },
    );
    eprintln!(
        "render: path traced in {:.1} s",
        start.elapsed().as_secs_f64()
    );
    LinearImage {
        width: scene.camera.width,
        height: scene.camera.height,
        pixels,
    }
}

fn real_time(scene: &Scene, args: &Args) -> Result<LinearImage, String> {
    let start = Instant::now();
    let mut app = headless::headless_app();
    let adapter = headless::adapter_name(&mut app);
    let limit = app
        .sub_app(RenderApp)
        .world()
        .resource::<RenderDevice>()
        .limits()
        .max_storage_buffer_binding_size as u64;
    let resolution = scene.settings.volume_resolution;
    let lights = scene.lights.len();
    let bytes = |n: u32| {
        let settings = CloudQualitySettings {
            volume_resolution: n,
            ..scene.settings
        };
        largest_binding(n, settings.light_resolution(), lights)
    };
    if bytes(resolution) > limit {
        return Err(format!(
            "settings.volume_resolution is {resolution} (light volumes of {}³ for {lights} lights); \
             this adapter ({adapter}) allows at most {} (its storage buffers hold {limit} bytes)",
            scene.settings.light_resolution(),
            (1..=resolution)
                .rev()
                .find(|&n| bytes(n) <= limit)
                .unwrap_or(0)
        ));
    }
    eprintln!(
        "render: adapter {adapter}, started in {:.0} ms",
        start.elapsed().as_secs_f64() * 1e3
    );
    let target = headless::spawn_scene(&mut app, scene);
    let mut recorder = FrameRecorder::default();
    let warmup = headless::render_until_steady(&mut app, &mut recorder, &target, 100);
    eprintln!(
        "render: illumination finished and drawn after {warmup} frames ({:.0} ms)",
        start.elapsed().as_secs_f64() * 1e3
    );
    for i in 1..args.frames {
        let frame = recorder.frame(&mut app);
        eprintln!(
            "render: frame {}/{}: {:.1} ms",
            i, args.frames, frame.wall_ms
        );
    }
    let image = headless::capture(&mut app, &mut recorder, &target);
    for _ in 0..3 {
        recorder.drain(&mut app); // late GPU timestamps
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
    Ok(image)
}

/// The `--stats` file (schema in the README).
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
