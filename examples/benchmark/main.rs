//! The time–error benchmark: renders fixed benchmark scenes with the real-time renderer over a
//! sweep of its quality knobs, measures GPU time (timestamp queries, summed over passes) and wall
//! time per frame, and compares every image with a path-traced ground truth (PHYSICS.md's relative
//! RMSE, relMSE and mean absolute error, beside the reference's own sample count and noise level).
//!
//! ```text
//! cargo run --example benchmark -- [--quick] [--out DIR] [--scenes a,b] [--frames K] [--font TTF]
//! cargo run --example benchmark -- --settings '(volume_resolution: 64)' [--settings …] [--scenes a,b]
//! cargo run --example benchmark -- --illumination [--out DIR]
//! cargo run --example benchmark -- --decompose [--scenes a,b] [--spp N] [--out DIR]
//! ```
//!
//! Writes `DIR/results.csv`, `DIR/results.md` and `DIR/pareto.png` (default `DIR` is
//! `target/benchmark`); path-traced references are cached as `DIR/reference-<hash>-s<seed>.exr`,
//! keyed by a hash of the scene contents, image size, sample count and seed, so a rerun does not
//! trace them again. `--illumination` instead writes `DIR/illumination.csv` and `.md`: every
//! pass's GPU time at 32³ and 64³ (light volumes of 64³ and 128³) with 1 and 5 lights,
//! incremental shading against the brute force march (`ShadingMethod::BruteForce`). `--decompose` writes `DIR/decomposition.md`: the
//! default settings' error split into single scattering, each scattering order and the closure,
//! against the path tracer split by order (CPU references, no adapter; see `decompose.rs`).
//!
//! Timing. The GPU time of a setting is the sum of the per-pass GPU times (Bevy's render
//! diagnostics; `FrameStats::gpu_ms` of the headless harness) of a frame in which every pass runs:
//! each measured frame touches the cloud's `Particles` asset, which re-uploads it and reruns
//! voxelize, shade (every light), gather, scatter and sort; the draw (the `Transparent3d` pass,
//! `main_transparent_pass_3d`) runs every frame anyway. The static cost is that of a frame where
//! nothing changed: the draw only. Both are medians over `--frames` frames, wall time beside them.

mod decompose;
#[path = "../../tests/common/headless.rs"]
mod headless;

use std::{
    collections::HashMap,
    fmt::Write as _,
    path::{Path, PathBuf},
    process::ExitCode,
    time::Instant,
};

use bevy::{diagnostic::DiagnosticsStore, prelude::*};
use bevy_particle_clouds::{
    CloudPass, CloudQualitySettings, Compositing, PASSES, Particle, ParticleCloud, Particles,
    ScatterStencil,
    image_io::{LinearImage, read_exr, write_exr, write_png},
    math::SplitMix64,
    particle_files::{write_csv, write_ply_binary},
    reference::{
        metrics::{mean_absolute_error, rel_mse, relative_rmse},
        path_tracer::{self, PathTracerSettings, noise_level},
    },
    scene::Scene,
    settings::ShadingMethod,
};
use headless::{FrameRecorder, FrameStats};

const USAGE: &str = "usage: benchmark [--quick | --decompose] [--out DIR] [--scenes NAME,NAME] [--frames K] [--spp N] \
[--font TTF] [--illumination] [--replot] [--settings RON]...";

/// Where Debian's `fonts-dejavu-core` puts the font of the plot's labels.
const DEFAULT_FONT: &str = "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf";

/// Bevy's render diagnostic of the transparent pass: the cloud billboards are its only items.
const DRAW_DIAGNOSTIC: &str = "render/main_transparent_pass_3d/elapsed_gpu";

struct Args {
    quick: bool,
    out: PathBuf,
    scenes: Option<Vec<String>>,
    frames: usize,
    font: PathBuf,
    illumination: bool,
    /// Overrides every scene's reference samples per pixel.
    spp: Option<u32>,
    /// Only redraw `DIR/pareto.png` from `DIR/results.csv`.
    replot: bool,
    /// Split the default settings' error by scattering order (CPU only).
    decompose: bool,
    /// Measure only these settings instead of the sweep (`--settings RON`, repeatable).
    settings: Vec<CloudQualitySettings>,
}

fn parse_args() -> Result<Args, String> {
    let mut args = Args {
        quick: false,
        out: PathBuf::from("target/benchmark"),
        scenes: None,
        frames: 3,
        font: PathBuf::from(DEFAULT_FONT),
        illumination: false,
        spp: None,
        replot: false,
        decompose: false,
        settings: Vec::new(),
    };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        let mut value = |name: &str| it.next().ok_or(format!("{name} needs a value\n{USAGE}"));
        match arg.as_str() {
            "--quick" => args.quick = true,
            "--illumination" => args.illumination = true,
            "--replot" => args.replot = true,
            "--decompose" => args.decompose = true,
            "--out" => args.out = value("--out")?.into(),
            "--font" => args.font = value("--font")?.into(),
            "--scenes" => {
                args.scenes = Some(value("--scenes")?.split(',').map(str::to_string).collect())
            }
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
                args.spp = Some(
                    v.parse()
                        .ok()
                        .filter(|&n| n >= 1)
                        .ok_or(format!("--spp is {v}; it must be an integer >= 1"))?,
                );
            }
            "--settings" => {
                let v = value("--settings")?;
                args.settings
                    .push(ron::from_str(&v).map_err(|e| format!("--settings {v}: {e}"))?);
            }
            "-h" | "--help" => return Err(USAGE.into()),
            other => return Err(format!("unknown argument {other}\n{USAGE}")),
        }
    }
    Ok(args)
}

// ---------------------------------------------------------------------------------------------
// Benchmark scenes
// ---------------------------------------------------------------------------------------------

/// A scene of the benchmark: a file under `benchmarks/scenes/`, its particle file (generated by
/// `generate` when missing), the size errors are measured at and the reference's samples.
struct BenchScene {
    name: &'static str,
    /// Particle file next to the scene file, written by `generate` when missing ("" for a scene
    /// with inline particles).
    particle_file: &'static str,
    generate: fn() -> Vec<Particle>,
    /// The real-time image is box-filtered by this integer factor before it is compared with a
    /// reference rendered at the reduced size (the path tracer jitters over whole pixels, so a
    /// reference pixel is exactly the average of the pixels it covers).
    error_downsample: u32,
    /// Samples per pixel of each of the two reference renders (they are averaged), chosen so that
    /// the reference's noise is at most a third of the scene's accuracy goal; a quarter of this
    /// with `--quick`.
    spp: u32,
    /// Part of `--quick`.
    quick: bool,
}

const SCENES: &[BenchScene] = &[
    BenchScene {
        name: "thin_smoke",
        particle_file: "thin_smoke.csv",
        generate: thin_smoke,
        error_downsample: 2,
        spp: 20480,
        quick: true,
    },
    BenchScene {
        name: "cumulus",
        particle_file: "cumulus.csv",
        generate: cumulus_2000,
        error_downsample: 2,
        spp: 2048,
        quick: true,
    },
    BenchScene {
        name: "cumulus_side",
        particle_file: "cumulus.csv",
        generate: cumulus_2000,
        error_downsample: 2,
        spp: 2048,
        quick: true,
    },
    BenchScene {
        name: "cumulus_back",
        particle_file: "cumulus.csv",
        generate: cumulus_2000,
        error_downsample: 2,
        spp: 4096,
        quick: true,
    },
    BenchScene {
        name: "two_lights",
        particle_file: "two_lights.csv",
        generate: round_cloud,
        error_downsample: 2,
        spp: 6144,
        quick: true,
    },
    BenchScene {
        name: "single_particle",
        particle_file: "",
        generate: Vec::new,
        error_downsample: 2,
        spp: 8192,
        quick: true,
    },
    BenchScene {
        name: "albedo_one",
        particle_file: "two_lights.csv",
        generate: round_cloud,
        error_downsample: 2,
        spp: 2560,
        quick: true,
    },
    BenchScene {
        name: "paper_3100",
        particle_file: "paper_3100.ply",
        generate: paper_3100,
        error_downsample: 4,
        spp: 512,
        quick: false,
    },
    BenchScene {
        name: "paper_38k_1light",
        particle_file: "paper_38k.ply",
        generate: paper_38k,
        error_downsample: 4,
        spp: 512,
        quick: false,
    },
    BenchScene {
        name: "paper_38k_5lights",
        particle_file: "paper_38k.ply",
        generate: paper_38k,
        error_downsample: 4,
        spp: 512,
        quick: false,
    },
];

