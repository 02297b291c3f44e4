//! The coarse-grid cycles of the scattering (`scatter_coarse_cycles`) on the GPU against the f64
//! CPU reference: a few orders of the series, then cycles that solve for the residual's smooth
//! part on a grid of half the side. Under a sky, for an isotropic medium and for an anisotropic
//! one (whose volumes hold angular moments), and at an odd side, where the cycles only sweep;
//! along the 26 lattice directions and along the 98.

use bevy::prelude::*;
use bevy_particle_clouds::headless::{self, FrameRecorder};
use bevy_particle_clouds::{
    CloudPass, CloudQualitySettings, Medium, SweepDirections,
    reference::{
        illumination::{LocalLight, illuminate_under_sky},
        metrics::max_relative_difference,
    },
};

use crate::{
    common,
    illumination::{TOLERANCE, flat, random_particles},
    warm_start::{difference, gpu_multiple, lit_cloud_app},
};

/// Dispatches of the scattering with `pairs` direction pairs: `fine` orders of the series (a
/// sweep per pair and an accumulation each, the two-mode closure's three), then with a coarse
/// grid the media's restriction, and per cycle two restart sweeps (a sweep per pair and 2 each)
/// and, with a coarse grid, the residual's restriction, 32 coarse orders closed alike and the
/// prolongation.
fn scatter_dispatches(pairs: u32, fine: u32, cycles: u32, coarse: bool) -> u32 {
    let series = |orders: u32| orders * (pairs + 1) + 3;
    let transfer = if coarse { 2 + series(32) } else { 0 };
    series(fine) + coarse as u32 + cycles * (2 * (pairs + 2) + transfer)
}

const LATTICE_26: SweepDirections = SweepDirections::Lattice26;
const LATTICE_98: SweepDirections = SweepDirections::Lattice98;

#[test]
fn cycles_match_the_cpu_reference() {
    check_cycles(16, 0.0, LATTICE_26);
}

#[test]
fn cycles_carry_the_moments_of_an_anisotropic_medium() {
    check_cycles(16, 0.6, LATTICE_26);
}

#[test]
fn an_odd_side_has_no_coarse_grid_and_only_sweeps() {
    check_cycles(15, 0.0, LATTICE_26);
}

/// The 98 directions' sweep (steps of up to 2 voxels per axis, their own weights), on both
/// grids of the cycles, with moments.
#[test]
fn the_98_directions_sweep_matches_the_cpu_reference() {
    check_cycles(16, 0.6, LATTICE_98);
}

/// At an odd side, whose lines of step 2 start at either parity.
#[test]
fn the_98_directions_sweep_an_odd_side() {
    check_cycles(15, 0.0, LATTICE_98);
}

fn check_cycles(side: u32, anisotropy: f32, directions: SweepDirections) {
    let particles = random_particles(5, 60);
    let medium = Medium {
        extinction: 12.0,
        albedo: 0.99,
        anisotropy,
    };
    let settings = CloudQualitySettings {
        scatter_coarse_cycles: 2,
        scatter_directions: directions,
        ..common::quality(side, 4)
    };
    let sky = Vec3::new(0.1, 0.2, 0.4);
    let direction = Vec3::new(0.2, -1.0, 0.1);
    let irradiance = Vec3::new(1.0, 0.9, 0.8);

    let light = (direction, irradiance);
    let (mut app, _) = lit_cloud_app(sky, light, (&particles, medium, settings));
    let mut recorder = FrameRecorder::default();
    headless::render_until_steady(&mut app, &mut recorder, 1, 20).unwrap();
    let frame = recorder
        .frames
        .iter()
        .find(|f| f.runs(CloudPass::Scatter) > 0)
        .expect("a frame that scatters")
        .clone();
    assert_eq!(
        frame.dispatches(CloudPass::Scatter),
        scatter_dispatches(
            directions.pairs().len() as u32,
            4,
            2,
            side.is_multiple_of(2)
        )
    );
    let gpu = gpu_multiple(&mut app);

    let cpu = |settings: &CloudQualitySettings| {
        let light = LocalLight {
            direction: direction.as_dvec3(),
            irradiance: irradiance.as_dvec3(),
        };
        illuminate_under_sky(&particles, &medium, 1.0, &[light], sky.as_dvec3(), settings)
            .unwrap()
            .multiple
    };
    let cycled = cpu(&settings);
    let error = difference(&gpu, &cycled);
    assert!(error <= TOLERANCE, "GPU differs by {error:e}");
    // The cycles changed the solution: the series alone is far from it.
    let series = cpu(&CloudQualitySettings {
        scatter_coarse_cycles: 0,
        ..settings
    });
    let apart = max_relative_difference(&flat(&series.total), &flat(&cycled.total));
    assert!(
        apart > 20.0 * TOLERANCE,
        "cycles moved it by {apart:e} only"
    );
    // The other direction set's solution is another: the GPU followed the one asked for.
    let other = cpu(&CloudQualitySettings {
        scatter_directions: match directions {
            SweepDirections::Lattice26 => LATTICE_98,
            SweepDirections::Lattice98 => LATTICE_26,
        },
        ..settings
    });
    let apart = max_relative_difference(&flat(&other.total), &flat(&cycled.total));
    assert!(
        apart > 20.0 * TOLERANCE,
        "the other directions moved it by {apart:e} only"
    );
}
