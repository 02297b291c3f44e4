//! The time–error benchmark: renders fixed benchmark scenes with the real-time renderer over a
//! sweep of its quality knobs, measures GPU time (timestamp queries, summed over passes) and wall
//! time per frame, and compares every image with a path-traced ground truth (docs/physics.md's relative
//! RMSE, relMSE and mean absolute error, beside the reference's own sample count and noise level).
//!
//! ```text
//! cargo run --example benchmark -- [--quick] [--out DIR] [--scenes a,b] [--frames K] [--font TTF]
//! cargo run --example benchmark -- --settings '(volume_resolution: 64)' [--settings …] [--scenes a,b]
//! cargo run --example benchmark -- --illumination [--view 640x480] [--out DIR]
//! cargo run --example benchmark -- --voxelize [--out DIR]
//! cargo run --example benchmark -- --scale [--out DIR]
//! cargo run --example benchmark -- --frame-budget [--view 1920x1080] [--bandwidth 4.8] [--draw-methods raster,compute] [--sweep-dispatches per-pair,per-order] [--out DIR]
//! cargo run --example benchmark -- --warm-start [--scenes a,b] [--out DIR]
//! cargo run --example benchmark -- --decompose [--scenes a,b] [--spp N] [--settings RON]... [--out DIR]
//! cargo run --example benchmark -- --grid-error [--scenes albedo_one] [--out DIR]
//! cargo run --example benchmark -- --sky-map [--scenes cloud_over_ground_sky] [--out DIR]
//! cargo run --example benchmark -- --coarse-cycles [--scenes albedo_one] [--settings '(volume_resolution: 64)'] [--out DIR]
//! cargo run --example benchmark -- --raster-vs-compute [--view 1920x1080] [--layers 13] [--out DIR]
//! cargo run --example benchmark -- --line-sweep [--grid 128] [--segments 8] [--out DIR]
//! cargo run --example benchmark -- --still-view [--scenes a,b] [--out DIR]
//! cargo run --example benchmark -- --sweep-response [--out DIR]
//! ```
//!
//! Writes `DIR/results.csv`, `DIR/results.md` and `DIR/pareto.png` (default `DIR` is
//! `target/benchmark`); path-traced references are cached as `DIR/reference-<hash>-s<seed>.exr`,
//! keyed by a hash of the scene contents, image size, sample count and seed, so a rerun does not
//! trace them again. `--illumination` instead writes `DIR/illumination.csv` and `.md`: every
//! pass's GPU time at 32³ and 64³ (light volumes of 64³ and 128³) with 1 and 5 lights,
//! incremental shading against the brute force march (`ShadingMethod::BruteForce`). `--decompose` writes `DIR/decomposition.md`: the
//! default settings' error split into single scattering, each scattering order and the closure
//! (beside the image itself, which the parts, drawn alone, need not sum to),
//! against the path tracer split by order (CPU references, no adapter; see `decompose.rs`).
//! `--grid-error` writes `DIR/grid_error.md`: the error against volume resolution and scattering
//! iterations up to the converged series, and where the scattering grid's error lies (CPU
//! references; see `grid_error.rs`). `--sky-map` writes `DIR/sky_map.md`: the sky map's error
//! against its direction count and size (CPU references) and its cost (see `sky_map.rs`).
//! `--coarse-cycles` writes `DIR/coarse_cycles.md`: the scattering series against two-grid
//! cycles of as many sweeps or fewer (CPU references; see `coarse_cycles.rs`).
//! `--sweep-response` writes `DIR/sweep_response.md`: how one scattering sweep carries a source's
//! spatial detail against the exact transport (CPU reference; see `sweep_response.rs`).
//!
//! Timing. The GPU time of a setting is the sum of the per-pass GPU times (Bevy's render
//! diagnostics; `FrameStats::gpu_ms` of the headless harness) of a frame in which every pass runs:
//! each measured frame touches the cloud's `Particles` asset, which re-uploads it and reruns
//! voxelize, shade (every light), gather, scatter and sort; the draw (the `Transparent3d` pass,
//! `main_transparent_pass_3d`) runs every frame anyway. The static cost is that of a frame where
//! nothing changed: the draw only. Both are medians over `--frames` frames, wall time beside them.
//! Every mode draws a still view again each frame (`CloudRedraw::EveryFrame`), so that its static
//! frame measures the draw; `--still-view` measures what the default, which keeps a still view's
//! clouds, saves.

