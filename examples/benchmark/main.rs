//! The time–error benchmark and the measurements beside it, one subcommand each: renders fixed
//! benchmark scenes with the real-time renderer over a sweep of its quality knobs, measures GPU
//! time (timestamp queries, summed over passes) and wall time per frame, and compares every image
//! with a path-traced ground truth (docs/physics.md's relative RMSE, relMSE and mean absolute
//! error, beside the reference's own sample count and noise level).
//!
//! ```text
//! cargo run --example benchmark -- accuracy [--quick] [--out DIR] [--scenes a,b] [--frames K] [--font TTF]
//! cargo run --example benchmark -- accuracy --settings '(volume_resolution: 64)' [--settings …] [--scenes a,b]
//! cargo run --example benchmark -- replot [--out DIR]
//! cargo run --example benchmark -- decompose [--scenes a,b] [--spp N] [--settings RON]... [--out DIR]
//! cargo run --example benchmark -- illumination [--view 640x480] [--out DIR]
//! cargo run --example benchmark -- cloud-target [--scenes a,b] [--out DIR]
//! cargo run --example benchmark -- voxelize [--out DIR]
//! cargo run --example benchmark -- scale [--scenes clouds] [--draw-methods compute] [--out DIR]
//! cargo run --example benchmark -- replot-scale [--out DIR]
//! cargo run --example benchmark -- frame-budget [--view 1920x1080] [--bandwidth 4.8] [--draw-methods raster,compute] [--sweep-dispatches per-pair,per-order] [--out DIR]
//! cargo run --example benchmark -- warm-start [--scenes a,b] [--out DIR]
//! cargo run --example benchmark -- grid-error [--scenes albedo_one] [--out DIR]
//! cargo run --example benchmark -- sky-map [--scenes cloud_over_ground_sky] [--out DIR]
//! cargo run --example benchmark -- coarse-cycles [--scenes albedo_one] [--settings '(volume_resolution: 64)'] [--out DIR]
//! cargo run --example benchmark -- raster-vs-compute [--view 1920x1080] [--layers 13] [--out DIR]
//! cargo run --example benchmark -- line-sweep [--grid 128] [--segments 8] [--out DIR]
//! cargo run --example benchmark -- still-view [--scenes a,b] [--out DIR]
//! cargo run --example benchmark -- sweep-response [--out DIR]
//! ```
//!
//! `--out DIR` (default `target/benchmark`) may come before or after the subcommand; `benchmark
//! help SUBCOMMAND` lists a subcommand's options. Each subcommand is a module of its own
//! (`accuracy.rs`, `frame_budget.rs`, …; both replots in `replot.rs`), and every plot is drawn in
//! `plot.rs`.
//!
//! `accuracy` writes `DIR/results.csv`, `DIR/results.md` and `DIR/pareto.png`; path-traced
//! references are cached as `DIR/reference-<hash>-s<seed>.exr`, keyed by a hash of the scene
//! contents, image size, sample count and seed, so a rerun does not trace them again.
//! `illumination` writes `DIR/illumination.csv` and `.md`: every pass's GPU time at 32³ and 64³
//! (light volumes of 64³ and 128³) with 1 and 5 lights, incremental shading against the brute
//! force march (`ShadingMethod::BruteForce`). `decompose` writes `DIR/decomposition.md`: the
//! default settings' error split into single scattering, each scattering order and the closure
//! (beside the image itself, which the parts, drawn alone, need not sum to), against the path
//! tracer split by order (CPU references, no adapter; see `decompose.rs`). `grid-error` writes
//! `DIR/grid_error.md`: the error against volume resolution and scattering iterations up to the
//! converged series, and where the scattering grid's error lies (CPU references; see
//! `grid_error.rs`). `sky-map` writes `DIR/sky_map.md`: the sky map's error against its direction
//! count and size (CPU references) and its cost (see `sky_map.rs`). `coarse-cycles` writes
//! `DIR/coarse_cycles.md`: the scattering series against two-grid cycles of as many sweeps or
//! fewer (CPU references; see `coarse_cycles.rs`). `sweep-response` writes
//! `DIR/sweep_response.md`: how one scattering sweep carries a source's spatial detail against the
//! exact transport (CPU reference; see `sweep_response.rs`).
//!
//! Timing. The GPU time of a setting is the sum of the per-pass GPU times (Bevy's render
//! diagnostics; `FrameStats::gpu_ms` of the headless harness) of a frame in which every pass runs:
//! each measured frame touches the cloud's `Particles` asset, which re-uploads it and reruns
//! voxelize, shade (every light), gather, scatter and sort; the draw (the `Transparent3d` pass,
//! `main_transparent_pass_3d`) runs every frame anyway. The static cost is that of a frame where
//! nothing changed: the draw only. Both are medians over `--frames` frames, wall time beside them.
//! Every subcommand draws a still view again each frame (`CloudRedraw::EveryFrame`), so that its
//! static frame measures the draw; `still-view` measures what the default, which keeps a still
//! view's clouds, saves.

