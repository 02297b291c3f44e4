//! `scale`: cost at game scale, in three sweeps (issue #11):
//!
//! - **particles**: one cumulus of 3,100, 38,000, 300,000 and 1,200,000 particles (radii
//!   `∝ count^(-1/3)`) at default settings, 640×360;
//! - **clouds**: the same 38,400 particles (100 puffs of 384) as 1, 10 and 100 clouds, at
//!   [`cloud_sweep_settings`], 1280×720, and the 100 clouds again with level of detail on;
//! - **view size**: the 38,000-particle cumulus at 1280×720, 1920×1080 and 3840×2160.
//!
//! On lavapipe (a 2-core CPU) the draw's fill dominates, so the particle sweep is at 640×360 and
//! the cloud 80 m away (about a third of the view's height).
//!
//! Each configuration: every pass's GPU time in frames that rerun every pass (the particles
//! touched), the static frame's draw, wall times, and how many times each pass ran in a re-lit
//! frame. Writes `DIR/scale.csv`, `DIR/scale.md` and `DIR/scale.png` (`plot.rs` draws it;
//! `benchmark replot-scale` redraws it from the CSV). `--draw-methods compute` draws every
//! configuration by compute (the last method named is the one used).

use std::fmt::Write as _;

use bevy_particle_clouds::{LightSample, Medium, scene::ResolvedCloud};

use super::*;

/// The cloud sweep's knobs, the defaults but 16³ × 8 iterations (then the default coarse-grid
/// cycles): 100 clouds at the default 48³ would take minutes a frame on lavapipe.
fn cloud_sweep_settings() -> CloudQualitySettings {
    CloudQualitySettings {
        volume_resolution: 16,
        scatter_iterations: 8,
        ..default()
    }
}

/// One measured configuration.
pub(crate) struct ScaleRow {
    pub(crate) sweep: &'static str,
    pub(crate) label: String,
    /// Particles, clouds or view pixels.
    pub(crate) x: f64,
    pub(crate) timing: Timing,
    /// Runs of each pass in a frame that re-lights everything.
    pub(crate) runs: [u32; PASSES],
    /// Compute dispatches of each pass in that frame.
    pub(crate) dispatches: [u32; PASSES],
}

fn camera(distance: f32, width: u32, height: u32) -> bevy_particle_clouds::scene::SceneCamera {
    bevy_particle_clouds::scene::SceneCamera {
        position: Vec3::new(0.0, 0.3 * distance, distance),
        look_at: Vec3::ZERO,
        up: Vec3::Y,
        vertical_fov_degrees: 40.0,
        width,
        height,
    }
}

fn scene(
    clouds: Vec<ResolvedCloud>,
    distance: f32,
    (width, height): (u32, u32),
    settings: CloudQualitySettings,
) -> Scene {
    Scene {
        camera: camera(distance, width, height),
        background: Vec3::new(0.2, 0.35, 0.6),
        lights: vec![LightSample {
            direction: Vec3::new(-0.6, -0.7, -0.4).normalize(),
            irradiance: Vec3::new(3.0, 2.9, 2.7),
        }],
        clouds,
        objects: Vec::new(),
        fog: None,
        shadow_map_resolution: bevy_particle_clouds::scene::DEFAULT_SHADOW_MAP_RESOLUTION,
        settings,
    }
}

/// A 20 m cumulus of `count` particles whose radii shrink as `count^(-1/3)` from the paper's
/// 3,100-particle cloud's, so that the particles fill the same volume whatever `count` (and the
/// draw's fill grows only as `count^(1/3)`).
fn cumulus(count: usize) -> ResolvedCloud {
    let shrink = (3_100.0 / count as f32).cbrt();
    let particles = generators::cumulus_with_puffs(20.0, count, 11, |size, core| {
        size * (0.07 + 0.06 * core) * shrink
    });
    ResolvedCloud {
        translation: Vec3::ZERO,
        medium: Medium {
            extinction: 2.0,
            albedo: 0.95,
            ..Default::default()
        },
        particles: particles.particles,
    }
}