/// A rising, widening and thinning plume of smoke, 2 m tall.
fn thin_smoke() -> Vec<Particle> {
    let mut rng = SplitMix64::new(11);
    (0..800)
        .map(|_| {
            let t = rng.next_f32();
            let axis = Vec3::new(
                0.35 * (3.0 * t).sin(),
                -1.0 + 2.0 * t,
                0.2 * (2.0 * t).cos(),
            );
            let spread = 0.12 + 0.35 * t;
            Particle {
                position: axis + rng.in_unit_ball() * spread,
                radius: 0.1 + 0.2 * t,
                density: 1.0 - 0.6 * t,
            }
        })
        .collect()
}

/// A cumulus of `count` puffs about `size` metres across: lobes around a core, a flat base.
fn cumulus(size: f32, count: usize, puff: f32, seed: u64) -> Vec<Particle> {
    let mut rng = SplitMix64::new(seed);
    let lobes: Vec<(Vec3, f32)> = (0..7)
        .map(|i| {
            let a = i as f32 / 7.0 * std::f32::consts::TAU + rng.next_f32();
            let r = if i == 0 {
                0.0
            } else {
                0.28 + 0.12 * rng.next_f32()
            };
            let centre = Vec3::new(a.cos() * r, 0.1 + 0.25 * rng.next_f32(), a.sin() * r * 0.7);
            (centre * size, size * (0.22 + 0.12 * rng.next_f32()))
        })
        .collect();
    (0..count)
        .map(|i| {
            let (centre, lobe_radius) = lobes[i % lobes.len()];
            let mut p = centre + rng.in_unit_ball() * lobe_radius;
            p.y = p.y.max(-0.05 * size);
            let core = 1.0 - ((p - centre).length() / lobe_radius).min(1.0);
            Particle {
                position: p,
                radius: size * puff * (1.0 + core),
                density: 0.5 + 0.5 * core,
            }
        })
        .collect()
}

fn cumulus_2000() -> Vec<Particle> {
    cumulus(2.5, 2000, 0.05, 7)
}

fn paper_3100() -> Vec<Particle> {
    cumulus(2.5, 3100, 0.045, 31)
}

fn paper_38k() -> Vec<Particle> {
    cumulus(2.5, 38_000, 0.02, 38)
}

/// A round cloud 2.4 m across (the paper's Figure 2 lights it from two sides).
fn round_cloud() -> Vec<Particle> {
    let mut rng = SplitMix64::new(2);
    (0..600)
        .map(|_| {
            let p = rng.in_unit_ball();
            Particle {
                position: p * 1.1,
                radius: 0.2 + 0.15 * rng.next_f32(),
                density: 1.0 - 0.5 * p.length(),
            }
        })
        .collect()
}

fn scenes_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("benchmarks/scenes")
}

/// Loads a benchmark scene, writing its particle file first when it is missing.
fn load_scene(bench: &BenchScene) -> Result<Scene, String> {
    let dir = scenes_dir();
    let particles = dir.join(bench.particle_file);
    if !bench.particle_file.is_empty() && !particles.exists() {
        let set = (bench.generate)();
        let result = if bench.particle_file.ends_with(".ply") {
            write_ply_binary(&particles, &set)
        } else {
            write_csv(&particles, &set)
        };
        result.map_err(|e| format!("cannot write {}: {}", particles.display(), e.detail()))?;
        eprintln!(
            "benchmark: generated {} ({} particles)",
            particles.display(),
            set.len()
        );
    }
    Scene::load(&dir.join(format!("{}.ron", bench.name))).map_err(|e| e.to_string())
}

// ---------------------------------------------------------------------------------------------
// References
// ---------------------------------------------------------------------------------------------

/// A path-traced ground truth: the mean of two independent renders.
struct Reference {
    image: Vec<[f32; 4]>,
    width: u32,
    height: u32,
    /// Samples per pixel of `image` (both renders together).
    spp: u32,
    /// Noise level of `image`: PHYSICS.md's noise level of one render (relative RMSE of the two
    /// renders / √2) divided by √2, since `image` averages both.
    noise: f64,
    /// The same after a 4×4 box filter of both renders.
    noise_box4: f64,
}

/// FNV-1a, 64 bits: a hash that is the same on every machine and Rust version.
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// The scene as the path tracer sees it (camera, background, lights, clouds, objects), hashed.
fn reference_hash(scene: &Scene, spp: u32) -> u64 {
    let text = format!(
        "{:?}|{:?}|{:?}|{:?}|{:?}|spp {spp}",
        scene.camera, scene.background, scene.lights, scene.clouds, scene.objects
    );
    fnv1a(text.as_bytes())
}

fn reference(scene: &Scene, bench: &BenchScene, spp: u32, out: &Path) -> Result<Reference, String> {
    let mut small = scene.clone();
    small.camera.width = scene.camera.width / bench.error_downsample;
    small.camera.height = scene.camera.height / bench.error_downsample;
    let hash = reference_hash(&small, spp);
    let mut images = Vec::new();
    for seed in [1u64, 2] {
        let path = out.join(format!("reference-{hash:016x}-s{seed}.exr"));
        let image = match read_exr(&path) {
            Ok(image)
                if image.width == small.camera.width && image.height == small.camera.height =>
            {
                eprintln!(
                    "benchmark: {}: cached reference {}",
                    bench.name,
                    path.display()
                );
                image
            }
            _ => {
                let start = Instant::now();
                eprintln!(
                    "benchmark: {}: path tracing the reference, {}x{} at {} spp, seed {seed} ({} threads)",
                    bench.name,
                    small.camera.width,
                    small.camera.height,
                    spp,
                    rayon::current_num_threads()
                );
                let pixels = path_tracer::render(
                    &small,
                    &PathTracerSettings {
                        samples_per_pixel: spp,
                        seed,
                        progress: true,
                    },
                );
                let image = LinearImage {
                    width: small.camera.width,
                    height: small.camera.height,
                    pixels,
                };
                write_exr(&image, &path).map_err(|e| e.to_string())?;
                eprintln!(
                    "benchmark: {}: traced in {:.1} s",
                    bench.name,
                    start.elapsed().as_secs_f64()
                );
                image
            }
        };
        images.push(image);
    }
    let noise = noise_level(&images[0].pixels, &images[1].pixels) / std::f64::consts::SQRT_2;
    let noise_box4 = noise_level(
        &downsample(&images[0], 4).pixels,
        &downsample(&images[1], 4).pixels,
    ) / std::f64::consts::SQRT_2;
    let image = images[0]
        .pixels
        .iter()
        .zip(&images[1].pixels)
        .map(|(a, b)| std::array::from_fn(|c| 0.5 * (a[c] + b[c])))
        .collect();
    let _ = write_png(
        &LinearImage {
            width: small.camera.width,
            height: small.camera.height,
            pixels: image_clone(&images),
        },
        &out.join(format!("{}-reference.png", bench.name)),
    );
    Ok(Reference {
        image,
        width: small.camera.width,
        height: small.camera.height,
        spp: 2 * spp,
        noise,
        noise_box4,
    })
}

fn image_clone(images: &[LinearImage]) -> Vec<[f32; 4]> {
    images[0]
        .pixels
        .iter()
        .zip(&images[1].pixels)
        .map(|(a, b)| std::array::from_fn(|c| if c == 3 { 1.0 } else { 0.5 * (a[c] + b[c]) }))
        .collect()
}

