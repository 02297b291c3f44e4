//! `grid-error`: where the multiple-scattering grid's error against the path tracer lies, with
//! the f64 CPU references of the real-time passes (which the GPU matches; no adapter needed).
//!
//! - the error at several `volume_resolution`s and `scatter_iterations`, up to the converged
//!   series: does raising either knob bring the image closer to the truth?
//! - the image's energy per block of pixels, real-time over truth, for the converged series: where
//!   the grid puts too much light, and too little;
//! - a coarse grid reading a finer grid's solution, averaged onto it by density, and sweeping
//!   from the finer grid's single scattering or through its density: which of the coarse grid's
//!   representation, source, density or sweep holds its error.

use std::{fmt::Write, path::Path};

use bevy::math::{DVec3, Vec3};
use bevy_particle_clouds::{
    CloudQualitySettings, ScatterStencil,
    image_io::LinearImage,
    reference::{
        illumination::{
            CloudIllumination, DensityGrid, Moments, illuminate_scene_cloud, restrict_by_density,
            scatter,
        },
        metrics::relative_rmse,
    },
    scene::Scene,
};

use super::{
    BenchScene, Reference, ReferenceSpp, cloud_pixels,
    decompose::{billboards, energy},
    denoised, downsample, named_scenes, write_report,
};

/// The options of `benchmark grid-error`.
#[derive(clap::Args, Debug)]
pub(crate) struct GridErrorArgs {
    /// Only these scenes (comma-separated names; default: `albedo_one`): isotropic clouds under a
    /// black sky, without a ground.
    #[arg(long, value_delimiter = ',')]
    pub(crate) scenes: Option<Vec<String>>,
    #[command(flatten)]
    pub(crate) reference: ReferenceSpp,
}

/// `benchmark grid-error`: each chosen scene's (default `albedo_one`) error against the grid's
/// knobs; writes `DIR/grid_error.md`.
pub(crate) fn grid_error_benchmark(args: &GridErrorArgs, out: &Path) -> Result<(), String> {
    let mut md = String::from(
        "The scattering grid's error against the path tracer (`cargo run --example benchmark -- \
         grid-error`), computed with the f64 CPU references of the real-time passes (which the \
         GPU matches).\n",
    );
    for (bench, scene) in named_scenes(args.scenes.as_deref(), "albedo_one")? {
        let name = bench.name;
        let isotropic = scene.clouds.iter().all(|c| c.medium.anisotropy == 0.0);
        if !isotropic || scene.background != Vec3::ZERO || scene.cloud_ground().is_some() {
            return Err(format!(
                "`{name}` has an anisotropic medium, a sky or a ground; grid-error takes \
                 isotropic clouds under a black sky"
            ));
        }
        let spp = args.reference.spp.unwrap_or(bench.spp);
        let reference = super::reference(&scene, bench, spp, out)?;
        md.push_str(&grid_error(bench, &scene, &reference));
    }
    write_report(out, "grid_error.md", &md)
}

/// `(volume_resolution, scatter_iterations)` of the first table.
const GRIDS: [(u32, u32); 9] = [
    (32, 400),
    (48, 32),
    (48, 64),
    (48, 128),
    (48, 400),
    (64, 32),
    (64, 64),
    (64, 128),
    (64, 400),
];

/// Of those, the ones whose energy is shown block by block.
const BLOCKS_OF: [(u32, u32); 3] = [(48, 64), (48, 400), (64, 400)];

/// The block grid over the error-resolution image (columns, rows).
const BLOCKS: (u32, u32) = (8, 6);

/// The coarse and fine grids of the last table, and their iterations.
const COARSE_FINE: (u32, u32, u32) = (32, 64, 200);

fn settings(n: u32, m: u32) -> CloudQualitySettings {
    CloudQualitySettings {
        volume_resolution: n,
        scatter_iterations: m,
        ..CloudQualitySettings::default()
    }
}

/// The real-time image (CPU reference) of cloud 0 lit as `ill`, at the reference's resolution.
pub(crate) fn image(
    scene: &Scene,
    ill: &CloudIllumination,
    s: &CloudQualitySettings,
    factor: u32,
) -> LinearImage {
    let camera = (scene.camera.position - scene.clouds[0].translation).as_dvec3();
    let seen = ill.seen_from(camera, s.compositing);
    billboards(
        scene,
        &|x, ray| seen.scattered_at(x, ray),
        s,
        &ill.fine,
        factor,
    )
}

