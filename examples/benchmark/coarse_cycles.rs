//! `--coarse-cycles`: the scattering series against the same series accelerated by two-grid
//! cycles (`reference::illumination::scatter_coarse_cycles`, docs/illumination.md §4,
//! "Coarse-grid cycles"), at the same or fewer sweeps, against the path tracer. CPU references
//! only; the GPU's cycles are measured by the sweep (`--settings '(scatter_coarse_cycles: 2)'`).

use std::fmt::Write;

use bevy_particle_clouds::{
    CloudQualitySettings,
    reference::illumination::{
        CloudIllumination, CoarseCycles, illuminate_scene_cloud, scatter_coarse_cycles,
    },
    scene::Scene,
};

use super::{BenchScene, Reference, grid_error};

/// Plain series of these many orders.
const SERIES: [u32; 5] = [16, 32, 64, 128, 400];

/// Two-grid schedules: fine orders, cycles, coarse orders.
const SCHEDULES: [(u32, u32, u32); 5] =
    [(4, 3, 32), (4, 5, 32), (8, 5, 32), (4, 8, 32), (4, 5, 64)];

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
         (a sweep of the {}³ grid counts an eighth).\n\n\
         | scattering | sweeps | rel. RMSE | 4×4 box | energy / truth |\n\
         |---|---:|---:|---:|---:|\n",
        bench.name,
        reference.spp,
        reference.width,
        reference.height,
        reference.noise,
        reference.noise_box4,
        n / 2,
    );
    let row = |md: &mut String,
               label: String,
               sweeps: f64,
               s: &CloudQualitySettings,
               ill: &CloudIllumination| {
        let e = grid_error::errors(
            &grid_error::image(scene, ill, s, bench.error_downsample),
            reference,
            scene.background,
        );
        let _ = writeln!(
            md,
            "| {label} | {sweeps:.0} | {:.4} | {:.4} | {:.4} |",
            e.rmse, e.boxed, e.energy
        );
    };
    for m in SERIES {
        eprintln!("benchmark: {}: series of {m} orders (CPU)", bench.name);
        let s = CloudQualitySettings {
            scatter_iterations: m,
            ..settings
        };
        let Some(ill) = illuminate_scene_cloud(scene, 0, &s) else {
            return format!("\n### {}\n\nNo cloud with density.\n", bench.name);
        };
        row(&mut md, format!("series, {m} orders"), m as f64, &s, &ill);
    }
    let Some(mut ill) = illuminate_scene_cloud(scene, 0, &settings) else {
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
        row(&mut md, label, schedule.fine_sweeps(), &settings, &ill);
    }
    md
}
