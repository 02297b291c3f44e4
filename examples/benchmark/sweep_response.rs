//! `--sweep-response`: how the discrete-ordinates sweep (docs/illumination.md §4) carries a
//! source that varies in space, against the exact transport. In an infinite homogeneous medium
//! of albedo 1 the transport operator maps a source `1 + cos(k . x)` to `1 + f(k / sigma)
//! cos(k . x)` with `f(x) = atan(x) / x`: light spreads over about a mean free path, so detail
//! finer than that fades. One sweep of the f64 CPU reference over a uniform grid, the mode's
//! gain measured at the grid's centre (far from its edges), against `f`. No adapter needed.

use std::fmt::Write;

use bevy::math::DVec3;
use bevy_particle_clouds::{
    ScatterStencil,
    reference::illumination::{DensityGrid, scatter},
};

/// Voxels per side of the uniform grid (voxel size 1).
const SIDE: usize = 64;
/// Half-width of the central block the gain is measured over, in voxels.
const CENTRE: usize = 6;
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

/// One sweep's gain of the mode `cos(k . x)`, `k = 2 pi / period` times `direction` per
/// voxel (`period` along an axis), through voxels of optical depth `sigma_h`: the centre's amplitude of the mode over its
/// mean (which the mean source, 1, would give).
fn sweep_gain(sigma_h: f64, direction: [f64; 3], period: f64) -> f64 {
    let grid = DensityGrid {
        n: SIDE,
        centre: DVec3::ZERO,
        side: SIDE as f64,
        h: 1.0,
        rho: vec![1.0; SIDE.pow(3)],
    };
    let k = 2.0 * std::f64::consts::PI / period;
    let phase = |i: usize, j: usize, l: usize| {
        k * (direction[0] * i as f64 + direction[1] * j as f64 + direction[2] * l as f64)
    };
    // x: the uniform source, y: the mode.
    let mut s0 = vec![DVec3::ZERO; grid.len()];
    for (idx, s) in s0.iter_mut().enumerate() {
        let (i, j, l) = (idx % SIDE, idx / SIDE % SIDE, idx / (SIDE * SIDE));
        *s = DVec3::new(1.0, phase(i, j, l).cos(), 0.0);
    }
    let s1 = &scatter(
        &grid,
        sigma_h,
        1.0,
        ScatterStencil::DiscreteOrdinates,
        &s0,
        1,
    )
    .orders[0];
    let (mut projected, mut norm, mut mean) = (0.0, 0.0, 0.0);
    let range = SIDE / 2 - CENTRE..SIDE / 2 + CENTRE;
    for l in range.clone() {
        for j in range.clone() {
            for i in range.clone() {
                let mode = phase(i, j, l).cos();
                let s = s1[grid.index(i, j, l)];
                projected += s.y * mode;
                norm += mode * mode;
                mean += s.x;
            }
        }
    }
    projected / norm / (mean / (2 * CENTRE).pow(3) as f64)
}

/// The markdown table.
pub(crate) fn table() -> String {
    let mut md = String::from(
        "# The sweep's response to detail\n\nOne discrete-ordinates sweep (26 lattice \
         directions, parabolic source) of a source `1 + cos(k . x)` over a uniform grid of \
         albedo 1, against the exact transport's `atan(x) / x`, `x = k / sigma`, `k` the mode's wavenumber (`cargo run \
         --example benchmark -- --sweep-response`; f64 CPU reference, the gain measured at the \
         grid's centre).\n\n| voxel optical depth | mode | period along an axis (voxels) | \
         `k / sigma` | sweep | exact | sweep / exact |\n|---:|---|---:|---:|---:|---:|---:|\n",
    );
    for sigma_h in VOXEL_DEPTHS {
        for (direction, label) in DIRECTIONS {
            for period in PERIODS {
                eprintln!("benchmark: sweep response, sigma h {sigma_h}, {label}, {period}");
                let length = direction.iter().map(|c| c * c).sum::<f64>().sqrt();
                let x = 2.0 * std::f64::consts::PI / period * length / sigma_h;
                let (sweep, exact) = (sweep_gain(sigma_h, direction, period), exact_gain(x));
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