mod accuracy;
mod cloud_target_scale;
mod coarse_cycles;
mod decompose;
mod dense;
mod fog;
mod frame_budget;
mod grid_error;
mod illumination;
mod line_sweep;
mod plot;
mod raster_vs_compute;
mod reference_cache;
mod replot;
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
use clap::{Parser, Subcommand};
use fog::*;
use indicatif::{ProgressBar, ProgressStyle};
use plot::*;
use reference_cache::*;
use report::*;
use scale::*;
use scenes::*;
use sweep::*;

/// Where Debian's `fonts-dejavu-core` puts the font of the plot's labels.
const DEFAULT_FONT: &str = "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf";

/// The render diagnostics of the draw: Bevy's transparent pass (the cloud billboards are its only
/// items) and the cloud target's draw and composite (`cloud_target_scale` below 1).
fn draw_diagnostics() -> [DiagnosticPath; 2] {
    ["main_transparent_pass_3d", CloudPass::Draw.span_name()]
        .map(|span| DiagnosticPath::from_components(["render", span, "elapsed_gpu"]))
}

/// The time–error benchmark of the real-time renderer against the path tracer, and the
/// measurements beside it.
#[derive(Parser, Debug)]
#[command(long_about = None)]
struct Cli {
    /// Where results, plots and cached references go.
    #[arg(long, global = true, default_value = "target/benchmark")]
    out: PathBuf,
    #[command(subcommand)]
    mode: Mode,
}

/// What the benchmark measures: one subcommand, one module.
#[derive(Subcommand, Debug)]
enum Mode {
    /// The time–error sweep: every setting's cost and error against the path tracer
    /// (results.csv, results.md, pareto.png).
    Accuracy(accuracy::AccuracyArgs),
    /// Only redraw DIR/pareto.png from DIR/results.csv.
    Replot(replot::ReplotArgs),
    /// Split the default settings' error by scattering order (CPU only).
    Decompose(decompose::DecomposeArgs),
    /// Media far denser than the fine grid resolves: a ball at rising extinction, the real-time
    /// image against the path tracer's beside the optical thickness of one fine voxel.
    Dense(dense::DenseArgs),
    /// Every illumination pass's GPU time, incremental against brute-force shading.
    Illumination(illumination::IlluminationArgs),
    /// The draw's cost and error at each cloud target scale (1, 1/2, 1/4): against the path
    /// tracer and against the full-size image.
    CloudTarget(cloud_target_scale::CloudTargetArgs),
    /// What three game-sized scenes cost per frame (the paper's 38,000 particles with 5 lights at
    /// 128³, the 1.2-million-particle snow bunny, the 100-cloud cloudscape), pass by pass, beside
    /// each pass's memory-bandwidth floor.
    FrameBudget(frame_budget::FrameBudgetArgs),
    /// The draw's kind of per-pixel work in a fragment shader against a compute shader, in plain
    /// wgpu (`raster_vs_compute.rs`).
    RasterVsCompute(raster_vs_compute::RasterVsComputeArgs),
    /// The scattering sweep's line march in plain wgpu (`line_sweep.rs`): whole lines against
    /// lines cut into `--segments`.
    LineSweep(line_sweep::LineSweepArgs),
    /// A still frame's cost when the view keeps its clouds (`CloudRedraw::WhenChanged`, the
    /// default) against drawing them again.
    StillView(still_view::StillViewArgs),
    /// The voxelize pass's cost against particle size (r/h from 1 to 64).
    Voxelize(voxelize::VoxelizeArgs),
    /// The scattering's warm restart under a moving sun: its error against the path tracer and
    /// its cost, per sun step and warm iteration count.
    WarmStart(warm_start::WarmStartArgs),
    /// The error against `volume_resolution` and `scatter_iterations` up to the converged series,
    /// and where the scattering grid's error lies (CPU only; isotropic scenes without a sky or
    /// ground).
    GridError(grid_error::GridErrorArgs),
    /// The scattering series against two-grid cycles of as many sweeps or fewer (CPU only; one
    /// cloud under a black sky, without a ground). The GPU's cycles: `accuracy --settings
    /// '(scatter_coarse_cycles: 2)'`.
    CoarseCycles(coarse_cycles::CoarseCyclesArgs),
    /// The sky map's error against its direction count and size (CPU references) and its cost
    /// for one cloud and a field of 100.
    SkyMap(sky_map::SkyMapArgs),
    /// How one scattering sweep carries a source's spatial detail (a Fourier mode) against the
    /// exact transport, per voxel optical depth (CPU only, no scene).
    SweepResponse,
    /// Cost at scale: against particles (3.1k–1.2M), clouds (1, 10, 100) and view size
    /// (720p–4K).
    Scale(scale::ScaleArgs),
    /// Only redraw DIR/scale.png from DIR/scale.csv.
    ReplotScale(replot::ReplotArgs),
}

