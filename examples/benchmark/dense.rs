//! `dense`: how media far denser than the fine grid resolves go dark. One ball of particles at
//! rising extinction, the real-time image (the GPU, at the default settings) against the path
//! tracer's, beside each case's optical thickness across one fine voxel, `τ_h = σ_t ρ h`.
//!
//! The light volumes hold the optical depth at voxel centres: where one voxel is optically
//! thick, its lit skin, which carries almost all the light a dense medium scatters, is read as
//! if it lay at the centre, and darkens. This measures where that starts, for the warning the
//! renderer gives (`DENSE_VOXEL_LIMIT`).

use super::*;
use bevy_particle_clouds::render::plan::params::DENSE_VOXEL_LIMIT;

/// Particles in the ball.
const PARTICLES: usize = 400;
/// Their radius, metres (the ball's is 1 m).
const RADIUS: f32 = 0.25;
/// Extinctions of the medium, 1/m at density 1.
const EXTINCTIONS: [f32; 10] = [3.0, 10.0, 30.0, 100.0, 200.0, 300.0, 1e3, 1e4, 1e5, 1e6];

/// The options of `benchmark dense`.
#[derive(clap::Args, Debug)]
pub(crate) struct DenseArgs {
    /// Path-traced samples per pixel.
    #[arg(long, default_value_t = 64)]
    spp: u32,
}

/// A 64×64 view of the ball at `extinction`, lit from the side.
fn scene(extinction: f32) -> Scene {
    let mut rng = SplitMix64::new(11);
    let particles = (0..PARTICLES)
        .map(|_| {
            // Uniform in the ball of radius 1 - RADIUS, by rejection.
            let position = loop {
                let p = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0 - 1.0;
                if p.length_squared() <= 1.0 {
                    break p * (1.0 - RADIUS);
                }
            };
            Particle {
                position,
                radius: RADIUS,
                density: 1.0,
            }
        })
        .collect();
    let medium = bevy_particle_clouds::Medium {
        extinction,
        albedo: 0.9,
        ..Default::default()
    };
    let light = Vec3::new(-1.0, -0.4, -0.3);
    let settings = CloudQualitySettings::default();
    super::voxelize::one_cloud_scene(4.0, 35.0, light, medium, particles, settings)
}

/// The summed density's largest value at a particle's centre (the particles' own peak is 1).
fn peak_density(particles: &[Particle]) -> f32 {
    particles
        .iter()
        .map(|a| {
            particles
                .iter()
                .map(|b| {
                    let u2 = a.position.distance_squared(b.position) / (b.radius * b.radius);
                    b.density * (1.0 - u2).max(0.0).powi(2)
                })
                .sum::<f32>()
        })
        .fold(0.0, f32::max)
}

/// Mean of the pixels' RGB.
fn mean(pixels: &[[f32; 4]]) -> f64 {
    let sum: f64 = pixels
        .iter()
        .map(|p| (p[0] + p[1] + p[2]) as f64 / 3.0)
        .sum();
    sum / pixels.len().max(1) as f64
}

pub(crate) fn dense_benchmark(args: &DenseArgs, out: &Path) -> Result<(), String> {
    let settings = CloudQualitySettings::default();
    let m = settings.light_resolution() as f32;
    let first = scene(EXTINCTIONS[0]);
    let peak = peak_density(&first.clouds[0].particles);
    // The cloud's cube: the particles' extent, as the renderer fits it (side / m per voxel).
    let side = 2.0;
    let h = side / m;
    let mut table = format!(
        "{PARTICLES} particles of radius {RADIUS} m and density 1 in a ball of 1 m, albedo 0.9, one \
         light from the side, 64×64, default settings (fine grid {m}³, h ≈ {h:.4} m). Real-time: \
         the GPU; truth: the path tracer at {} spp. `τ_h`: optical thickness across one fine \
         voxel at a particle's own peak (σ_t h), and at the summed density's peak ({peak:.2}).\n\n\
         | σ_t, 1/m | τ_h, particle peak | τ_h, summed peak | mean radiance: real-time / truth | rel. RMSE |\n\
         |---:|---:|---:|---:|---:|\n",
        args.spp
    );
    let mut adapter = String::new();
    for extinction in EXTINCTIONS {
        let scene = scene(extinction);
        let mut bench = Bench::new(&scene);
        adapter.clone_from(&bench.adapter);
        let (image, _) = bench.measure(1);
        drop(bench);
        let (bar, progress) =
            path_tracing_progress(&format!("σ_t {extinction}"), scene.camera.height);
        let truth = path_tracer::render(
            &scene,
            &PathTracerSettings {
                samples_per_pixel: args.spp,
                seed: 1,
                progress: Some(progress),
                time_limit: None,
            },
        );
        bar.finish_and_clear();
        let ratio = mean(&image.pixels) / mean(&truth).max(f64::MIN_POSITIVE);
        let error = relative_rmse(&image.pixels, &truth);
        eprintln!("benchmark: dense, σ_t {extinction}: real-time / truth {ratio:.3}");
        let _ = writeln!(
            table,
            "| {extinction} | {:.3} | {:.3} | {ratio:.3} | {error:.3} |",
            extinction * h,
            extinction * peak * h
        );
    }
    let _ = write!(
        table,
        "\nThe renderer warns where `τ_h` at the densest particle's peak exceeds \
         `DENSE_VOXEL_LIMIT` = {DENSE_VOXEL_LIMIT}.\n"
    );
    table.insert_str(0, &format!("Adapter: `{adapter}`. "));
    write_report(out, "dense.md", &table)?;
    println!("{table}");
    Ok(())
}
