//! `warm-start`: the scattering's warm restart under a moving sun (`warm_scatter_iterations`,
//! docs/illumination.md §4), against the path tracer.
//!
//! Each scene's lights are first turned by `Δ` about the vertical and the scene is rendered until
//! steady (the full solve there); then the lights are turned back to the scene's, and the next
//! frame restarts the scattering warm from the turned solution. That frame's image is compared
//! with the scene's path-traced reference (the reference's noise removed in quadrature), beside
//! the image of the full solve that settles it one frame later; and its scatter GPU time beside
//! that of the full solve at the turned lights.

use super::*;

/// Sun steps between two solves, degrees.
const STEPS: [f32; 3] = [1.0, 5.0, 20.0];
/// Warm iterations measured.
const ITERATIONS: [u32; 3] = [2, 4, 8];
/// The scenes measured unless `--scenes` names others: one sun each.
const DEFAULT_SCENES: [&str; 2] = ["cumulus", "paper_38k_1light"];

struct WarmRow {
    scene: &'static str,
    step: f32,
    iterations: u32,
    warm_ms: Option<f64>,
    full_ms: Option<f64>,
    warm_error: f64,
    full_error: f64,
    against_full: f64,
    reference_noise: f64,
    reference_spp: u32,
}

/// The GPU scatter time of the first frame from `first` on whose scattering ran.
fn scatter_ms(b: &Bench, first: usize) -> Option<f64> {
    b.recorder.frames[first..]
        .iter()
        .find(|f| f.runs(CloudPass::Scatter) > 0)
        .and_then(|f| f.gpu_ms.get(&CloudPass::Scatter).copied())
}

/// The options of `benchmark warm-start`.
#[derive(clap::Args, Debug)]
pub(crate) struct WarmStartArgs {
    /// Only these scenes (comma-separated names; default: `cumulus`, `paper_38k_1light`).
    #[arg(long, value_delimiter = ',')]
    pub(crate) scenes: Option<Vec<String>>,
    #[command(flatten)]
    pub(crate) reference: ReferenceSpp,
}

pub(crate) fn warm_start_benchmark(args: &WarmStartArgs, out: &Path) -> Result<(), String> {
    let mut rows = Vec::new();
    let mut adapter = String::new();
    for bench in chosen_scenes(args.scenes.as_deref(), &DEFAULT_SCENES) {
        let scene = load_scene(bench)?;
        let reference = reference(&scene, bench, args.reference.spp.unwrap_or(bench.spp), out)?;
        let error = |image: &LinearImage| {
            let small = downsample(image, bench.error_downsample);
            denoised(
                relative_rmse(&small.pixels, &reference.image),
                reference.noise,
            )
        };
        for step in STEPS {
            for iterations in ITERATIONS {
                eprintln!(
                    "benchmark: {}: sun step {step}°, {iterations} warm iterations",
                    bench.name
                );
                let mut b = Bench::new(&scene);
                adapter = b.adapter.clone();
                b.set_quality(CloudQualitySettings {
                    warm_scatter_iterations: iterations,
                    ..default()
                });
                b.turn_lights(step);
                b.image();
                b.turn_lights(-step);
                let warm_frame = b.recorder.frames.len();
                let warm = headless::capture(&mut b.app, &mut b.recorder, &b.target.image)
                    .map_err(|e| e.to_string())?;
                let full = b.image();
                for _ in 0..4 {
                    b.recorder.drain(&mut b.app).map_err(|e| e.to_string())?; // late timestamps
                }
                let row = WarmRow {
                    scene: bench.name,
                    step,
                    iterations,
                    warm_ms: scatter_ms(&b, warm_frame),
                    // The full solve at the turned lights, the bench's first scattering.
                    full_ms: scatter_ms(&b, 0),
                    warm_error: error(&warm),
                    full_error: error(&full),
                    against_full: relative_rmse(&warm.pixels, &full.pixels),
                    reference_noise: reference.noise,
                    reference_spp: reference.spp,
                };
                eprintln!(
                    "benchmark: {}: warm rel. RMSE {:.4} (full {:.4}, warm vs full {:.4}); scatter {:?} ms vs {:?} ms",
                    row.scene,
                    row.warm_error,
                    row.full_error,
                    row.against_full,
                    row.warm_ms,
                    row.full_ms
                );
                rows.push(row);
            }
        }
    }
    let table = table(&adapter, &rows);
    let path = out.join("warm_start.md");
    std::fs::write(&path, &table).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    println!("{table}");
    eprintln!("benchmark: wrote {}", path.display());
    Ok(())
}

fn table(adapter: &str, rows: &[WarmRow]) -> String {
    let ms = |v: Option<f64>| v.map_or("n/a".to_string(), |v| format!("{v:.1}"));
    let mut md = format!(
        "Adapter: `{adapter}`. Default settings (32 iterations) but `warm_scatter_iterations`. The \
         scene's lights were turned by the step about the vertical, solved in full, and turned \
         back: the warm frame restarts from that solution, the next frame settles it with the \
         full series. Error: relative RMSE against the path tracer at the scene's error \
         resolution, the reference's noise removed in quadrature; warm vs full: between the two \
         images at full resolution. Scatter: the pass's GPU time in the warm frame, and in the \
         full solve at the turned lights.\n\n\
         | scene | sun step | warm iterations | rel. RMSE warm | rel. RMSE full | added | warm vs full | scatter warm (ms) | scatter full (ms) | reference spp (noise) |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    );
    for r in rows {
        let _ = writeln!(
            md,
            "| {} | {}° | {} | {:.4} | {:.4} | {:+.4} | {:.4} | {} | {} | {} ({:.4}) |",
            r.scene,
            r.step,
            r.iterations,
            r.warm_error,
            r.full_error,
            r.warm_error - r.full_error,
            r.against_full,
            ms(r.warm_ms),
            ms(r.full_ms),
            r.reference_spp,
            r.reference_noise
        );
    }
    md
}