/// 100 puffs of 384 particles on a 10 × 10 grid 12 m apart, grouped into `clouds` clouds of
/// whole puffs (each cloud's particles in its own local frame around its first puff).
fn puffs(clouds: usize) -> Vec<ResolvedCloud> {
    let per = 100 / clouds;
    (0..clouds)
        .map(|c| {
            let origin = puff_centre(c * per);
            let particles = (c * per..(c + 1) * per)
                .flat_map(|p| {
                    let offset = puff_centre(p) - origin;
                    generators::cumulus(8.0, 384, 500 + p as u64)
                        .particles
                        .into_iter()
                        .map(move |mut q| {
                            q.position += offset;
                            q
                        })
                })
                .collect();
            ResolvedCloud {
                translation: origin,
                medium: Medium {
                    extinction: 2.5,
                    albedo: 0.95,
                    ..Default::default()
                },
                particles,
            }
        })
        .collect()
}

fn puff_centre(p: usize) -> Vec3 {
    Vec3::new((p % 10) as f32 - 4.5, 0.0, (p / 10) as f32 - 4.5) * 12.0
}

fn measure(
    scene: &Scene,
    lod: Option<f32>,
    frames: usize,
    adapter: &mut String,
) -> (Timing, [u32; PASSES], [u32; PASSES]) {
    let mut b = Bench::new(scene);
    *adapter = b.adapter.clone();
    if let Some(pixels_per_voxel) = lod {
        b.set_level_of_detail(pixels_per_voxel, 8);
    }
    let (_, timing) = b.measure(frames);
    let (runs, dispatches) = b.relit_counts();
    (timing, runs, dispatches)
}

/// The options of `benchmark scale`.
#[derive(clap::Args, Debug)]
pub(crate) struct ScaleArgs {
    /// Only these sweeps (comma-separated: `particles`, `clouds`, `view`; default: all three).
    #[arg(long, value_delimiter = ',')]
    pub(crate) scenes: Option<Vec<String>>,
    /// How the billboards are drawn (`raster`, `compute`; comma-separated, the last one named is
    /// used).
    #[arg(long, value_delimiter = ',', default_value = "raster", value_parser = parse_draw_method)]
    pub(crate) draw_methods: Vec<DrawMethod>,
    #[command(flatten)]
    pub(crate) frames: Frames,
    #[command(flatten)]
    pub(crate) plot: PlotFont,
}

pub(crate) fn scale_benchmark(args: &ScaleArgs, out: &Path) -> Result<(), String> {
    let frames = args.frames.count();
    let mut adapter = String::new();
    let mut rows = Vec::new();
    // `--scenes` names the sweeps to run (`particles`, `clouds`, `view`); all by default.
    let wanted = |sweep: &str| {
        args.scenes
            .as_ref()
            .is_none_or(|names| names.iter().any(|n| sweep.starts_with(n.as_str())))
    };
    let method = *args.draw_methods.last().unwrap_or(&DrawMethod::Raster);
    let mut run =
        |sweep: &'static str, label: String, x: f64, mut scene: Scene, lod: Option<f32>| {
            if !wanted(sweep) {
                return Ok(());
            }
            scene.settings.draw_method = method;
            eprintln!("benchmark: scale, {sweep}: {label}");
            let (timing, runs, dispatches) = measure(&scene, lod, frames, &mut adapter);
            eprintln!(
                "benchmark: scale, {sweep}: {label}: GPU {:.1} ms (static {:.1}), wall {:.0} ms",
                timing.gpu_ms_total, timing.gpu_ms_static, timing.wall_ms
            );
            rows.push(ScaleRow {
                sweep,
                label,
                x,
                timing,
                runs,
                dispatches,
            });
            // After each configuration, so that a sweep stopped part-way (4K frames take minutes
            // on llvmpipe) keeps the rows it measured.
            write_tables(args, out, &adapter, method, &rows).map(drop)
        };
    let hd = (1280, 720);
    for count in [3_100, 38_000, 300_000, 1_200_000] {
        let s = scene(vec![cumulus(count)], 80.0, (640, 360), default());
        run(
            "particles",
            format!("{count} particles"),
            count as f64,
            s,
            None,
        )?;
    }
    for clouds in [1, 10, 100] {
        let s = scene(puffs(clouds), 170.0, hd, cloud_sweep_settings());
        run("clouds", format!("{clouds} clouds"), clouds as f64, s, None)?;
    }
    let s = scene(puffs(100), 170.0, hd, cloud_sweep_settings());
    run(
        "clouds, level of detail",
        "100 clouds, 2 pixels per voxel".into(),
        100.0,
        s,
        Some(2.0),
    )?;
    for (w, h) in [(1280, 720), (1920, 1080), (3840, 2160)] {
        let s = scene(vec![cumulus(38_000)], 80.0, (w, h), default());
        run("view", format!("{w}×{h}"), (w * h) as f64, s, None)?;
    }
    write_scale(args, out, &adapter, method, &rows)
}

