//! `sweep-response`: how the discrete-ordinates sweep (docs/illumination.md §4) carries a
//! source that varies in space, against the exact transport. In an infinite homogeneous medium
//! of albedo 1 the transport operator maps a source `1 + cos(k . x)` to `1 + f(k / sigma)
//! cos(k . x)` with `f(x) = atan(x) / x`: light spreads over about a mean free path, so detail
//! finer than that fades. One sweep of the f64 CPU reference over a uniform grid, the mode's
//! gain measured at the grid's centre (far from its edges), against `f`. No adapter needed.

use std::fmt::Write;

use bevy_particle_clouds::reference::illumination::sweep_mode_gain;

/// Voxels per side of the uniform grid (voxel size 1).
const SIDE: usize = 64;
/// The voxels' optical depth `sigma h`.
const VOXEL_DEPTHS: [f64; 5] = [0.125, 0.25, 0.5, 1.0, 2.0];
/// The modes' periods along an axis, in voxels (2: the grid's Nyquist).
const PERIODS: [f64; 4] = [2.0, 4.0, 8.0, 16.0];
/// The modes' directions: along an axis, and along a body diagonal.
const DIRECTIONS: [([f64; 3], &str); 2] =
    [([1.0, 0.0, 0.0], "axis"), ([1.0, 1.0, 1.0], "diagonal")];

/// The exact transport's gain of a mode of wavenumber `x = |k| / sigma`.
fn exact_gain(x: f64) -> f64 {
    if x < 1e-9 { 1.0 } else { x.atan() / x }
}

/// The markdown table.
pub(crate) fn table() -> String {
    let mut md = String::from(
        "# The sweep's response to detail\n\nOne discrete-ordinates sweep (26 lattice \
         directions, parabolic source) of a source `1 + cos(k . x)` over a uniform grid of \
         albedo 1, against the exact transport's `atan(x) / x`, `x = k / sigma`, `k` the mode's wavenumber (`cargo run \
         --example benchmark -- sweep-response`; f64 CPU reference, the gain measured at the \
         grid's centre).\n\n| voxel optical depth | mode | period along an axis (voxels) | \
         `k / sigma` | sweep | exact | sweep / exact |\n|---:|---|---:|---:|---:|---:|---:|\n",
    );
    for sigma_h in VOXEL_DEPTHS {
        for (direction, label) in DIRECTIONS {
            for period in PERIODS {
                eprintln!("benchmark: sweep response, sigma h {sigma_h}, {label}, {period}");
                let length = direction.iter().map(|c| c * c).sum::<f64>().sqrt();
                let x = 2.0 * std::f64::consts::PI / period * length / sigma_h;
                let (sweep, exact) = (
                    sweep_mode_gain(SIDE, sigma_h, direction, period),
                    exact_gain(x),
                );
                let _ = writeln!(
                    md,
                    "| {sigma_h} | {label} | {period} | {x:.2} | {sweep:.3} | {exact:.3} | {:.2} |",
                    sweep / exact
                );
            }
        }
    }
    md
}