/// `--frames`, for the subcommands that time frames.
#[derive(clap::Args, Debug)]
pub(crate) struct Frames {
    /// Measured frames per setting (medians are reported).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u64).range(1..))]
    frames: u64,
}

impl Frames {
    /// `--frames` as a count.
    pub(crate) fn count(&self) -> usize {
        self.frames as usize
    }
}

/// `--spp`, for the subcommands that compare with path-traced references.
#[derive(clap::Args, Debug)]
pub(crate) struct ReferenceSpp {
    /// Overrides every scene's reference samples per pixel.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub(crate) spp: Option<u32>,
}

/// `--font`, for the subcommands that draw a plot.
#[derive(clap::Args, Debug)]
pub(crate) struct PlotFont {
    /// The TTF font of the plot's labels.
    #[arg(long, default_value = DEFAULT_FONT)]
    pub(crate) font: PathBuf,
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

fn run() -> Result<(), String> {
    let Cli { out, mode } = Cli::parse();
    std::fs::create_dir_all(&out).map_err(|e| format!("cannot create {}: {e}", out.display()))?;
    let out = out.as_path();
    match &mode {
        Mode::Accuracy(args) => accuracy::accuracy_benchmark(args, out),
        Mode::Replot(args) => replot::replot(args, out),
        Mode::Decompose(args) => decompose::decompose_benchmark(args, out),
        Mode::Dense(args) => dense::dense_benchmark(args, out),
        Mode::Illumination(args) => illumination::illumination_benchmark(args, out),
        Mode::CloudTarget(args) => cloud_target_scale::cloud_target_benchmark(args, out),
        Mode::FrameBudget(args) => frame_budget::frame_budget_benchmark(args, out),
        Mode::RasterVsCompute(args) => raster_vs_compute::raster_vs_compute_benchmark(args, out),
        Mode::LineSweep(args) => line_sweep::line_sweep_benchmark(args, out),
        Mode::StillView(args) => still_view::still_view_benchmark(args, out),
        Mode::Voxelize(args) => voxelize::voxelize_benchmark(args, out),
        Mode::WarmStart(args) => warm_start::warm_start_benchmark(args, out),
        Mode::GridError(args) => grid_error::grid_error_benchmark(args, out),
        Mode::CoarseCycles(args) => coarse_cycles::coarse_cycles_benchmark(args, out),
        Mode::SkyMap(args) => sky_map::sky_map_benchmark(args, out),
        Mode::SweepResponse => write_report(out, "sweep_response.md", &sweep_response::table()),
        Mode::Scale(args) => scale::scale_benchmark(args, out),
        Mode::ReplotScale(args) => replot::replot_scale(args, out),
    }
}