mod cloud_target_scale;
mod coarse_cycles;
mod decompose;
mod fog;
mod frame_budget;
mod grid_error;
mod illumination;
mod line_sweep;
mod plot;
mod raster_vs_compute;
mod reference_cache;
mod report;
mod scale;
mod scenes;
mod sky_map;
mod still_view;
mod sweep;
mod sweep_response;
mod voxelize;
mod warm_start;

use std::{
    collections::HashMap,
    fmt::Write as _,
    path::{Path, PathBuf},
    process::ExitCode,
    time::Instant,
};

use bevy::{
    diagnostic::{DiagnosticPath, DiagnosticsStore},
    prelude::*,
};
use bevy_particle_clouds::headless::{self, FrameRecorder, FrameStats};
use bevy_particle_clouds::reference::path_tracer::Progress;
use bevy_particle_clouds::{
    BillboardShading, CloudLevelOfDetail, CloudPass, CloudQualitySettings, Compositing, DrawMethod,
    PASSES, Particle, ParticleCloud, Particles, ScatterStencil, SweepDirections,
    fog::Fog,
    generators,
    image_io::{ImageMetadata, LinearImage, read_exr, write_exr_with_metadata, write_png},
    math::SplitMix64,
    particle_files::{write_csv, write_ply_binary},
    reference::{
        metrics::{mean_absolute_error, rel_mse, relative_rmse},
        path_tracer::{self, PathTracerSettings, noise_level},
    },
    scene::Scene,
    settings::{ShadingMethod, SweepDispatch},
};
use clap::Parser;
use cloud_target_scale::*;
use fog::*;
use frame_budget::*;
use illumination::*;
use indicatif::{ProgressBar, ProgressStyle};
use plot::*;
use reference_cache::*;
use report::*;
use scale::*;
use scenes::*;
use still_view::still_view_benchmark;
use sweep::*;
use voxelize::*;
use warm_start::*;

/// Where Debian's `fonts-dejavu-core` puts the font of the plot's labels.
const DEFAULT_FONT: &str = "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf";

/// The render diagnostics of the draw: Bevy's transparent pass (the cloud billboards are its only
/// items) and the cloud target's draw and composite (`cloud_target_scale` below 1).
fn draw_diagnostics() -> [DiagnosticPath; 2] {
    ["main_transparent_pass_3d", CloudPass::Draw.span_name()]
        .map(|span| DiagnosticPath::from_components(["render", span, "elapsed_gpu"]))
}