/// Real-time | path tracer | difference, side by side. The difference is `4 (real-time -
/// reference)`: red where the real-time image is brighter, blue where it is darker.
fn side_by_side(real_time: &LinearImage, reference: &LinearImage) -> LinearImage {
    let (w, h) = (reference.width, reference.height);
    let mut out = LinearImage::new(3 * w, h);
    for y in 0..h {
        for x in 0..w {
            let (a, b) = (real_time.pixel(x, y), reference.pixel(x, y));
            let d = (0..3).map(|c| a[c] - b[c]).sum::<f32>() / 3.0 * 4.0;
            *out.pixel_mut(x, y) = [a[0], a[1], a[2], 1.0];
            *out.pixel_mut(w + x, y) = [b[0], b[1], b[2], 1.0];
            *out.pixel_mut(2 * w + x, y) = [d.max(0.0), 0.0, (-d).max(0.0), 1.0];
        }
    }
    out
}

/// Box-filters an image by an integer factor.
fn downsample(image: &LinearImage, factor: u32) -> LinearImage {
    if factor == 1 {
        return image.clone();
    }
    let (w, h) = (image.width / factor, image.height / factor);
    let mut out = LinearImage::new(w, h);
    let weight = 1.0 / (factor * factor) as f32;
    for y in 0..h {
        for x in 0..w {
            let mut sum = [0.0f32; 4];
            for dy in 0..factor {
                for dx in 0..factor {
                    let p = image.pixel(x * factor + dx, y * factor + dy);
                    (0..4).for_each(|c| sum[c] += p[c] * weight);
                }
            }
            *out.pixel_mut(x, y) = sum;
        }
    }
    out
}

// ---------------------------------------------------------------------------------------------
// Real-time measurements
// ---------------------------------------------------------------------------------------------

/// The default settings before the view transmittance became the default: sorted compositing,
/// 16 iterations, light supersampling 2, 4 chord segments.
const PREVIOUS_DEFAULT: CloudQualitySettings = CloudQualitySettings {
    volume_resolution: 48,
    scatter_iterations: 16,
    forward_scattering: 0.0,
    scatter_stencil: ScatterStencil::DiscreteOrdinates,
    light_supersampling: 2,
    chord_segments: 4,
    compositing: Compositing::Sorted,
};

/// The quality settings of a sweep: the defaults, then each knob varied on its own around them
/// (so every knob's cost and error are measured), plus the paper's stencil.
fn sweep(quick: bool) -> Vec<CloudQualitySettings> {
    let base = CloudQualitySettings::default();
    let (resolutions, iterations, segments, supersampling): (&[u32], &[u32], &[u32], &[u32]) =
        if quick {
            (&[32, 48, 64], &[0, 16], &[1, 4], &[1, 2])
        } else {
            (
                &[16, 24, 32, 48, 64, 96, 128],
                &[0, 1, 2, 4, 8, 16, 32, 64],
                &[1, 2, 4, 8],
                &[1, 2, 3],
            )
        };
    let mut settings = vec![base];
    let mut add = |s: CloudQualitySettings| {
        if !settings.contains(&s) {
            settings.push(s);
        }
    };
    for &volume_resolution in resolutions {
        add(CloudQualitySettings {
            volume_resolution,
            ..base
        });
    }
    for &scatter_iterations in iterations {
        add(CloudQualitySettings {
            scatter_iterations,
            ..base
        });
    }
    for &chord_segments in segments {
        add(CloudQualitySettings {
            chord_segments,
            ..base
        });
    }
    for &light_supersampling in supersampling {
        add(CloudQualitySettings {
            light_supersampling,
            ..base
        });
    }
    // Resolution and iterations together, where the front is expected.
    if !quick {
        for volume_resolution in [32, 48, 64] {
            for scatter_iterations in [4, 8, 16, 32] {
                add(CloudQualitySettings {
                    volume_resolution,
                    scatter_iterations,
                    ..base
                });
            }
        }
    }
    // The paper's compositing, sorted particles, at the default and the finest grid, and the
    // defaults of 0.1 (sorted, 16 iterations, supersampling 2, 4 chord segments).
    let sorted: &[u32] = if quick { &[48] } else { &[48, 128] };
    for &volume_resolution in sorted {
        add(CloudQualitySettings {
            volume_resolution,
            compositing: Compositing::Sorted,
            ..base
        });
    }
    add(PREVIOUS_DEFAULT);
    let paper: &[u32] = if quick { &[48] } else { &[32, 48, 128] };
    for &volume_resolution in paper {
        add(CloudQualitySettings {
            volume_resolution,
            scatter_stencil: ScatterStencil::Paper,
            ..base
        });
    }
    settings
}

fn median(mut values: Vec<f64>) -> f64 {
    values.retain(|v| v.is_finite());
    if values.is_empty() {
        return f64::NAN;
    }
    values.sort_by(f64::total_cmp);
    let n = values.len();
    if n % 2 == 1 {
        values[n / 2]
    } else {
        0.5 * (values[n / 2 - 1] + values[n / 2])
    }
}

/// Median timings of a setting.
#[derive(Clone, Debug, Default)]
struct Timing {
    /// Per pass (CloudPass::ALL order, draw from the transparent pass), frames where all rerun.
    pass_ms: [f64; PASSES],
    /// GPU time of a frame where every pass runs: median of the per-frame sums.
    gpu_ms_total: f64,
    /// GPU time of a static frame (the draw only).
    gpu_ms_static: f64,
    wall_ms: f64,
    wall_ms_static: f64,
}

/// A running app with one scene, for measuring many settings.
struct Bench {
    app: App,
    target: headless::SceneTarget,
    recorder: FrameRecorder,
    clouds: Vec<(Entity, Handle<Particles>)>,
    draw_seen: Option<bevy::platform::time::Instant>,
    adapter: String,
}

impl Bench {
    fn new(scene: &Scene) -> Bench {
        let mut app = headless::headless_app();
        let adapter = headless::adapter_name(&mut app);
        let target = headless::spawn_scene(&mut app, scene);
        let clouds = app
            .world_mut()
            .query::<(Entity, &ParticleCloud)>()
            .iter(app.world())
            .map(|(e, c)| (e, c.particles.clone()))
            .collect();
        Bench {
            app,
            target,
            recorder: FrameRecorder::default(),
            clouds,
            draw_seen: None,
            adapter,
        }
    }

    fn set_quality(&mut self, settings: CloudQualitySettings) {
        for &(entity, _) in &self.clouds {
            self.app.world_mut().entity_mut(entity).insert(settings);
        }
    }

    /// Marks every cloud's particles changed: the next frame reruns every pass.
    fn touch_particles(&mut self) {
        for (_, handle) in &self.clouds {
            let mut assets = self.app.world_mut().resource_mut::<Assets<Particles>>();
            assets.get_mut(handle).expect("particles").into_inner();
        }
    }

    /// The transparent pass's GPU time measured since the last call, if a new one arrived.
    fn new_draw_time(&mut self) -> Option<f64> {
        let store = self.app.world().get_resource::<DiagnosticsStore>()?;
        let m = store
            .get(&bevy::diagnostic::DiagnosticPath::const_new(
                DRAW_DIAGNOSTIC,
            ))?
            .measurement()?;
        if self.draw_seen == Some(m.time) {
            return None;
        }
        self.draw_seen = Some(m.time);
        Some(m.value)
    }

    fn frame(&mut self) -> usize {
        self.recorder.frame(&mut self.app);
        self.recorder.frames.len() - 1
    }