/// Writes the sweep's tables, `scale.csv` and `scale.md`, then draws `scale.png`.
fn write_scale(
    args: &ScaleArgs,
    out: &Path,
    adapter: &str,
    method: DrawMethod,
    rows: &[ScaleRow],
) -> Result<(), String> {
    let md = write_tables(args, out, adapter, method, rows)?;
    let title = format!("{adapter}, drawn by {method:?}");
    plot_scale(&out.join("scale.png"), &args.plot.font, &title, rows)?;
    println!("{md}");
    eprintln!(
        "benchmark: wrote scale.csv, scale.md and scale.png in {}",
        out.display()
    );
    Ok(())
}

/// Writes `rows` as `scale.csv` and `scale.md` in the output folder; returns the Markdown.
fn write_tables(
    args: &ScaleArgs,
    out: &Path,
    adapter: &str,
    method: DrawMethod,
    rows: &[ScaleRow],
) -> Result<String, String> {
    let names: Vec<&str> = CloudPass::ALL.iter().map(|p| p.name()).collect();
    let mut csv = format!(
        "adapter,draw_method,sweep,label,x,{},gpu_ms_total,gpu_ms_static,wall_ms,wall_ms_static,{},{}\n",
        columns(&names, "gpu_ms"),
        columns(&names, "runs"),
        columns(&names, "dispatches"),
    );
    let mut md = format!(
        "Adapter: `{adapter}`. GPU ms per pass: median of {} frames that rerun every pass (the \
         particles touched); draw: a static frame's. Runs: how many times each pass ran in a \
         re-lit frame (per cloud, per light, per scattering iteration, per view); dispatches: the \
         compute dispatches of that frame (voxelize, shade, gather and scatter batch every cloud of \
         a volume shape). Particles: 640×360, radii ∝ count^(-1/3); clouds sweep: `volume_resolution` 16, \
         8 iterations; the others: default settings. Drawn by {method:?} (`draw_method`).\n\n\
         | sweep | configuration | voxelize | shade | gather | scatter | sort + view volume | draw (static) | GPU total | wall | static wall | pass runs | dispatches |\n\
         |---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
        args.frames.count()
    );
    for r in rows {
        let p = &r.timing.pass_ms;
        let _ = writeln!(
            csv,
            "\"{adapter}\",{method:?},\"{}\",\"{}\",{},{},{:.4},{:.4},{:.3},{:.3},{},{}",
            r.sweep,
            r.label,
            r.x,
            p.iter()
                .map(|v| format!("{v:.4}"))
                .collect::<Vec<_>>()
                .join(","),
            r.timing.gpu_ms_total,
            r.timing.gpu_ms_static,
            r.timing.wall_ms,
            r.timing.wall_ms_static,
            joined(&r.runs),
            joined(&r.dispatches),
        );
        let _ = writeln!(
            md,
            "| {} | {} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.0} | {:.0} | {} | {} |",
            r.sweep,
            r.label,
            p[0],
            p[1],
            p[2],
            p[3],
            p[4] + p[5],
            p[6],
            r.timing.gpu_ms_total,
            r.timing.wall_ms,
            r.timing.wall_ms_static,
            r.runs.iter().sum::<u32>(),
            r.dispatches.iter().sum::<u32>()
        );
    }
    for (path, text) in [("scale.csv", &csv), ("scale.md", &md)] {
        let path = out.join(path);
        std::fs::write(&path, text).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    }
    Ok(md)
}

/// `prefix_voxelize,prefix_shade,…`: one CSV column per pass.
fn columns(names: &[&str], prefix: &str) -> String {
    names
        .iter()
        .map(|n| format!("{prefix}_{n}"))
        .collect::<Vec<_>>()
        .join(",")
}

/// Counts as CSV fields.
fn joined(counts: &[u32]) -> String {
    counts
        .iter()
        .map(u32::to_string)
        .collect::<Vec<_>>()
        .join(",")
}
