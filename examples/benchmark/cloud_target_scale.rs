//! `cloud-target`: the draw's cost and error at each `cloud_target_scale` (the paper's §4
//! fill-rate optimisation), at otherwise default settings.
//!
//! Cost: the draw's GPU time in a static frame (nothing else runs), and the static frame's wall
//! time, medians over [`ROUNDS`] rounds that visit every scale in turn (so that a slow drift of
//! the machine does not favour one scale). Error: the relative RMSE against the path tracer (at the scene's error resolution, the
//! reference's noise removed in quadrature), and against the full-size image at full resolution
//! (no noise, and no downsampling to hide the upsample's error in).

use super::*;

/// The scales measured: full size, half and a quarter per axis.
pub(crate) const SCALES: [f32; 3] = [1.0, 0.5, 0.25];

/// Rounds of static frames per scale, interleaved over the scales.
const ROUNDS: usize = 4;

/// The scenes measured unless `--scenes` names others: the paper's 640×480 scenes.
const DEFAULT_SCENES: [&str; 3] = ["paper_3100", "paper_38k_1light", "paper_38k_5lights"];

struct ScaleRow {
    scene: &'static str,
    scale: f32,
    draw_ms: f64,
    static_wall_ms: f64,
    rel_rmse: f64,
    reference_noise: f64,
    reference_spp: u32,
    against_full: f64,
}

/// The options of `benchmark cloud-target`.
#[derive(clap::Args, Debug)]
pub(crate) struct CloudTargetArgs {
    /// Only these scenes (comma-separated names; default: the paper's three 640×480 scenes).
    #[arg(long, value_delimiter = ',')]
    pub(crate) scenes: Option<Vec<String>>,
    #[command(flatten)]
    pub(crate) reference: ReferenceSpp,
    #[command(flatten)]
    pub(crate) frames: Frames,
}

pub(crate) fn cloud_target_benchmark(args: &CloudTargetArgs, out: &Path) -> Result<(), String> {
    let mut rows = Vec::new();
    let mut adapter = String::new();
    for bench in chosen_scenes(args.scenes.as_deref(), &DEFAULT_SCENES) {
        let scene = load_scene(bench)?;
        let reference = reference(&scene, bench, args.reference.spp.unwrap_or(bench.spp), out)?;
        let reference_image = reference.image.clone();
        let mut b = Bench::new(&scene);
        adapter = b.adapter.clone();
        let quality = |scale| CloudQualitySettings {
            cloud_target_scale: scale,
            ..default()
        };
        let mut full: Option<LinearImage> = None;
        let mut images = Vec::new();
        let mut scene_rows = Vec::new();
        for scale in SCALES {
            b.set_quality(quality(scale));
            let image = b.image();
            let against_full = full.as_ref().map_or(0.0, |f| {
                relative_rmse(&opaque(&image).pixels, &opaque(f).pixels)
            });
            let small = downsample(&image, bench.error_downsample);
            images.push(opaque(&image));
            full.get_or_insert(image);
            scene_rows.push(ScaleRow {
                scene: bench.name,
                scale,
                draw_ms: 0.0,
                static_wall_ms: 0.0,
                rel_rmse: relative_rmse(&small.pixels, &reference_image),
                reference_noise: reference.noise,
                reference_spp: reference.spp,
                against_full,
            });
        }
        let _ = write_png(
            &side_by_side_all(&images),
            &out.join(format!("{}-cloud-target.png", bench.name)),
        );
        let mut times = vec![(Vec::new(), Vec::new()); SCALES.len()];
        for _ in 0..ROUNDS {
            for (i, scale) in SCALES.into_iter().enumerate() {
                b.set_quality(quality(scale));
                let (draw, wall) = b.static_frames(args.frames.count());
                times[i].0.extend(draw);
                times[i].1.extend(wall);
            }
        }
        for (row, (draw, wall)) in scene_rows.iter_mut().zip(times) {
            row.draw_ms = median(draw);
            row.static_wall_ms = median(wall);
            eprintln!(
                "benchmark: {} scale {}: draw GPU {:.2} ms, static frame wall {:.1} ms; rel. RMSE {:.4} (denoised {:.4}), against full size {:.4}",
                row.scene,
                row.scale,
                row.draw_ms,
                row.static_wall_ms,
                row.rel_rmse,
                denoised(row.rel_rmse, row.reference_noise),
                row.against_full
            );
        }
        rows.extend(scene_rows);
    }
    let table = table(&adapter, &rows, args.frames.count());
    let md_path = out.join("cloud_target.md");
    std::fs::write(&md_path, &table)
        .map_err(|e| format!("cannot write {}: {e}", md_path.display()))?;
    println!("{table}");
    eprintln!("benchmark: wrote {}", md_path.display());
    Ok(())
}

/// Images of one size side by side, left to right.
fn side_by_side_all(images: &[LinearImage]) -> LinearImage {
    let (w, h) = (images[0].width, images[0].height);
    let mut out = LinearImage::new(w * images.len() as u32, h);
    for (i, image) in images.iter().enumerate() {
        for y in 0..h {
            for x in 0..w {
                *out.pixel_mut(i as u32 * w + x, y) = image.pixel(x, y);
            }
        }
    }
    out
}

/// The image with alpha 1 (the metrics compare RGB).
fn opaque(image: &LinearImage) -> LinearImage {
    let mut shown = image.clone();
    shown.pixels.iter_mut().for_each(|p| p[3] = 1.0);
    shown
}

fn table(adapter: &str, rows: &[ScaleRow], frames: usize) -> String {
    let mut md = format!(
        "Adapter: `{adapter}`. Default settings but `cloud_target_scale`. Draw: GPU time of the \
         draw in a static frame (the transparent pass at full size; the cloud target's draw and \
         composite below it), median of {ROUNDS} rounds of {frames} frames visiting the scales in \
         turn, and its ratio to the full-size draw of \
         the same run. Static frame: its wall time, Bevy's per-frame work included. Error: \
         relative RMSE against the path tracer at the scene's error resolution, with the \
         reference's noise removed in quadrature, and against the full-size image at full \
         resolution.\n\n\
         | scene | scale | draw (ms) | draw / full size | static frame wall (ms) | rel. RMSE vs path tracer (denoised) | added | reference spp (noise) | rel. RMSE vs full size |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    );
    for row in rows {
        let full = rows
            .iter()
            .find(|r| r.scene == row.scene && r.scale == 1.0)
            .expect("the full-size row comes first");
        let error = denoised(row.rel_rmse, row.reference_noise);
        let _ = writeln!(
            md,
            "| {} | {} | {:.2} | {:.2} | {:.0} | {:.4} | {:+.4} | {} ({:.4}) | {:.4} |",
            row.scene,
            row.scale,
            row.draw_ms,
            row.draw_ms / full.draw_ms,
            row.static_wall_ms,
            error,
            error - denoised(full.rel_rmse, full.reference_noise),
            row.reference_spp,
            row.reference_noise,
            row.against_full
        );
    }
    md
}