/// Errors of one image: relative RMSE and after a 4×4 box (the reference's noise removed from
/// both), and its energy over the truth's.
pub(crate) struct Errors {
    pub(crate) rmse: f64,
    pub(crate) boxed: f64,
    pub(crate) energy: f64,
}

pub(crate) fn errors(image: &LinearImage, reference: &Reference, sky: bevy::math::Vec3) -> Errors {
    let truth = &reference.image;
    let rmse = relative_rmse(
        &cloud_pixels(&image.pixels, truth, sky),
        &cloud_pixels(truth, truth, sky),
    );
    let truth_image = LinearImage {
        width: reference.width,
        height: reference.height,
        pixels: truth.clone(),
    };
    let boxed_truth = downsample(&truth_image, 4).pixels;
    let boxed = relative_rmse(
        &cloud_pixels(&downsample(image, 4).pixels, &boxed_truth, sky),
        &cloud_pixels(&boxed_truth, &boxed_truth, sky),
    );
    Errors {
        rmse: denoised(rmse, reference.noise),
        boxed: denoised(boxed, reference.noise_box4),
        energy: energy(image) / energy(&truth_image),
    }
}

/// Per block (row-major), the energy of `pixels` in it.
fn block_energies(pixels: &[[f32; 4]], width: u32, height: u32) -> Vec<f64> {
    let (bx, by) = BLOCKS;
    let mut out = vec![0.0; (bx * by) as usize];
    for (i, p) in pixels.iter().enumerate() {
        let (x, y) = (i as u32 % width, i as u32 / width);
        out[((y * by / height) * bx + x * bx / width) as usize] += (p[0] + p[1] + p[2]) as f64;
    }
    out
}

/// `values` averaged onto `coarse` by `fine`'s density (what a coarse voxel scatters is `rho S`).
fn restrict(values: &[DVec3], fine: &DensityGrid, coarse: &DensityGrid) -> Vec<DVec3> {
    restrict_by_density(&Moments::isotropic(values.to_vec()), fine, coarse).mean
}

/// The markdown section of one scene.
pub(crate) fn grid_error(bench: &BenchScene, scene: &Scene, reference: &Reference) -> String {
    let factor = bench.error_downsample;
    let sky = scene.background;
    let mut md = format!(
        "\n### {}\n\nReference: {} spp at {}×{} (noise {:.4}; {:.4} after a 4×4 box filter), \
         removed in quadrature. Other settings default.\n\n\
         | volume_resolution | scatter_iterations | rel. RMSE | 4×4 box | energy / truth |\n\
         |---:|---:|---:|---:|---:|\n",
        bench.name,
        reference.spp,
        reference.width,
        reference.height,
        reference.noise,
        reference.noise_box4
    );
    let mut blocks = Vec::new();
    for (n, m) in GRIDS {
        eprintln!("benchmark: {}: {n}³ × {m} (CPU)", bench.name);
        let s = settings(n, m);
        let Some(ill) = illuminate_scene_cloud(scene, 0, &s) else {
            return format!("\n### {}\n\nNo cloud with density.\n", bench.name);
        };
        let shown = image(scene, &ill, &s, factor);
        let e = errors(&shown, reference, sky);
        let _ = writeln!(
            md,
            "| {n}³ | {m} | {:.4} | {:.4} | {:.4} |",
            e.rmse, e.boxed, e.energy
        );
        if BLOCKS_OF.contains(&(n, m)) {
            blocks.push((
                format!("{n}³ × {m}"),
                block_energies(&shown.pixels, shown.width, shown.height),
            ));
        }
    }
    md.push_str(&block_table(reference, &blocks));
    md.push_str(&coarse_fine_table(bench, scene, reference));
    md
}