    /// Renders the finished image of the current settings and measures it.
    fn measure(&mut self, frames: usize) -> (LinearImage, Timing) {
        headless::render_until_steady(&mut self.app, &mut self.recorder, &self.target, 200);
        let image = headless::capture(&mut self.app, &mut self.recorder, &self.target);
        // Static frames: nothing changed, only the draw runs.
        for _ in 0..2 {
            self.frame();
            self.new_draw_time();
        }
        let mut draw = Vec::new();
        let mut static_frames = Vec::new();
        for _ in 0..frames {
            static_frames.push(self.frame());
            draw.extend(self.new_draw_time());
        }
        // Frames where everything reruns.
        let mut dynamic = Vec::new();
        for _ in 0..frames {
            self.touch_particles();
            dynamic.push(self.frame());
        }
        for _ in 0..4 {
            self.recorder.drain(&mut self.app); // late GPU timestamps
        }
        let frames_of = |ids: &[usize]| -> Vec<FrameStats> {
            ids.iter()
                .map(|&i| self.recorder.frames[i].clone())
                .collect()
        };
        let statics = frames_of(&static_frames);
        // Every illumination pass and the view pass (the sort or the view volume).
        let reran = |f: &FrameStats| {
            [CloudPass::Voxelize, CloudPass::Shade, CloudPass::Gather]
                .iter()
                .all(|&p| f.runs(p) > 0)
                && f.runs(CloudPass::Sort) + f.runs(CloudPass::ViewVolume) > 0
        };
        let dynamics: Vec<FrameStats> = frames_of(&dynamic).into_iter().filter(reran).collect();
        if std::env::var_os("BENCHMARK_DEBUG").is_some() {
            for f in frames_of(&dynamic) {
                eprintln!(
                    "  frame: wall {:.1} ms, runs {:?}, gpu {:?}",
                    f.wall_ms, f.passes, f.gpu_ms
                );
            }
        }
        assert!(
            !dynamics.is_empty(),
            "none of the {frames} measured frames reran every pass"
        );
        let draw_ms = median(draw);
        let mut pass_ms = [0.0; PASSES];
        for (i, pass) in CloudPass::ALL.iter().enumerate() {
            pass_ms[i] = if *pass == CloudPass::Draw {
                draw_ms
            } else {
                median(
                    dynamics
                        .iter()
                        .map(|f| {
                            f.gpu_ms
                                .get(pass)
                                .copied()
                                .unwrap_or(if f.runs(*pass) == 0 { 0.0 } else { f64::NAN })
                        })
                        .collect(),
                )
            };
        }
        let gpu_ms_total = median(
            dynamics
                .iter()
                .map(|f| {
                    CloudPass::ALL
                        .iter()
                        .filter(|&&p| p != CloudPass::Draw)
                        .map(|p| {
                            f.gpu_ms.get(p).copied().unwrap_or(if f.runs(*p) == 0 {
                                0.0
                            } else {
                                f64::NAN
                            })
                        })
                        .sum::<f64>()
                        + draw_ms
                })
                .collect(),
        );
        let timing = Timing {
            pass_ms,
            gpu_ms_total,
            gpu_ms_static: draw_ms,
            wall_ms: median(dynamics.iter().map(|f| f.wall_ms).collect()),
            wall_ms_static: median(statics.iter().map(|f| f.wall_ms).collect()),
        };
        (image, timing)
    }
}

// ---------------------------------------------------------------------------------------------
// Results
// ---------------------------------------------------------------------------------------------

#[derive(Clone)]
struct Row {
    scene: &'static str,
    particles: usize,
    lights: usize,
    size: (u32, u32),
    error_size: (u32, u32),
    settings: CloudQualitySettings,
    timing: Timing,
    /// The time axis of the Pareto front: `gpu_ms_total`, or `wall_ms` on llvmpipe (see [`wall_axis`]).
    cost_ms: f64,
    rel_rmse: f64,
    /// The relative RMSE after a 4×4 box filter of both images (noise averages out, bias does not).
    rel_rmse_box4: f64,
    rel_mse: f64,
    mae: f64,
    reference_spp: u32,
    reference_noise: f64,
    /// The reference's noise after the same 4×4 box filter.
    reference_noise_box4: f64,
    pareto: bool,
}

/// An error with the reference's own noise removed in quadrature (0 when the noise explains it all).
fn denoised(error: f64, noise: f64) -> f64 {
    (error * error - noise * noise).max(0.0).sqrt()
}

fn stencil_name(s: ScatterStencil) -> &'static str {
    match s {
        ScatterStencil::DiscreteOrdinates => "DiscreteOrdinates",
        ScatterStencil::Paper => "Paper",
    }
}

fn setting_label(s: &CloudQualitySettings) -> String {
    let stencil = match s.scatter_stencil {
        ScatterStencil::DiscreteOrdinates => "D",
        ScatterStencil::Paper => "P",
    };
    let compositing = match s.compositing {
        Compositing::ViewTransmittance => "",
        Compositing::Sorted => " sorted",
    };
    format!(
        "{}³ ×{} {stencil} K{} L{}{compositing}",
        s.volume_resolution, s.scatter_iterations, s.chord_segments, s.light_supersampling
    )
}

static WALL_AXIS: std::sync::OnceLock<bool> = std::sync::OnceLock::new();

/// Whether the Pareto front uses wall time instead of GPU time: on llvmpipe (lavapipe), where a
/// timestamp is only taken when the driver flushes, so a pass of one dispatch reads ~0 ms and the
/// first dispatch of every pass is missed; the GPU is the CPU there, and the wall time of a frame
/// is its cost (plus a constant per-frame overhead, which does not change which settings dominate).
fn wall_axis() -> bool {
    *WALL_AXIS.get().unwrap_or(&false)
}

fn cost_name() -> &'static str {
    if wall_axis() {
        "wall ms per frame"
    } else {
        "GPU ms per frame"
    }
}

/// Marks the rows of one scene on the Pareto front of (GPU time, relative RMSE): no other row is
/// at least as fast and at least as accurate, and strictly better in one.
fn mark_pareto(rows: &mut [Row]) {
    let points: Vec<(f64, f64)> = rows.iter().map(|r| (r.cost_ms, r.rel_rmse)).collect();
    for (i, row) in rows.iter_mut().enumerate() {
        let (t, e) = points[i];
        row.pareto = t.is_finite()
            && !points
                .iter()
                .any(|&(t2, e2)| t2 <= t && e2 <= e && (t2 < t || e2 < e));
    }
}

/// The rows that dominate the default settings of a scene.
fn dominating<'a>(rows: &'a [Row]) -> Vec<&'a Row> {
    let Some(d) = rows
        .iter()
        .find(|r| r.settings == CloudQualitySettings::default())
    else {
        return vec![];
    };
    let (t, e) = (d.cost_ms, d.rel_rmse);
    rows.iter()
        .filter(|r| {
            let (t2, e2) = (r.cost_ms, r.rel_rmse);
            t2 <= t && e2 <= e && (t2 < t || e2 < e)
        })
        .collect()
}

fn write_csv_results(path: &Path, adapter: &str, rows: &[Row]) -> std::io::Result<()> {
    let mut s = String::from(
        "adapter,scene,particles,lights,width,height,error_width,error_height,volume_resolution,scatter_iterations,\
         stencil,forward_scattering,chord_segments,light_supersampling,compositing,is_default,gpu_ms_total,gpu_ms_voxelize,gpu_ms_shade,gpu_ms_gather,gpu_ms_scatter,\
         gpu_ms_view,gpu_ms_draw,gpu_ms_static,wall_ms,wall_ms_static,rel_rmse,rel_mse,mae,reference_spp,reference_noise,pareto,pareto_time_axis,\
         rel_rmse_denoised,rel_rmse_box4,reference_noise_box4,rel_rmse_box4_denoised\n",
    );
    for r in rows {
        let t = &r.timing;
        let _ = writeln!(
            s,
            "\"{adapter}\",{},{},{},{},{},{},{},{},{},{},{},{},{},{:?},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.3},{:.3},{:.6},{:.6},{:.6},{},{:.6},{},{},{:.6},{:.6},{:.6},{:.6}",
            r.scene,
            r.particles,
            r.lights,
            r.size.0,
            r.size.1,
            r.error_size.0,
            r.error_size.1,
            r.settings.volume_resolution,
            r.settings.scatter_iterations,
            stencil_name(r.settings.scatter_stencil),
            r.settings.forward_scattering,
            r.settings.chord_segments,
            r.settings.light_supersampling,
            r.settings.compositing,
            r.settings == CloudQualitySettings::default(),
            t.gpu_ms_total,
            t.pass_ms[0],
            t.pass_ms[1],
            t.pass_ms[2],
            t.pass_ms[3],
            t.pass_ms[4] + t.pass_ms[5],
            t.pass_ms[6],
            t.gpu_ms_static,
            t.wall_ms,
            t.wall_ms_static,
            r.rel_rmse,
            r.rel_mse,
            r.mae,
            r.reference_spp,
            r.reference_noise,
            r.pareto,
            if wall_axis() {
                "wall_ms"
            } else {
                "gpu_ms_total"
            },
            denoised(r.rel_rmse, r.reference_noise),
            r.rel_rmse_box4,
            r.reference_noise_box4,
            denoised(r.rel_rmse_box4, r.reference_noise_box4),
        );
    }
    std::fs::write(path, s)
}

