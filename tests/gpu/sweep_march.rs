//! The sweep's two marches (`SweepMarch`): reading ahead and serial, the same arithmetic in the
//! same order, give the same volumes, for an isotropic medium and for one whose volumes hold
//! angular moments, through the series and the coarse-grid cycles. (On llvmpipe the default
//! march is the serial one, which the other GPU tests compare with the CPU reference.) So do its
//! two dispatches (`SweepDispatch`): one per direction pair, and one per order, whose sum of the
//! pairs' shares groups the additions otherwise (f32 rounding).

use bevy::prelude::*;
use bevy_particle_clouds::headless::{self, FrameRecorder};
use bevy_particle_clouds::{
    CloudQualitySettings, Medium,
    reference::metrics::max_relative_difference,
    settings::{SweepDirections, SweepDispatch, SweepMarch},
};

use crate::{
    common,
    illumination::random_particles,
    warm_start::{gpu_multiple, lit_cloud_app},
};

/// Largest allowed difference, relative to the volume's largest value: set while the density's
/// last bits could differ between two renders (voxelize's float atomics; it sums in a fixed order
/// now, and the bound stays until a parallel GPU measures it again).
const TOLERANCE: f64 = 1e-5;

/// The same for the two dispatches, whose sums group the pairs' shares otherwise (each pair's two
/// marches first): llvmpipe measured 3e-7 to 7e-6 with the 26 directions and up to 2e-5 with the
/// 98, through the closure, which enlarges what the last orders differ by. A pair's lines
/// missing or doubled would differ by about a pair's share, 1/13 or 1/49.
const PER_ORDER_TOLERANCE: f64 = 1e-4;

fn multiple(march: SweepMarch, anisotropy: f32) -> Vec<f64> {
    multiple_with(
        march,
        SweepDispatch::PerPair,
        anisotropy,
        SweepDirections::Lattice26,
    )
}

fn multiple_with(
    march: SweepMarch,
    dispatch: SweepDispatch,
    anisotropy: f32,
    directions: SweepDirections,
) -> Vec<f64> {
    let settings = CloudQualitySettings {
        scatter_coarse_cycles: 1,
        scatter_directions: directions,
        ..common::quality(16, 6)
    };
    let medium = Medium {
        extinction: 10.0,
        albedo: 0.98,
        anisotropy,
    };
    let particles = random_particles(7, 60);
    let sky = Vec3::new(0.1, 0.2, 0.4);
    let light = (Vec3::new(0.2, -1.0, 0.1), Vec3::ONE);
    let (mut app, _) = lit_cloud_app(sky, light, (&particles, medium, settings));
    app.insert_resource(march);
    app.insert_resource(dispatch);
    headless::render_until_steady(&mut app, &mut FrameRecorder::default(), 1, 20).unwrap();
    gpu_multiple(&mut app)
}

#[test]
fn the_read_ahead_march_equals_the_serial_one() {
    for anisotropy in [0.0, 0.6] {
        let serial = multiple(SweepMarch::Serial, anisotropy);
        let read_ahead = multiple(SweepMarch::ReadAhead, anisotropy);
        assert!(serial.iter().any(|&s| s > 0.0), "no multiple scattering");
        let error = max_relative_difference(&read_ahead, &serial);
        assert!(
            error <= TOLERANCE,
            "g {anisotropy}: the marches differ by {error:e} of the maximum"
        );
    }
}

#[test]
fn one_dispatch_per_order_equals_one_per_pair() {
    // Each march, with and without moments, and the 98 directions (two renders each).
    let cases = [
        (SweepMarch::Serial, 0.0, SweepDirections::Lattice26),
        (SweepMarch::ReadAhead, 0.6, SweepDirections::Lattice26),
        (SweepMarch::Serial, 0.0, SweepDirections::Lattice98),
    ];
    for (march, anisotropy, directions) in cases {
        let per_pair = multiple_with(march, SweepDispatch::PerPair, anisotropy, directions);
        let per_order = multiple_with(march, SweepDispatch::PerOrder, anisotropy, directions);
        assert!(per_pair.iter().any(|&s| s > 0.0), "no multiple scattering");
        let error = max_relative_difference(&per_order, &per_pair);
        assert!(
            error <= PER_ORDER_TOLERANCE,
            "g {anisotropy}, {directions:?}, {march:?}: the dispatches differ by {error:e} of the maximum"
        );
    }
}