/// Real-time over truth per block, for the blocks that hold at least 1 % of the brightest
/// block's energy.
fn block_table(reference: &Reference, blocks: &[(String, Vec<f64>)]) -> String {
    let truth = block_energies(&reference.image, reference.width, reference.height);
    let brightest = truth.iter().copied().fold(0.0, f64::max);
    let mut md = format!(
        "\nEnergy per block of the image ({} × {} blocks, row 0 at the top), real-time over \
         truth:\n\n| block (row, column) | truth |",
        BLOCKS.0, BLOCKS.1
    );
    for (label, _) in blocks {
        let _ = write!(md, " {label} |");
    }
    md.push_str("\n|---|---:|");
    md.push_str(&"---:|".repeat(blocks.len()));
    md.push('\n');
    for (b, t) in truth.iter().enumerate() {
        if *t < 0.01 * brightest {
            continue;
        }
        let _ = write!(
            md,
            "| {}, {} | {t:.1} |",
            b as u32 / BLOCKS.0,
            b as u32 % BLOCKS.0
        );
        for (_, energies) in blocks {
            let _ = write!(md, " {:.3} |", energies[b] / t);
        }
        md.push('\n');
    }
    md
}

/// The coarse grid's image from its own solution, from the fine grid's (averaged onto it by
/// density), and from its own sweep of the fine grid's single scattering, through its own
/// density and through the fine grid's downsampled.
fn coarse_fine_table(bench: &BenchScene, scene: &Scene, reference: &Reference) -> String {
    let (nc, nf, m) = COARSE_FINE;
    eprintln!(
        "benchmark: {}: {nc}³ against {nf}³, {m} iterations (CPU)",
        bench.name
    );
    let sc = settings(nc, m);
    let (Some(coarse), Some(fine)) = (
        illuminate_scene_cloud(scene, 0, &sc),
        illuminate_scene_cloud(scene, 0, &settings(nf, m)),
    ) else {
        return String::new();
    };
    let fine_source = restrict(&fine.source.mean, &fine.grid, &coarse.grid);
    let sweep = |grid: &DensityGrid| {
        let mut ill = coarse.clone();
        ill.multiple = scatter(
            grid,
            coarse.k_local,
            coarse.albedo,
            ScatterStencil::DiscreteOrdinates,
            &fine_source,
            m,
        );
        ill
    };
    let mut read_fine = coarse.clone();
    read_fine.multiple.total = restrict(&fine.multiple.total, &fine.grid, &coarse.grid);
    let downsampled = fine.grid.downsample((nf / nc) as usize);
    let rows = [
        ("its own solution".to_string(), coarse.clone()),
        (
            format!("the {nf}³ grid's solution, averaged onto it by density"),
            read_fine,
        ),
        (
            format!("its sweep of the {nf}³ grid's single scattering (averaged)"),
            sweep(&coarse.grid),
        ),
        (
            format!("the same through the {nf}³ grid's density, downsampled"),
            sweep(&downsampled),
        ),
    ];
    let mut md = format!(
        "\nThe {nc}³ grid's image at {m} iterations, its `S_m` taken from:\n\n| `S_m` | rel. RMSE | 4×4 box | energy / truth |\n|---|---:|---:|---:|\n"
    );
    let measure = |ill: &CloudIllumination, s: &CloudQualitySettings| {
        errors(
            &image(scene, ill, s, bench.error_downsample),
            reference,
            scene.background,
        )
    };
    for (label, ill) in rows {
        let e = measure(&ill, &sc);
        let _ = writeln!(
            md,
            "| {label} | {:.4} | {:.4} | {:.4} |",
            e.rmse, e.boxed, e.energy
        );
    }
    let e = measure(&fine, &settings(nf, m));
    let _ = writeln!(
        md,
        "\n(The {nf}³ grid's own image: {:.4}, 4×4 box {:.4}, energy {:.4}.)",
        e.rmse, e.boxed, e.energy
    );
    md
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_blocks_hold_the_whole_image_s_energy() {
        let (w, h) = (80, 60);
        let pixels: Vec<[f32; 4]> = (0..w * h).map(|i| [i as f32, 1.0, 0.5, 1.0]).collect();
        let blocks = block_energies(&pixels, w, h);
        assert_eq!(blocks.len(), 48);
        let total: f64 = pixels.iter().map(|p| (p[0] + p[1] + p[2]) as f64).sum();
        assert!((blocks.iter().sum::<f64>() - total).abs() < 1e-9 * total);
        // Block (0, 0) is the top-left 10 x 10 pixels.
        let first: f64 = (0..10)
            .flat_map(|y| (0..10).map(move |x| y * w + x))
            .map(|i| i as f64 + 1.5)
            .sum();
        assert!((blocks[0] - first).abs() < 1e-9 * first);
    }
}