fn markdown(adapter: &str, rows: &[Row], scene_order: &[&'static str]) -> String {
    let mut s = format!(
        "Adapter: `{adapter}`. GPU ms: sum of the per-pass GPU times of a frame in which every pass reruns \
         (voxelize + shade + gather + scatter + sort + draw), median; static: a frame with nothing changed (draw only). \
         Wall ms: the frame's wall time (update + GPU wait). Errors against the path-traced reference \
         (relative RMSE, relMSE, mean absolute error); ★ = on the Pareto front of ({}, relative RMSE), \
         **bold** = the default settings (`CloudQualitySettings::default()`). Settings: `N³ ×M stencil Kk Lf` = volume_resolution, \
         scatter_iterations, stencil (D = DiscreteOrdinates, P = Paper), chord_segments, light_supersampling; \
         forward_scattering 0.\n",
        if wall_axis() {
            "wall ms: on llvmpipe the timestamps miss single-dispatch passes"
        } else {
            "GPU ms"
        }
    );
    for &name in scene_order {
        let scene_rows: Vec<&Row> = rows.iter().filter(|r| r.scene == name).collect();
        let Some(first) = scene_rows.first() else {
            continue;
        };
        let _ = write!(
            s,
            "\n### {name}\n\n{} particles, {} light(s), rendered at {}×{}, errors at {}×{}; reference: {} spp, noise {:.4} (relative RMSE; {:.4} after a 4×4 box filter)\n\n",
            first.particles,
            first.lights,
            first.size.0,
            first.size.1,
            first.error_size.0,
            first.error_size.1,
            first.reference_spp,
            first.reference_noise,
            first.reference_noise_box4
        );
        s.push_str("| setting | GPU ms | voxelize | shade | gather | scatter | sort | draw | static GPU ms | wall ms | static wall ms | rel. RMSE | denoised | 4×4 box, denoised | relMSE | MAE | front |\n");
        s.push_str(
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|:---:|\n",
        );
        let mut sorted = scene_rows.clone();
        sorted.sort_by(|a, b| a.cost_ms.total_cmp(&b.cost_ms));
        for r in sorted {
            let t = &r.timing;
            let label = setting_label(&r.settings);
            let label = if r.settings == CloudQualitySettings::default() {
                format!("**{label}**")
            } else {
                label
            };
            let _ = writeln!(
                s,
                "| {label} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.0} | {:.0} | {:.4} | {:.4} | {:.4} | {:.5} | {:.5} | {} |",
                t.gpu_ms_total,
                t.pass_ms[0],
                t.pass_ms[1],
                t.pass_ms[2],
                t.pass_ms[3],
                t.pass_ms[4] + t.pass_ms[5],
                t.pass_ms[6],
                t.gpu_ms_static,
                t.wall_ms,
                t.wall_ms_static,
                r.rel_rmse,
                denoised(r.rel_rmse, r.reference_noise),
                denoised(r.rel_rmse_box4, r.reference_noise_box4),
                r.rel_mse,
                r.mae,
                if r.pareto { "★" } else { "" }
            );
        }
        let dom = dominating(
            &rows
                .iter()
                .filter(|r| r.scene == name)
                .cloned()
                .collect::<Vec<_>>(),
        )
        .iter()
        .map(|r| setting_label(&r.settings))
        .collect::<Vec<_>>();
        if dom.is_empty() {
            s.push_str("\nThe default settings are on the Pareto front.\n");
        } else {
            let _ = writeln!(
                s,
                "\nThe default settings are dominated by: {}.",
                dom.join(", ")
            );
        }
    }
    s
}

// ---------------------------------------------------------------------------------------------
// The Pareto plot
// ---------------------------------------------------------------------------------------------

fn plot(
    path: &Path,
    font: &Path,
    adapter: &str,
    rows: &[Row],
    scene_order: &[&'static str],
) -> Result<(), String> {
    use plotters::prelude::*;
    let bytes = std::fs::read(font).map_err(|e| {
        format!(
            "cannot read the plot's font {}: {e}; install it with `apt-get install fonts-dejavu-core` or pass --font FILE.ttf",
            font.display()
        )
    })?;
    let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
    plotters::style::register_font("sans-serif", FontStyle::Normal, bytes)
        .map_err(|_| format!("{} is not a TrueType/OpenType font", font.display()))?;

    let scenes: Vec<&str> = scene_order
        .iter()
        .copied()
        .filter(|n| rows.iter().any(|r| r.scene == *n))
        .collect();
    let cols = scenes.len().min(3).max(1) as u32;
    let rows_n = (scenes.len() as u32).div_ceil(cols).max(1);
    let (w, h) = (420 * cols, 330 * rows_n + 64);
    let mut buffer = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let (title, body) = root.split_vertically(64);
        title
            .draw_text(
                &format!(
                    "{} (every pass reruns) vs. relative RMSE, {adapter}",
                    cost_name()
                ),
                &("sans-serif", 18).into_font().color(&BLACK),
                (10, 12),
            )
            .map_err(|e| e.to_string())?;
        let panels = body.split_evenly((rows_n as usize, cols as usize));
        for (panel, name) in panels.iter().zip(&scenes) {
            let pts: Vec<&Row> = rows
                .iter()
                .filter(|r| r.scene == *name && r.cost_ms.is_finite())
                .collect();
            let (t_lo, t_hi) = pts.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
                (lo.min(r.cost_ms), hi.max(r.cost_ms))
            });
            let (e_lo, e_hi) = pts.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
                (lo.min(r.rel_rmse), hi.max(r.rel_rmse))
            });
            let noise = pts.first().map_or(0.0, |r| r.reference_noise);
            let mut chart = ChartBuilder::on(panel)
                .caption(
                    format!("{name} (ref. noise {noise:.3})"),
                    ("sans-serif", 15),
                )
                .margin(8)
                .x_label_area_size(32)
                .y_label_area_size(52)
                .build_cartesian_2d(
                    ((t_lo * 0.8).max(1e-3)..t_hi * 1.25).log_scale(),
                    (e_lo * 0.9).max(1e-4)..e_hi * 1.08,
                )
                .map_err(|e| e.to_string())?;
            chart
                .configure_mesh()
                .x_desc(cost_name())
                .y_desc("relative RMSE")
                .label_style(("sans-serif", 11))
                .axis_desc_style(("sans-serif", 12))
                .x_labels(8)
                .y_labels(6)
                .x_label_formatter(&|v| {
                    if *v >= 10.0 {
                        format!("{v:.0}")
                    } else {
                        format!("{v:.1}")
                    }
                })
                .y_label_formatter(&|v| format!("{v:.2}"))
                .light_line_style(WHITE)
                .draw()
                .map_err(|e| e.to_string())?;
            if noise > e_lo * 0.9 {
                chart
                    .draw_series(LineSeries::new(
                        [(t_lo * 0.8, noise), (t_hi * 1.25, noise)],
                        ShapeStyle::from(&RGBColor(160, 160, 160)).stroke_width(1),
                    ))
                    .map_err(|e| e.to_string())?;
            }
            let mut front: Vec<(f64, f64)> = pts
                .iter()
                .filter(|r| r.pareto)
                .map(|r| (r.cost_ms, r.rel_rmse))
                .collect();
            front.sort_by(|a, b| a.0.total_cmp(&b.0));
            chart
                .draw_series(LineSeries::new(
                    front.clone(),
                    ShapeStyle::from(&BLACK).stroke_width(2),
                ))
                .map_err(|e| e.to_string())?
                .label("Pareto front")
                .legend(|(x, y)| {
                    PathElement::new(vec![(x, y), (x + 14, y)], BLACK.stroke_width(2))
                });
            let res_colour = |n: u32| match n {
                ..=24 => RGBColor(120, 120, 120),
                32 => RGBColor(230, 159, 0),
                48 => RGBColor(86, 180, 233),
                64 => RGBColor(0, 158, 115),
                96 => RGBColor(0, 114, 178),
                _ => RGBColor(213, 94, 0),
            };
            for stencil in [ScatterStencil::DiscreteOrdinates, ScatterStencil::Paper] {
                let series: Vec<&&Row> = pts
                    .iter()
                    .filter(|r| r.settings.scatter_stencil == stencil)
                    .collect();
                if series.is_empty() {
                    continue;
                }
                let drawn = chart
                    .draw_series(series.iter().map(|r| {
                        let c = res_colour(r.settings.volume_resolution);
                        let p = (r.cost_ms, r.rel_rmse);
                        match stencil {
                            ScatterStencil::DiscreteOrdinates => {
                                Circle::new(p, 3, c.filled()).into_dyn()
                            }
                            ScatterStencil::Paper => {
                                TriangleMarker::new(p, 4, c.stroke_width(1)).into_dyn()
                            }
                        }
                    }))
                    .map_err(|e| e.to_string())?;
                match stencil {
                    ScatterStencil::DiscreteOrdinates => drawn
                        .label("DiscreteOrdinates stencil")
                        .legend(|(x, y)| Circle::new((x + 7, y), 3, BLACK.filled())),
                    ScatterStencil::Paper => drawn
                        .label("Paper stencil")
                        .legend(|(x, y)| TriangleMarker::new((x + 7, y), 4, BLACK.stroke_width(1))),
                };
            }
            if let Some(d) = pts
                .iter()
                .find(|r| r.settings == CloudQualitySettings::default())
            {
                chart
                    .draw_series([Cross::new(
                        (d.cost_ms, d.rel_rmse),
                        7,
                        ShapeStyle::from(&RED).stroke_width(2),
                    )])
                    .map_err(|e| e.to_string())?
                    .label("default settings")
                    .legend(|(x, y)| Cross::new((x + 7, y), 5, RED.stroke_width(2)));
            }
        }
        // Markers, once: stencil shapes, the default, the front.
        let text = ("sans-serif", 14).into_font().color(&BLACK);
        let y = 46;
        let t = |e: DrawingAreaErrorKind<_>| e.to_string();
        title
            .draw(&Circle::new((16, y), 4, BLACK.filled()))
            .map_err(t)?;
        title
            .draw_text("DiscreteOrdinates stencil", &text, (26, y - 7))
            .map_err(t)?;
        title
            .draw(&TriangleMarker::new((200, y), 5, BLACK.stroke_width(1)))
            .map_err(t)?;
        title
            .draw_text("Paper stencil", &text, (210, y - 7))
            .map_err(t)?;
        title
            .draw(&Cross::new((480, y), 6, RED.stroke_width(2)))
            .map_err(t)?;
        title
            .draw_text("default settings", &text, (492, y - 7))
            .map_err(t)?;
        title
            .draw(&PathElement::new(
                vec![(630, y), (654, y)],
                BLACK.stroke_width(2),
            ))
            .map_err(t)?;
        title
            .draw_text(
                "Pareto front; grey line: reference noise",
                &text,
                (660, y - 7),
            )
            .map_err(t)?;
        // Resolution colours, once.
        let legend = ["32³", "48³", "64³", "96³", "128³"];
        let colours = [
            (230, 159, 0),
            (86, 180, 233),
            (0, 158, 115),
            (0, 114, 178),
            (213, 94, 0),
        ];
        for (i, (l, c)) in legend.iter().zip(colours).enumerate() {
            let x = w as i32 - 330 + 64 * i as i32;
            title
                .draw(&Circle::new((x, 20), 5, RGBColor(c.0, c.1, c.2).filled()))
                .map_err(|e| e.to_string())?;
            title
                .draw_text(
                    l,
                    &("sans-serif", 14).into_font().color(&BLACK),
                    (x + 8, 13),
                )
                .map_err(|e| e.to_string())?;
        }
        root.present().map_err(|e| e.to_string())?;
    }
    let image = image::RgbImage::from_raw(w, h, buffer).expect("buffer size");
    image
        .save_with_format(path, image::ImageFormat::Png)
        .map_err(|e| format!("cannot write {}: {e}", path.display()))
}