/// The time–error benchmark of the real-time renderer against the path tracer.
#[derive(Parser, Debug)]
#[command(long_about = None)]
pub(crate) struct Args {
    /// A short sweep (fewer settings and scenes) for a quick look.
    #[arg(long, conflicts_with_all = ["decompose", "illumination", "replot"])]
    pub(crate) quick: bool,
    /// Where results, plots and cached references go.
    #[arg(long, default_value = "target/benchmark")]
    pub(crate) out: PathBuf,
    /// Only these scenes (comma-separated names); with --scale, only these sweeps (particles,
    /// clouds, view); with --illumination, `paper_38k_1light` or `paper_38k_5lights`.
    #[arg(long, value_delimiter = ',')]
    pub(crate) scenes: Option<Vec<String>>,
    /// Measured frames per setting (medians are reported).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u64).range(1..))]
    frames: u64,
    /// The TTF font of the plot's labels.
    #[arg(long, default_value = DEFAULT_FONT)]
    pub(crate) font: PathBuf,
    /// Every illumination pass's GPU time instead of the sweep.
    #[arg(long, conflicts_with_all = ["decompose", "replot"])]
    pub(crate) illumination: bool,
    /// The draw's cost and error at each cloud target scale (1, 1/2, 1/4) instead of the sweep:
    /// against the path tracer and against the full-size image.
    #[arg(long, conflicts_with_all = ["decompose", "replot", "illumination"])]
    pub(crate) cloud_target: bool,
    /// Cost at scale instead of the sweep: against particles (3.1k–1.2M), clouds (1, 10, 100)
    /// and view size (720p–4K).
    /// With --replot: only redraw DIR/scale.png from DIR/scale.csv.
    #[arg(long, conflicts_with_all = ["decompose", "illumination", "cloud_target", "voxelize"])]
    pub(crate) scale: bool,
    /// What three game-sized scenes cost per frame (the paper's 38,000 particles with 5 lights
    /// at 128³, the 1.2-million-particle snow bunny, the 100-cloud cloudscape), pass by pass,
    /// beside each pass's memory-bandwidth floor, instead of the sweep. `--scenes` picks among
    /// `paper`, `paper-half` (drawn at half size), `snow`, `cloudscape`.
    #[arg(long, conflicts_with_all = ["decompose", "replot", "illumination", "cloud_target", "scale", "voxelize"])]
    pub(crate) frame_budget: bool,
    /// The view's size, pixels: with --frame-budget and --raster-vs-compute (default
    /// 1920x1080), and with --illumination (default: the scenes' own 640x480).
    #[arg(long, value_parser = parse_view)]
    view: Option<(u32, u32)>,
    /// With --frame-budget: how the billboards are drawn, each in turn (comma-separated:
    /// `raster`, `compute`); with --scale, the last of them.
    #[arg(long, value_delimiter = ',', default_value = "raster", value_parser = parse_draw_method)]
    pub(crate) draw_methods: Vec<DrawMethod>,
    /// With --frame-budget: how the scattering sweep dispatches an order's direction pairs,
    /// each in turn (comma-separated: `per-pair`, the default, and `per-order`; `SweepDispatch`).
    #[arg(long, value_delimiter = ',', default_value = "per-pair", value_parser = parse_sweep_dispatch)]
    pub(crate) sweep_dispatches: Vec<SweepDispatch>,
    /// With --frame-budget: the memory bandwidth the floors are computed at, TB/s (default: an
    /// H200's HBM3e).
    #[arg(long, default_value_t = 4.8)]
    pub(crate) bandwidth: f64,
    /// The voxelize pass's cost against particle size (r/h from 1 to 64) instead of the sweep.
    #[arg(long, conflicts_with_all = ["decompose", "replot", "illumination", "cloud_target"])]
    pub(crate) voxelize: bool,
    /// The scattering's warm restart under a moving sun instead of the sweep: its error against
    /// the path tracer and its cost, per sun step and warm iteration count.
    #[arg(long, conflicts_with_all = ["decompose", "replot", "illumination", "cloud_target", "voxelize", "scale"])]
    pub(crate) warm_start: bool,
    /// Overrides every scene's reference samples per pixel.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub(crate) spp: Option<u32>,
    /// Only redraw DIR/pareto.png from DIR/results.csv.
    #[arg(long)]
    pub(crate) replot: bool,
    /// Split the default settings' error by scattering order (CPU only).
    #[arg(long)]
    pub(crate) decompose: bool,
    /// The error against `volume_resolution` and `scatter_iterations` up to the converged
    /// series, and where the scattering grid's error lies (CPU only; isotropic scenes without a
    /// sky or ground; default scene `albedo_one`).
    #[arg(long, conflicts_with_all = ["decompose", "replot", "illumination", "cloud_target", "scale", "voxelize", "frame_budget", "warm_start"])]
    pub(crate) grid_error: bool,
    /// The sky map's error against its direction count and size (CPU references) and its cost
    /// for one cloud and a field of 100 (default scene `cloud_over_ground_sky`).
    #[arg(long, conflicts_with_all = ["decompose", "replot", "illumination", "cloud_target", "scale", "voxelize", "frame_budget", "warm_start", "grid_error"])]
    pub(crate) sky_map: bool,
    /// The scattering series against two-grid cycles of as many sweeps or fewer (CPU only; one
    /// cloud under a black sky, without a ground; default scene `albedo_one`). The GPU's cycles:
    /// the sweep with `--settings '(scatter_coarse_cycles: 2)'`.
    #[arg(long, conflicts_with_all = ["decompose", "replot", "illumination", "cloud_target", "scale", "voxelize", "frame_budget", "warm_start", "grid_error", "sky_map"])]
    pub(crate) coarse_cycles: bool,
    /// How one scattering sweep carries a source's spatial detail (a Fourier mode) against the
    /// exact transport, per voxel optical depth (CPU only, no scene).
    #[arg(long, conflicts_with_all = ["decompose", "replot", "illumination", "cloud_target", "scale", "voxelize", "frame_budget", "warm_start", "grid_error", "sky_map", "coarse_cycles"])]
    pub(crate) sweep_response: bool,
    /// Clouds do not shadow each other (every cloud `NotShadowCaster`): what the cast of their
    /// shadows costs and what its absence does to the error.
    #[arg(long)]
    pub(crate) no_cloud_shadows: bool,
    /// No ground lights the clouds from below (no `CloudGround`, though the scene has lit
    /// objects): what the ground's light costs and what its absence does to the error.
    #[arg(long)]
    pub(crate) no_ground: bool,
    /// Texels per side of the cloud shadow maps of scenes with lit objects (default: each
    /// scene's `shadow_map_resolution`).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=4096))]
    pub(crate) shadow_map_resolution: Option<u32>,
    /// The draw's kind of per-pixel work in a fragment shader against a compute shader, in plain
    /// wgpu (`raster_vs_compute.rs`), at `--view`, instead of the sweep.
    #[arg(long, conflicts_with_all = ["decompose", "replot", "illumination", "cloud_target", "scale", "voxelize", "frame_budget"])]
    pub(crate) raster_vs_compute: bool,
    /// With --raster-vs-compute: billboards over each pixel (the paper's scene: 13 at 1080p).
    #[arg(long, default_value_t = 13, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub(crate) layers: u32,
    /// The scattering sweep's line march in plain wgpu (`line_sweep.rs`): whole lines against
    /// lines cut into `--segments`, instead of the sweep.
    #[arg(long, conflicts_with_all = ["decompose", "replot", "illumination", "cloud_target", "scale", "voxelize", "frame_budget", "raster_vs_compute"])]
    pub(crate) line_sweep: bool,
    /// A still frame's cost when the view keeps its clouds (`CloudRedraw::WhenChanged`, the
    /// default) against drawing them again, instead of the sweep.
    #[arg(long, conflicts_with_all = ["decompose", "replot", "illumination", "cloud_target", "scale", "voxelize", "frame_budget", "raster_vs_compute", "line_sweep"])]
    pub(crate) still_view: bool,
    /// With --line-sweep: voxels per side of the grid.
    #[arg(long, default_value_t = 128, value_parser = clap::value_parser!(u32).range(2..=512))]
    pub(crate) grid: u32,
    /// With --line-sweep: segments per line.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub(crate) segments: u32,
    /// Measure only these settings (RON, as a scene file's `settings`) instead of the sweep; with
    /// --decompose, decompose each (against one path-traced reference per scene) instead of the
    /// defaults. Repeatable.
    #[arg(long = "settings", value_name = "RON", value_parser = parse_settings)]
    pub(crate) settings: Vec<CloudQualitySettings>,
}

