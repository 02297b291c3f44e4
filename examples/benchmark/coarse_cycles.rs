//! `coarse-cycles`: the scattering series against the same series accelerated by two-grid
//! cycles (`reference::illumination::scatter_coarse_cycles`, docs/illumination.md §4,
//! "Coarse-grid cycles"), at the same or fewer sweeps, against the path tracer. CPU references
//! only; the GPU's cycles are measured by `accuracy --settings '(scatter_coarse_cycles: 2)'`.

use std::{fmt::Write, path::Path};

use bevy::math::Vec3;

use bevy_particle_clouds::{
    CloudQualitySettings,
    image_io::LinearImage,
    reference::illumination::{CoarseCycles, illuminate_scene_cloud, scatter_coarse_cycles},
    reference::metrics::relative_rmse,
    scene::Scene,
    settings::COARSE_GRID_ORDERS,
};

use super::{
    BenchScene, Reference, ReferenceSpp, cloud_pixels, grid_error, named_scenes, parse_settings,
    write_report,
};

/// The options of `benchmark coarse-cycles`.
#[derive(clap::Args, Debug)]
pub(crate) struct CoarseCyclesArgs {
    /// Only these scenes (comma-separated names; default: `albedo_one`): one cloud under a black
    /// sky, without a ground.
    #[arg(long, value_delimiter = ',')]
    pub(crate) scenes: Option<Vec<String>>,
    /// The settings (RON, as a scene file's `settings`) of the series and the cycles, instead of
    /// each scene's own; only the first is used.
    #[arg(long = "settings", value_name = "RON", value_parser = parse_settings)]
    pub(crate) settings: Vec<CloudQualitySettings>,
    #[command(flatten)]
    pub(crate) reference: ReferenceSpp,
}

/// `benchmark coarse-cycles`: each chosen scene's (default `albedo_one`) error with the series
/// and with two-grid cycles; writes `DIR/coarse_cycles.md`.
pub(crate) fn coarse_cycles_benchmark(args: &CoarseCyclesArgs, out: &Path) -> Result<(), String> {
    let mut md = String::from(
        "# Coarse-grid cycles\n\nThe scattering series against two-grid cycles \
         (`cargo run --example benchmark -- coarse-cycles`; docs/illumination.md §4, \
         \"Coarse-grid cycles\"), computed with the f64 CPU references (the GPU's cycles: \
         `accuracy --settings '(scatter_coarse_cycles: 2)'`).\n",
    );
    for (bench, scene) in named_scenes(args.scenes.as_deref(), "albedo_one")? {
        // The CPU image (`grid_error::image`) is the cloud's alone, over black.
        if scene.clouds.len() != 1
            || scene.cloud_ground().is_some()
            || scene.background != Vec3::ZERO
        {
            return Err(format!(
                "`{}` has several clouds, a ground or a sky; coarse-cycles takes one cloud \
                 under a black sky",
                bench.name
            ));
        }
        let spp = args.reference.spp.unwrap_or(bench.spp);
        let reference = super::reference(&scene, bench, spp, out)?;
        let settings = args.settings.first().copied().unwrap_or(scene.settings);
        md.push_str(&coarse_cycles(bench, &scene, settings, &reference));
    }
    write_report(out, "coarse_cycles.md", &md)
}

/// Plain series of these many orders; the last is taken as converged.
const SERIES: [u32; 5] = [16, 32, 64, 128, CONVERGED];

/// Orders of the series taken as the grid's converged solution.
const CONVERGED: u32 = 400;

/// Two-grid schedules: fine orders, cycles, coarse orders. The first is the default
/// (`scatter_iterations` 8, `scatter_coarse_cycles` 2, [`COARSE_GRID_ORDERS`]); the next
/// sum fewer coarse orders per cycle.
const SCHEDULES: [(u32, u32, u32); 11] = [
    (8, 2, COARSE_GRID_ORDERS),
    (8, 2, 16),
    (8, 2, 8),
    (8, 3, 16),
    (8, 3, 8),
    (4, 3, 32),
    (4, 5, 32),
    (8, 5, 32),
    (4, 8, 32),
    (4, 5, 64),
    (4, 5, 8),
];

/// The markdown section of one scene (a single cloud, no ground) at `settings`.
pub(crate) fn coarse_cycles(
    bench: &BenchScene,
    scene: &Scene,
    settings: CloudQualitySettings,
    reference: &Reference,
) -> String {
    let n = settings.volume_resolution;
    let mut md = format!(
        "\n### {}\n\nReference: {} spp at {}×{} (noise {:.4}; {:.4} after a 4×4 box filter), \
         removed in quadrature. {n}³. Cost: sweeps of the {n}³ grid \
         (a sweep of the {}³ grid counts an eighth). \"From converged\": rel. RMSE against \
         the series of {CONVERGED} orders' image (the grid's own solution; no noise).\n\n\
         | scattering | sweeps | rel. RMSE | 4×4 box | energy / truth | from converged |\n\
         |---|---:|---:|---:|---:|---:|\n",
        bench.name,
        reference.spp,
        reference.width,
        reference.height,
        reference.noise,
        reference.noise_box4,
        n / 2,
    );
    // Each row's image, kept to compare with the converged series' once it is known.
    let mut rows: Vec<(String, f64, LinearImage)> = Vec::new();
    // The schedules replace only the multiple scattering, so they start from the last series'
    // illumination instead of solving the scene once more.
    let mut last = None;
    for m in SERIES {
        eprintln!("benchmark: {}: series of {m} orders (CPU)", bench.name);
        let s = CloudQualitySettings {
            scatter_iterations: m,
            scatter_coarse_cycles: 0,
            ..settings
        };
        let Some(ill) = illuminate_scene_cloud(scene, 0, &s) else {
            return format!("\n### {}\n\nNo cloud with density.\n", bench.name);
        };
        let image = grid_error::image(scene, &ill, &s, bench.error_downsample);
        rows.push((format!("series, {m} orders"), m as f64, image));
        last = Some(ill);
    }
    let Some(mut ill) = last else {
        return md;
    };
    for (fine_orders, cycles, coarse_orders) in SCHEDULES {
        let schedule = CoarseCycles {
            fine_orders,
            cycles,
            coarse_orders,
        };
        eprintln!("benchmark: {}: {schedule:?} (CPU)", bench.name);
        ill.multiple = scatter_coarse_cycles(
            &ill.grid,
            ill.k_local,
            (ill.albedo, ill.anisotropy),
            &ill.source,
            scene.background.as_dvec3(),
            schedule,
        );
        let label =
            format!("{fine_orders} orders, then {cycles} cycles of {coarse_orders} coarse orders");
        let image = grid_error::image(scene, &ill, &settings, bench.error_downsample);
        rows.push((label, schedule.fine_sweeps(), image));
    }
    let sky = scene.background;
    let converged = &rows[SERIES.len() - 1].2;
    for (label, sweeps, image) in &rows {
        let e = grid_error::errors(image, reference, sky);
        let from_converged = relative_rmse(
            &cloud_pixels(&image.pixels, &converged.pixels, sky),
            &cloud_pixels(&converged.pixels, &converged.pixels, sky),
        );
        let _ = writeln!(
            md,
            "| {label} | {sweeps:.1} | {:.4} | {:.4} | {:.4} | {from_converged:.4} |",
            e.rmse, e.boxed, e.energy
        );
    }
    md
}