// ---------------------------------------------------------------------------------------------
// Main
// ---------------------------------------------------------------------------------------------

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("error: {message}");
            ExitCode::from(2)
        }
    }
}

/// `--decompose`: every chosen scene's error at the default settings, part by part.
fn decomposition(args: &Args, chosen: &[&BenchScene]) -> Result<(), String> {
    let settings = args.settings.first().copied().unwrap_or_default();
    let mut md = String::from(
        "The default settings' error split by scattering order (`cargo run --example benchmark -- \
         --decompose`), computed with the f64 CPU references of the real-time passes (which the GPU \
         matches within 2e-4 of the maximum) against the path tracer split by order. Energies are \
         sums over the image; λ is an order's energy over the previous one's.\n",
    );
    for bench in chosen {
        let scene = load_scene(bench)?;
        let spp = args.spp.unwrap_or(bench.spp);
        eprintln!(
            "benchmark: {}: decomposing at {spp} spp per half",
            bench.name
        );
        let section =
            decompose::decompose(bench.name, &scene, &settings, bench.error_downsample, spp);
        eprintln!("{section}");
        md.push_str(&section);
    }
    let path = args.out.join("decomposition.md");
    std::fs::write(&path, &md).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    println!("{md}");
    Ok(())
}

fn run() -> Result<(), String> {
    let args = parse_args()?;
    std::fs::create_dir_all(&args.out)
        .map_err(|e| format!("cannot create {}: {e}", args.out.display()))?;
    if args.illumination {
        return illumination_benchmark(&args);
    }
    if args.replot {
        return replot(&args);
    }
    let start = Instant::now();
    let chosen: Vec<&BenchScene> = SCENES
        .iter()
        .filter(|s| match &args.scenes {
            Some(names) => names.iter().any(|n| n == s.name),
            None => (!args.quick && !args.decompose) || s.quick,
        })
        .collect();
    if chosen.is_empty() {
        let names: Vec<_> = SCENES.iter().map(|s| s.name).collect();
        return Err(format!(
            "no such scene; the scenes are {}",
            names.join(", ")
        ));
    }
    if args.decompose {
        return decomposition(&args, &chosen);
    }
    let settings = if args.settings.is_empty() {
        sweep(args.quick)
    } else {
        args.settings.clone()
    };
    let mut rows = Vec::new();
    let mut adapter = String::new();
    for bench in &chosen {
        let scene = load_scene(bench)?;
        let reference = reference(
            &scene,
            bench,
            args.spp
                .unwrap_or(if args.quick { bench.spp / 4 } else { bench.spp }),
            &args.out,
        )?;
        let mut b = Bench::new(&scene);
        adapter = b.adapter.clone();
        let _ = WALL_AXIS.set(adapter.contains("llvmpipe"));
        eprintln!(
            "benchmark: {}: adapter {adapter}; reference {} spp, noise {:.4}; {} settings",
            bench.name,
            reference.spp,
            reference.noise,
            settings.len()
        );
        let mut scene_rows = Vec::new();
        for s in &settings {
            let t0 = Instant::now();
            b.set_quality(*s);
            let (image, timing) = b.measure(args.frames);
            let image = downsample(&image, bench.error_downsample);
            assert_eq!(
                (image.width, image.height),
                (reference.width, reference.height)
            );
            let (rel_rmse, rel_mse_, mae) = (
                relative_rmse(&image.pixels, &reference.image),
                rel_mse(&image.pixels, &reference.image),
                mean_absolute_error(&image.pixels, &reference.image),
            );
            let reference_image = LinearImage {
                width: reference.width,
                height: reference.height,
                pixels: reference.image.clone(),
            };
            let rel_rmse_box4 = relative_rmse(
                &downsample(&image, 4).pixels,
                &downsample(&reference_image, 4).pixels,
            );
            if std::env::var_os("BENCHMARK_DEBUG").is_some() {
                let sum =
                    |p: &[[f32; 4]]| p.iter().map(|v| (v[0] + v[1] + v[2]) as f64).sum::<f64>();
                eprintln!(
                    "  mean ratio real-time / reference: {:.4}",
                    sum(&image.pixels) / sum(&reference.image)
                );
            }
            if *s == CloudQualitySettings::default() {
                let mut shown = image.clone();
                shown.pixels.iter_mut().for_each(|p| p[3] = 1.0);
                let _ = write_png(
                    &shown,
                    &args.out.join(format!("{}-default.png", bench.name)),
                );
                let _ = write_png(
                    &side_by_side(&shown, &reference_image),
                    &args.out.join(format!("{}-compare.png", bench.name)),
                );
            }
            eprintln!(
                "benchmark: {} {:<16} GPU {:8.2} ms (static {:6.2}), wall {:8.1} ms; rel. RMSE {:.4} (denoised {:.4}, 4x4 box {:.4}) relMSE {:.5} MAE {:.5} ({:.1} s)",
                bench.name,
                setting_label(s),
                timing.gpu_ms_total,
                timing.gpu_ms_static,
                timing.wall_ms,
                rel_rmse,
                denoised(rel_rmse, reference.noise),
                denoised(rel_rmse_box4, reference.noise_box4),
                rel_mse_,
                mae,
                t0.elapsed().as_secs_f64()
            );
            scene_rows.push(Row {
                scene: bench.name,
                particles: scene.clouds.iter().map(|c| c.particles.len()).sum(),
                lights: scene.lights.len(),
                size: (scene.camera.width, scene.camera.height),
                error_size: (reference.width, reference.height),
                settings: *s,
                cost_ms: if wall_axis() {
                    timing.wall_ms
                } else {
                    timing.gpu_ms_total
                },
                timing,
                rel_rmse,
                rel_rmse_box4,
                rel_mse: rel_mse_,
                mae,
                reference_spp: reference.spp,
                reference_noise: reference.noise,
                reference_noise_box4: reference.noise_box4,
                pareto: false,
            });
        }
        mark_pareto(&mut scene_rows);
        rows.extend(scene_rows);
        drop(b);
    }
    let order: Vec<&'static str> = chosen.iter().map(|s| s.name).collect();
    let csv = args.out.join("results.csv");
    write_csv_results(&csv, &adapter, &rows)
        .map_err(|e| format!("cannot write {}: {e}", csv.display()))?;
    let md = markdown(&adapter, &rows, &order);
    let md_path = args.out.join("results.md");
    std::fs::write(&md_path, &md)
        .map_err(|e| format!("cannot write {}: {e}", md_path.display()))?;
    println!("{md}");
    for name in &order {
        let scene_rows: Vec<Row> = rows.iter().filter(|r| r.scene == *name).cloned().collect();
        let dom = dominating(&scene_rows);
        if dom.is_empty() {
            eprintln!("benchmark: {name}: the default settings are on the Pareto front");
        } else {
            let names: Vec<_> = dom.iter().map(|r| setting_label(&r.settings)).collect();
            eprintln!(
                "benchmark: {name}: the default settings are dominated by {}",
                names.join(", ")
            );
        }
    }
    let png = args.out.join("pareto.png");
    plot(&png, &args.font, &adapter, &rows, &order)?;
    eprintln!(
        "benchmark: wrote {}, {} and {} in {:.0} s",
        csv.display(),
        md_path.display(),
        png.display(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Redraws `DIR/pareto.png` from `DIR/results.csv` (e.g. after changing the plot).
fn replot(args: &Args) -> Result<(), String> {
    let path = args.out.join("results.csv");
    let text = std::fs::read_to_string(&path)
        .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or_default().split(',').collect();
    let column = |name: &str| {
        header
            .iter()
            .position(|h| *h == name)
            .ok_or(format!("{}: no column {name}", path.display()))
    };
    let [
        adapter,
        scene,
        res,
        iters,
        stencil,
        fwd,
        segments,
        supersampling,
        compositing,
        gpu,
        wall,
        rmse,
        noise,
        spp,
        pareto,
        axis,
    ] = [
        "adapter",
        "scene",
        "volume_resolution",
        "scatter_iterations",
        "stencil",
        "forward_scattering",
        "chord_segments",
        "light_supersampling",
        "compositing",
        "gpu_ms_total",
        "wall_ms",
        "rel_rmse",
        "reference_noise",
        "reference_spp",
        "pareto",
        "pareto_time_axis",
    ]
    .map(column);
    let (adapter, scene, res, iters, stencil, fwd, segments, supersampling) = (
        adapter?,
        scene?,
        res?,
        iters?,
        stencil?,
        fwd?,
        segments?,
        supersampling?,
    );
    // Results written before the compositing knob existed were all sorted.
    let compositing = compositing.ok();
    let (gpu, wall, rmse, noise, spp, pareto, axis) =
        (gpu?, wall?, rmse?, noise?, spp?, pareto?, axis?);
    let mut rows = Vec::new();
    let mut order: Vec<&'static str> = Vec::new();
    let mut adapter_name = String::new();
    for line in lines.filter(|l| !l.is_empty()) {
        // The adapter is the only quoted field (it has no commas inside in practice, but may).
        let (quoted, rest) = line
            .strip_prefix('"')
            .and_then(|l| l.split_once("\","))
            .ok_or(format!("bad line {line}"))?;
        let fields: Vec<&str> = std::iter::once(quoted).chain(rest.split(',')).collect();
        let f = |i: usize| fields.get(i).copied().unwrap_or_default();
        let num = |i: usize| f(i).parse::<f64>().unwrap_or(f64::NAN);
        adapter_name = f(adapter).to_string();
        let _ = WALL_AXIS.set(f(axis) == "wall_ms");
        let name: &'static str = match order.iter().find(|n| **n == f(scene)) {
            Some(n) => n,
            None => {
                let n: &'static str = Box::leak(f(scene).to_string().into_boxed_str());
                order.push(n);
                n
            }
        };
        let settings = CloudQualitySettings {
            volume_resolution: num(res) as u32,
            scatter_iterations: num(iters) as u32,
            forward_scattering: num(fwd) as f32,
            scatter_stencil: match f(stencil) {
                "Paper" => ScatterStencil::Paper,
                _ => ScatterStencil::DiscreteOrdinates,
            },
            chord_segments: num(segments) as u32,
            light_supersampling: num(supersampling) as u32,
            compositing: match compositing.map(f) {
                Some("ViewTransmittance") => Compositing::ViewTransmittance,
                _ => Compositing::Sorted,
            },
        };
        let timing = Timing {
            gpu_ms_total: num(gpu),
            wall_ms: num(wall),
            ..default()
        };
        rows.push(Row {
            scene: name,
            particles: 0,
            lights: 0,
            size: (0, 0),
            error_size: (0, 0),
            settings,
            cost_ms: if wall_axis() {
                timing.wall_ms
            } else {
                timing.gpu_ms_total
            },
            timing,
            rel_rmse: num(rmse),
            rel_rmse_box4: f64::NAN,
            rel_mse: f64::NAN,
            mae: f64::NAN,
            reference_spp: num(spp) as u32,
            reference_noise: num(noise),
            reference_noise_box4: f64::NAN,
            pareto: f(pareto) == "true",
        });
    }
    let png = args.out.join("pareto.png");
    plot(&png, &args.font, &adapter_name, &rows, &order)?;
    eprintln!("benchmark: wrote {}", png.display());
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Issue #3: the illumination passes, incremental against brute-force shading
// ---------------------------------------------------------------------------------------------

/// What a measured frame changes, and so which passes rerun.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Change {
    /// Nothing: the draw only.
    Nothing,
    /// The cloud's albedo (by one part in 10⁶): scatter and the particle colours.
    Albedo,
    /// The first light's illuminance (by one part in 10⁶): gather, scatter, colours.
    Irradiance,
    /// Every light's direction (by ~10⁻⁴ rad): shade (every light), gather, scatter, colours.
    Direction,
    /// The camera (by 10⁻⁴ m): the sort.
    Camera,
    /// The particles (touched): everything (upload, voxelize, shade, gather, scatter, sort).
    Particles,
}

impl Bench {
    /// Applies `change` for frame number `i` (alternating up and down, so nothing drifts).
    fn change(&mut self, change: Change, i: usize) {
        let sign = if i % 2 == 0 { 1.0 } else { -1.0 };
        let world = self.app.world_mut();
        match change {
            Change::Nothing => {}
            Change::Albedo => {
                for mut cloud in world.query::<&mut ParticleCloud>().iter_mut(world) {
                    cloud.albedo *= 1.0 - sign * 1e-6;
                }
            }
            Change::Irradiance => {
                if let Some(mut light) = world
                    .query::<&mut DirectionalLight>()
                    .iter_mut(world)
                    .next()
                {
                    light.illuminance *= 1.0 + sign * 1e-6;
                }
            }
            Change::Direction => {
                for mut t in world
                    .query_filtered::<&mut Transform, With<DirectionalLight>>()
                    .iter_mut(world)
                {
                    t.rotate_y(sign * 1e-4);
                }
            }
            Change::Camera => {
                for mut t in world
                    .query_filtered::<&mut Transform, With<Camera3d>>()
                    .iter_mut(world)
                {
                    t.translation.x += sign * 1e-4;
                }
            }
            Change::Particles => self.touch_particles(),
        }
    }

    /// Median wall time of `frames` frames that each apply `change`, and the frames.
    fn wall_of(&mut self, change: Change, frames: usize) -> (f64, Vec<FrameStats>) {
        self.frame(); // settle
        let mut ids = Vec::new();
        for i in 0..frames {
            self.change(change, i);
            ids.push(self.frame());
        }
        if frames % 2 == 1 {
            self.change(change, frames); // undo the odd change
            self.frame();
        }
        for _ in 0..4 {
            self.recorder.drain(&mut self.app);
        }
        let stats: Vec<FrameStats> = ids
            .iter()
            .map(|&i| self.recorder.frames[i].clone())
            .collect();
        (median(stats.iter().map(|f| f.wall_ms).collect()), stats)
    }
}

/// Per-pass cost from wall-time differences of frames that rerun nested sets of passes (reliable
/// on every adapter, and the only per-pass figure that means something on llvmpipe).
#[derive(Clone, Debug, Default)]
struct WallPasses {
    /// voxelize (with the particles' upload), shade, gather, scatter (with colours), sort, draw
    /// (static frame, with Bevy's per-frame overhead).
    pass_ms: [f64; PASSES],
}

fn wall_passes(b: &mut Bench, frames: usize) -> (WallPasses, Timing) {
    let (_, timing) = b.measure(frames);
    let (w0, _) = b.wall_of(Change::Nothing, frames);
    let (wa, _) = b.wall_of(Change::Albedo, frames);
    let (wi, _) = b.wall_of(Change::Irradiance, frames);
    let (wd, _) = b.wall_of(Change::Direction, frames);
    let (wc, _) = b.wall_of(Change::Camera, frames);
    let (wp, _) = b.wall_of(Change::Particles, frames);
    // The camera's move reruns the view pass: the sort or the view volume, whichever runs.
    let view = wc - w0;
    let pass_ms = [wp - wd - view, wd - wi, wi - wa, wa - w0, view, 0.0, w0];
    (WallPasses { pass_ms }, timing)
}

fn illumination_benchmark(args: &Args) -> Result<(), String> {
    let mut csv = String::from(
        "adapter,scene,lights,volume_resolution,shading,gpu_ms_voxelize,gpu_ms_shade,gpu_ms_gather,gpu_ms_scatter,\
         gpu_ms_view,gpu_ms_draw,gpu_ms_total,wall_ms,wall_ms_voxelize,wall_ms_shade,wall_ms_gather,wall_ms_scatter,\
         wall_ms_view,wall_ms_static\n",
    );
    let mut adapter = String::new();
    let mut lines: Vec<(usize, u32, String, Timing, WallPasses)> = Vec::new();
    let mut ratios = Vec::new();
    for name in ["paper_38k_1light", "paper_38k_5lights"] {
        let bench = SCENES.iter().find(|s| s.name == name).expect("scene");
        let scene = load_scene(bench)?;
        let mut b = Bench::new(&scene);
        adapter = b.adapter.clone();
        // Light volumes of 64³ and 128³ (light_supersampling 2).
        for n in [32u32, 64] {
            let mut shade = HashMap::new();
            for method in [ShadingMethod::Incremental, ShadingMethod::BruteForce] {
                b.app.insert_resource(method);
                b.set_quality(CloudQualitySettings {
                    volume_resolution: n,
                    ..default()
                });
                let (w, t) = wall_passes(&mut b, args.frames);
                let method_name = format!("{method:?}");
                eprintln!(
                    "benchmark: {name} {n}³ {method_name}: shade GPU {:.2} ms, wall {:.1} ms; GPU total {:.2} ms, wall {:.1} ms",
                    t.pass_ms[1], w.pass_ms[1], t.gpu_ms_total, t.wall_ms
                );
                let p = &t.pass_ms;
                let q = &w.pass_ms;
                let _ = writeln!(
                    csv,
                    "\"{adapter}\",{name},{},{n},{method_name},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.3},{:.3},{:.3},{:.3},{:.3},{:.3},{:.3}",
                    scene.lights.len(),
                    p[0],
                    p[1],
                    p[2],
                    p[3],
                    p[4] + p[5],
                    p[6],
                    t.gpu_ms_total,
                    t.wall_ms,
                    q[0],
                    q[1],
                    q[2],
                    q[3],
                    q[4] + q[5],
                    q[6]
                );
                shade.insert(method, (t.pass_ms[1], w.pass_ms[1]));
                lines.push((scene.lights.len(), n, method_name, t, w));
            }
            let (gi, wi) = shade[&ShadingMethod::Incremental];
            let (gb, wb) = shade[&ShadingMethod::BruteForce];
            ratios.push((scene.lights.len(), n, gb / gi, wb / wi));
        }
        b.app.insert_resource(ShadingMethod::Incremental);
    }
    let mut table = format!(
        "Adapter: `{adapter}`. The 38,000-particle cloud (benchmarks/scenes/paper_38k_*.ron, 640×480), \
         8 scattering iterations, the default stencil and knobs. GPU: per-pass timestamps, median of {} frames in which \
         every pass reruns. Wall: per-pass cost from wall-time differences of frames that rerun nested sets of \
         passes (scatter: albedo changed; + gather: irradiance changed; + shade: light directions changed; \
         + voxelize: particles changed, including their upload; sort: camera moved; static: nothing changed, \
         the draw plus Bevy's per-frame work).\n\n",
        args.frames
    );
    table.push_str("| lights | volume | shading | GPU: voxelize | shade | gather | scatter | sort | draw | total | wall: voxelize | shade | gather | scatter | sort | static frame | all passes |\n");
    table.push_str(
        "|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for (lights, n, method, t, w) in &lines {
        let p = &t.pass_ms;
        let q = &w.pass_ms;
        let _ = writeln!(
            table,
            "| {lights} | {n}³ | {method} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} |",
            p[0],
            p[1],
            p[2],
            p[3],
            p[4] + p[5],
            p[6],
            t.gpu_ms_total,
            q[0],
            q[1],
            q[2],
            q[3],
            q[4] + q[5],
            q[6],
            t.wall_ms
        );
    }
    table.push_str("\nShade cost of the brute-force march (every voxel marching to the light) over the incremental pass:\n\n");
    table.push_str(
        "| lights | volume | ratio (GPU timestamps) | ratio (wall time) |\n|---:|---:|---:|---:|\n",
    );
    for (lights, n, g, w) in &ratios {
        let _ = writeln!(table, "| {lights} | {n}³ | {g:.1}× | {w:.1}× |");
    }
    let csv_path = args.out.join("illumination.csv");
    std::fs::write(&csv_path, csv)
        .map_err(|e| format!("cannot write {}: {e}", csv_path.display()))?;
    let md_path = args.out.join("illumination.md");
    std::fs::write(&md_path, &table)
        .map_err(|e| format!("cannot write {}: {e}", md_path.display()))?;
    println!("{table}");
    eprintln!(
        "benchmark: wrote {} and {}",
        csv_path.display(),
        md_path.display()
    );
    Ok(())
}