impl Args {
    /// `--frames` as a count.
    pub(crate) fn frames(&self) -> usize {
        self.frames as usize
    }

    /// `--view`, or 1920×1080, a game's view.
    pub(crate) fn game_view(&self) -> (u32, u32) {
        self.view.unwrap_or((1920, 1080))
    }

    /// `--view`, or `scene`'s own.
    pub(crate) fn view_or(&self, scene: (u32, u32)) -> (u32, u32) {
        self.view.unwrap_or(scene)
    }
}

/// `1920x1080`: a view's width and height, each 1–8192.
fn parse_view(text: &str) -> Result<(u32, u32), String> {
    let size = text
        .split_once(['x', '×'])
        .and_then(|(w, h)| Some((w.parse::<u32>().ok()?, h.parse::<u32>().ok()?)));
    match size {
        Some((w, h)) if (1..=8192).contains(&w) && (1..=8192).contains(&h) => Ok((w, h)),
        _ => Err(format!(
            "`{text}` is not WIDTHxHEIGHT with each in 1..=8192"
        )),
    }
}

fn parse_draw_method(text: &str) -> Result<DrawMethod, String> {
    match text {
        "raster" => Ok(DrawMethod::Raster),
        "compute" => Ok(DrawMethod::Compute),
        _ => Err(format!(
            "`{text}` is not a draw method; allowed are raster, compute"
        )),
    }
}

fn parse_sweep_dispatch(text: &str) -> Result<SweepDispatch, String> {
    match text {
        "per-pair" => Ok(SweepDispatch::PerPair),
        "per-order" => Ok(SweepDispatch::PerOrder),
        _ => Err(format!(
            "`{text}` is not a sweep dispatch; allowed are per-pair, per-order"
        )),
    }
}

fn parse_settings(text: &str) -> Result<CloudQualitySettings, String> {
    let settings: CloudQualitySettings = ron::from_str(text).map_err(|e| e.to_string())?;
    settings.validate().map_err(|e| e.to_string())?;
    Ok(settings)
}

/// A progress bar over the `rows` rows of a path-traced image, and the callback that advances it.
fn path_tracing_progress(label: &str, rows: u32) -> (ProgressBar, Progress) {
    let bar = ProgressBar::new(rows as u64).with_style(
        ProgressStyle::with_template(&format!(
            "{label} {{bar:40}} {{pos}}/{{len}} rows, {{eta}} left"
        ))
        .expect("progress template"),
    );
    let advance = bar.clone();
    (
        bar,
        Progress::new(move |done, _| advance.set_position(done as u64)),
    )
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

/// `--raster-vs-compute`: the default draw's per-pixel work (9 chord points, 5 lights and the
/// multiple scattering) and the bare fragments (no chord point), three ways each; writes
/// `DIR/raster_vs_compute.md`.
fn raster_vs_compute_benchmark(args: &Args) -> Result<(), String> {
    let (width, height) = args.game_view();
    let mut md = String::new();
    for points in [9, 0] {
        let work = raster_vs_compute::Workload {
            width,
            height,
            layers: args.layers,
            points,
            volumes: 6,
            n: 128,
        };
        eprintln!("benchmark: raster vs compute, {points} points");
        let (adapter, results) = raster_vs_compute::measure(work, args.frames())?;
        md.push_str(&raster_vs_compute::table(&adapter, work, &results));
        md.push('\n');
    }
    write_report(args, "raster_vs_compute.md", &md)
}

/// `--line-sweep`: 26 sweeps per timed submission (two iterations' worth); writes
/// `DIR/line_sweep.md`.
fn line_sweep_benchmark(args: &Args) -> Result<(), String> {
    eprintln!(
        "benchmark: line sweep, {}³, {} segments",
        args.grid, args.segments
    );
    let (adapter, results) = line_sweep::measure(args.grid, args.segments, 26, args.frames())?;
    let md = line_sweep::table(&adapter, args.grid, &results);
    write_report(args, "line_sweep.md", &md)
}

/// The scenes `--scenes` names (else `default` alone), loaded.
fn named_scenes(args: &Args, default: &str) -> Result<Vec<(&'static BenchScene, Scene)>, String> {
    let names = args.scenes.clone().unwrap_or_else(|| vec![default.into()]);
    names
        .iter()
        .map(|name| {
            let bench = SCENES
                .iter()
                .find(|s| s.name == name)
                .ok_or_else(|| format!("no such scene `{name}`"))?;
            Ok((bench, load_scene(bench)?))
        })
        .collect()
}

/// Writes `md` to `DIR/file` and prints it.
fn write_report(args: &Args, file: &str, md: &str) -> Result<(), String> {
    let path = args.out.join(file);
    std::fs::write(&path, md).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    println!("{md}");
    Ok(())
}

/// `--grid-error`: each chosen scene's (default `albedo_one`) error against the grid's knobs.
fn grid_error_benchmark(args: &Args) -> Result<(), String> {
    let mut md = String::from(
        "The scattering grid's error against the path tracer (`cargo run --example benchmark -- \
         --grid-error`), computed with the f64 CPU references of the real-time passes (which the \
         GPU matches).\n",
    );
    for (bench, scene) in named_scenes(args, "albedo_one")? {
        let name = bench.name;
        let isotropic = scene.clouds.iter().all(|c| c.medium.anisotropy == 0.0);
        if !isotropic || scene.background != Vec3::ZERO || scene.cloud_ground().is_some() {
            return Err(format!(
                "`{name}` has an anisotropic medium, a sky or a ground; --grid-error takes \
                 isotropic clouds under a black sky"
            ));
        }
        let spp = args.spp.unwrap_or(bench.spp);
        let reference = reference(&scene, bench, spp, &args.out)?;
        md.push_str(&grid_error::grid_error(bench, &scene, &reference));
    }
    write_report(args, "grid_error.md", &md)
}

/// `--coarse-cycles`: each chosen scene's (default `albedo_one`) error with the series and with
/// two-grid cycles.
fn coarse_cycles_benchmark(args: &Args) -> Result<(), String> {
    let mut md = String::from(
        "# Coarse-grid cycles\n\nThe scattering series against two-grid cycles \
         (`cargo run --example benchmark -- --coarse-cycles`; docs/illumination.md §4, \
         \"Coarse-grid cycles\"), computed with the f64 CPU references (the GPU's cycles: \
         the sweep with `--settings '(scatter_coarse_cycles: 2)'`).\n",
    );
    for (bench, scene) in named_scenes(args, "albedo_one")? {
        // The CPU image (`grid_error::image`) is the cloud's alone, over black.
        if scene.clouds.len() != 1
            || scene.cloud_ground().is_some()
            || scene.background != Vec3::ZERO
        {
            return Err(format!(
                "`{}` has several clouds, a ground or a sky; --coarse-cycles takes one cloud \
                 under a black sky",
                bench.name
            ));
        }
        let spp = args.spp.unwrap_or(bench.spp);
        let reference = reference(&scene, bench, spp, &args.out)?;
        let settings = args.settings.first().copied().unwrap_or(scene.settings);
        md.push_str(&coarse_cycles::coarse_cycles(
            bench, &scene, settings, &reference,
        ));
    }
    write_report(args, "coarse_cycles.md", &md)
}

/// `--sky-map`: the sky map's error and cost on each chosen scene (default
/// `cloud_over_ground_sky`).
fn sky_map_benchmark(args: &Args) -> Result<(), String> {
    let mut md = String::from(
        "# The sky map\n\nWhat the clouds hide of the sky from the ground (docs/illumination.md \
         §10), measured by `cargo run --example benchmark -- --sky-map`.\n",
    );
    for (bench, scene) in named_scenes(args, "cloud_over_ground_sky")? {
        let name = bench.name;
        if scene.background == Vec3::ZERO {
            return Err(format!(
                "`{name}` has a black sky; --sky-map takes a scene under a sky"
            ));
        }
        eprintln!("benchmark: {name}: the sky map's error (CPU)");
        md.push_str(&sky_map::error(name, &scene, &scene.settings));
        eprintln!("benchmark: {name}: the sky map's cost");
        md.push_str(&sky_map::cost(&scene)?);
    }
    write_report(args, "sky_map.md", &md)
}

/// `--decompose`: every chosen scene's error at the default settings (or at each `--settings`,
/// against one path-traced reference per scene), part by part.
fn decomposition(args: &Args, chosen: &[&BenchScene]) -> Result<(), String> {
    let settings = if args.settings.is_empty() {
        vec![CloudQualitySettings::default()]
    } else {
        args.settings.clone()
    };
    let mut md = String::from(
        "The error split by scattering order (`cargo run --example benchmark -- --decompose`), \
         computed with the f64 CPU references of the real-time passes (which the GPU matches \
         within 2e-4 of the maximum) against the path tracer split by order. Energies are sums \
         over the image; λ is an order's energy over the previous one's.\n",
    );
    for bench in chosen {
        let scene = load_scene(bench)?;
        let spp = args.spp.unwrap_or(bench.spp);
        let factor = bench.error_downsample;
        let real_time: Vec<decompose::RealTime> = settings
            .iter()
            .map(|s| decompose::real_time(&scene, s, factor))
            .collect();
        let orders = real_time.iter().map(|r| r.orders()).max().unwrap_or(1);
        eprintln!(
            "benchmark: {}: path tracing {orders} orders at {spp} spp per half",
            bench.name
        );
        let truth = decompose::Truth::render(&scene, factor, spp, orders);
        for (s, r) in settings.iter().zip(&real_time) {
            let section = decompose::decompose(bench.name, &scene, s, factor, spp, (r, &truth));
            eprintln!("{section}");
            md.push_str(&section);
        }
    }
    write_report(args, "decomposition.md", &md)
}

fn run() -> Result<(), String> {
    let args = Args::parse();
    std::fs::create_dir_all(&args.out)
        .map_err(|e| format!("cannot create {}: {e}", args.out.display()))?;
    if args.illumination {
        return illumination_benchmark(&args);
    }
    if args.cloud_target {
        return cloud_target_benchmark(&args);
    }
    if args.frame_budget {
        return frame_budget_benchmark(&args);
    }
    if args.raster_vs_compute {
        return raster_vs_compute_benchmark(&args);
    }
    if args.line_sweep {
        return line_sweep_benchmark(&args);
    }
    if args.still_view {
        return still_view_benchmark(&args);
    }
    if args.voxelize {
        return voxelize_benchmark(&args);
    }
    if args.warm_start {
        return warm_start_benchmark(&args);
    }
    if args.grid_error {
        return grid_error_benchmark(&args);
    }
    if args.coarse_cycles {
        return coarse_cycles_benchmark(&args);
    }
    if args.sky_map {
        return sky_map_benchmark(&args);
    }
    if args.sweep_response {
        return write_report(&args, "sweep_response.md", &sweep_response::table());
    }
    if args.scale {
        return if args.replot {
            replot_scale(&args)
        } else {
            scale_benchmark(&args)
        };
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
    let csv = args.out.join("results.csv");
    for bench in &chosen {
        let scene = load_scene(bench)?;
        let spp = args
            .spp
            .unwrap_or(if args.quick { bench.spp / 4 } else { bench.spp });
        let fog_effect = FogEffect::new(&scene, bench, spp, &args.out)?;
        let reference = reference(&scene, bench, spp, &args.out)?;
        let mut b = Bench::with_shadow_maps(&scene, args.shadow_map_resolution);
        if args.no_cloud_shadows {
            b.without_cloud_shadows();
        }
        if args.no_ground {
            b.without_ground();
        }
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
        let bar = ProgressBar::new(settings.len() as u64).with_style(
            ProgressStyle::with_template(&format!(
                "{} {{bar:40}} {{pos}}/{{len}} settings, {{eta}} left",
                bench.name
            ))
            .expect("progress template"),
        );
        for s in &settings {
            let t0 = Instant::now();
            b.set_quality(*s);
            let (image, timing) = match b.try_measure(args.frames()) {
                Ok(measured) => measured,
                Err(why) => {
                    bar.suspend(|| {
                        eprintln!(
                            "benchmark: {} {}: skipped, not measured: {why}",
                            bench.name,
                            setting_label(s)
                        )
                    });
                    bar.inc(1);
                    continue;
                }
            };
            let image = downsample(&image, bench.error_downsample);
            assert_eq!(
                (image.width, image.height),
                (reference.width, reference.height)
            );
            // Under a sky, over the pixels where the cloud changes it.
            let sky = scene.background;
            let (seen, truth) = (
                cloud_pixels(&image.pixels, &reference.image, sky),
                cloud_pixels(&reference.image, &reference.image, sky),
            );
            let (rel_rmse, rel_mse_, mae) = (
                relative_rmse(&seen, &truth),
                rel_mse(&seen, &truth),
                mean_absolute_error(&seen, &truth),
            );
            let reference_image = LinearImage {
                width: reference.width,
                height: reference.height,
                pixels: reference.image.clone(),
            };
            let boxed_truth = downsample(&reference_image, 4).pixels;
            let rel_rmse_box4 = relative_rmse(
                &cloud_pixels(&downsample(&image, 4).pixels, &boxed_truth, sky),
                &cloud_pixels(&boxed_truth, &boxed_truth, sky),
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
            // Scenes with fog: the error of what the fog changes (the same frame without it).
            if let Some(effect) = &fog_effect {
                b.set_fog(None);
                let clear = downsample(&b.image(), bench.error_downsample);
                let (clear_draw, clear_wall) = b.static_frames(args.frames());
                b.set_fog(scene.fog.as_ref());
                b.image();
                let (fog_draw, fog_wall) = b.static_frames(args.frames());
                bar.suspend(|| {
                    eprintln!(
                        "benchmark: {} {}: static frame with fog / without: draw {:.1} / {:.1} ms, wall {:.1} / {:.1} ms",
                        bench.name,
                        setting_label(s),
                        median(fog_draw),
                        median(clear_draw),
                        median(fog_wall),
                        median(clear_wall)
                    )
                });
                let (error, inherited) =
                    effect.error(&image.pixels, &clear.pixels, &reference, &scene);
                let noise = effect.noise(&reference);
                bar.suspend(|| {
                    eprintln!(
                        "benchmark: {} {}: the fog's effect: rel. RMSE {error:.4} (denoised {:.4}; noise {noise:.4}); the clear cloud's error through the fog alone would make it about {inherited:.4}",
                        bench.name,
                        setting_label(s),
                        denoised(error, noise)
                    )
                });
            }
            // Scenes with lit objects: the error over the pixels that see one (the ground and
            // the clouds' shadows on it).
            if let Some((mask, noise)) = &reference.ground {
                let error = relative_rmse(
                    &masked(&image.pixels, mask),
                    &masked(&reference.image, mask),
                );
                bar.suspend(|| {
                    eprintln!(
                        "benchmark: {} {}: over the lit objects' pixels rel. RMSE {error:.4} (denoised {:.4}; noise {noise:.4})",
                        bench.name,
                        setting_label(s),
                        denoised(error, *noise)
                    )
                });
            }
            // Above the bar on a terminal; plain lines in a log.
            bar.inc(1);
            bar.suspend(|| eprintln!(
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
            ));
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
        bar.finish_and_clear();
        mark_pareto(&mut scene_rows);
        rows.extend(scene_rows);
        drop(b);
        // After every scene, so that a sweep stopped part way keeps the scenes it finished.
        write_csv_results(&csv, &adapter, &rows)
            .map_err(|e| format!("cannot write {}: {e}", csv.display()))?;
    }
    let order: Vec<&'static str> = chosen.iter().map(|s| s.name).collect();
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

/// A CSV file the benchmark wrote, opened for a replot.
pub(crate) struct CsvTable {
    pub(crate) reader: csv::Reader<std::fs::File>,
    header: csv::StringRecord,
    pub(crate) path: PathBuf,
}

impl CsvTable {
    pub(crate) fn open(path: PathBuf) -> Result<Self, String> {
        let mut reader = csv::Reader::from_path(&path)
            .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
        let header = reader
            .headers()
            .map_err(|e| format!("cannot read {}: {e}", path.display()))?
            .clone();
        Ok(Self {
            reader,
            header,
            path,
        })
    }

    /// The index of column `name`.
    pub(crate) fn column(&self, name: &str) -> Result<usize, String> {
        self.header
            .iter()
            .position(|h| h == name)
            .ok_or(format!("{}: no column {name}", self.path.display()))
    }
}

/// Redraws `DIR/pareto.png` from `DIR/results.csv` (e.g. after changing the plot).
fn replot(args: &Args) -> Result<(), String> {
    let mut table = CsvTable::open(args.out.join("results.csv"))?;
    let path = table.path.clone();
    let cannot_read = |e: csv::Error| format!("cannot read {}: {e}", path.display());
    let column = |name: &str| table.column(name);
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
    // Results written before the compositing knob existed were all sorted, and before the
    // billboard shading knob all shaded along the chord.
    let compositing = compositing.ok();
    let shading = table.column("billboard_shading").ok();
    // Written before the coarse-grid cycles existed: none.
    let cycles = table.column("scatter_coarse_cycles").ok();
    // Written before the draw method was recorded: rasterised (the default then).
    let draw_method = table.column("draw_method").ok();
    // Written before the sweep's directions were a knob: the 26.
    let directions = table.column("scatter_directions").ok();
    let (gpu, wall, rmse, noise, spp, pareto, axis) =
        (gpu?, wall?, rmse?, noise?, spp?, pareto?, axis?);
    let mut rows = Vec::new();
    let mut order: Vec<&'static str> = Vec::new();
    let mut adapter_name = String::new();
    for record in table.reader.records() {
        let record = record.map_err(cannot_read)?;
        let f = |i: usize| record.get(i).unwrap_or_default();
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
            billboard_shading: match shading.map(f) {
                Some("Centre") => BillboardShading::Centre,
                _ => BillboardShading::Chord,
            },
            // The sweep draws at full size; `--cloud-target` measures the scales.
            cloud_target_scale: 1.0,
            draw_method: match draw_method.map(f) {
                Some("Compute") => DrawMethod::Compute,
                _ => DrawMethod::Raster,
            },
            // The sweep's frames are still; `--warm-start` measures the warm restart.
            warm_scatter_iterations: 0,
            scatter_coarse_cycles: cycles.map_or(0, |c| num(c) as u32),
            scatter_directions: match directions.map(f) {
                Some("Lattice98") => SweepDirections::Lattice98,
                _ => SweepDirections::Lattice26,
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
