//! Section 4: multiple scattering, orders of radiance swept along the lattice directions of
//! [`SweepDirections`] (or the paper's stencil), with the series' closure and warm restarts.

use bevy::math::DVec3;
use rayon::prelude::*;

use super::gather::{
    Flux, Moments, Quadrupole, flux_along, quadrupole_along, quadrupole_basis, zip_with,
};
use super::interpolation::unravel;
use super::voxelize::DensityGrid;
use crate::particle::DeltaM;
use crate::reference::ground::GroundLight;
use crate::settings::{ScatterStencil, SweepDirections};

mod closure;
mod sweep;

pub use closure::*;
pub use sweep::*;

/// Multiple scattering, every order past the first (contract section 4).
#[derive(Clone, Debug, PartialEq)]
pub struct MultipleScattering {
    /// `S_1, ..., S_M` (one mean per voxel each), the orders computed.
    pub orders: Vec<Vec<DVec3>>,
    /// How the series is closed past `S_M` (zero for `M = 0`).
    pub closure: SeriesClosure,
    /// `sum_{n=1..M} S_n` and the closure's tail per voxel (the means).
    pub total: Vec<DVec3>,
    /// The same sum of the orders' [`Flux`]es, closed alike; empty for an isotropic medium.
    pub flux: Vec<Flux>,
    /// The same sum of the orders' [`Quadrupole`]s, closed alike; empty for an isotropic medium.
    pub quadrupole: Vec<Quadrupole>,
    /// Coarse-grid cycles run after the orders ([`scatter_coarse_cycles`](super::scatter_coarse_cycles)):
    /// where any did, `total`, `flux` and `quadrupole` are their solution, not the closed sum.
    pub cycles: u32,
}

impl MultipleScattering {
    /// The solution's moments, as a warm restart starts from it.
    pub fn moments(&self) -> Moments {
        Moments {
            mean: self.total.clone(),
            flux: self.flux.clone(),
            quadrupole: self.quadrupole.clone(),
        }
    }

    /// The means' sum with the series closed by `closure` instead of its own, clamped at 0 like
    /// [`scatter_medium`]'s: the sum the GPU reaches from these orders with its own coefficients,
    /// which f32 orders move a little (the two-mode fit takes differences of the orders' size
    /// ratios). `None` below 2 orders, where `S_{M-1}` is not an order computed, and after
    /// coarse-grid cycles, which replace the closed sum.
    pub fn total_closed_with(&self, closure: &SeriesClosure) -> Option<Vec<DVec3>> {
        let [.., before, last] = self.orders.as_slice() else {
            return None;
        };
        if self.cycles > 0 {
            return None;
        }
        let mut sum = vec![DVec3::ZERO; last.len()];
        for order in &self.orders {
            sum.iter_mut().zip(order).for_each(|(t, s)| *t += *s);
        }
        let (last, before) = (
            Moments::isotropic(last.clone()),
            Moments::isotropic(before.clone()),
        );
        let zero = last.plus(&last, DVec3::splat(-1.0));
        let tail = closure.tail(&zero, &last, &before);
        Some(
            sum.iter()
                .zip(&tail.mean)
                .map(|(s, t)| (*s + *t).max(DVec3::ZERO))
                .collect(),
        )
    }
}

/// Iterates the stencil `iterations` times from `s0` (one entry per voxel; units of `E` per
/// steradian) and closes the series. `k_local` in 1/local metre, `albedo` in [0, 1]. A black
/// sky: [`scatter_under_sky`].
pub fn scatter(
    grid: &DensityGrid,
    k_local: f64,
    albedo: f64,
    stencil: ScatterStencil,
    s0: &[DVec3],
    iterations: u32,
) -> MultipleScattering {
    scatter_under_sky(grid, k_local, albedo, stencil, s0, DVec3::ZERO, iterations)
}

/// [`scatter`] under a uniform sky of radiance `sky` (section 4): the first iteration's sweeps
/// take it as the radiance entering the grid, so `S_1 = K S_0` plus the sky's single scattering,
/// and the sky's light is scattered on by the later orders. The paper's stencil has no boundary:
/// it ignores the sky.
pub fn scatter_under_sky(
    grid: &DensityGrid,
    k_local: f64,
    albedo: f64,
    stencil: ScatterStencil,
    s0: &[DVec3],
    sky: DVec3,
    iterations: u32,
) -> MultipleScattering {
    let medium = SweptMedium::alone(grid, k_local, albedo, 0.0);
    scatter_through(
        medium,
        stencil,
        &Moments::isotropic(s0.to_vec()),
        Boundary::sky(sky),
        iterations,
    )
}

/// [`scatter_under_sky`] for a medium of anisotropy `g` (section 4): the sweep goes through the
/// medium's δ-M transform, with the P2 source of its moments `g'` and `chi'_2`, from the source
/// `s0` of [`gather_source`](super::gather_source) (with its flux unless `g = 0`).
#[allow(clippy::too_many_arguments)]
pub fn scatter_medium(
    grid: &DensityGrid,
    k_local: f64,
    (albedo, g): (f64, f64),
    stencil: ScatterStencil,
    s0: &Moments,
    sky: DVec3,
    iterations: u32,
) -> MultipleScattering {
    let medium = SweptMedium::alone(grid, k_local, albedo, g);
    scatter_through(medium, stencil, s0, Boundary::sky(sky), iterations)
}

/// [`scatter_medium`] through `medium`: the full series, its sum clamped at 0 like the GPU's
/// closure. Radiance is never negative, but the sweep's parabolic source may dip below 0 beside
/// a sharp edge of the light (a relative 1e-4 in the tests' clouds).
pub(super) fn scatter_through(
    medium: SweptMedium,
    stencil: ScatterStencil,
    s0: &Moments,
    boundary: Boundary,
    iterations: u32,
) -> MultipleScattering {
    let mut series = scatter_series(medium, stencil, s0, boundary, iterations, Tail::TwoModes);
    series
        .total
        .iter_mut()
        .for_each(|t| *t = t.max(DVec3::ZERO));
    series
}

/// How [`scatter_series`] closes the series: the full series with two modes, a warm restart's
/// correction (whose orders may change sign) geometrically.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum Tail {
    TwoModes,
    Geometric,
}

/// The orders of the series from `s0` and their closed sum, signed (a warm restart's correction
/// may be negative).
pub(super) fn scatter_series(
    medium: SweptMedium,
    stencil: ScatterStencil,
    s0: &Moments,
    boundary: Boundary,
    iterations: u32,
    tail: Tail,
) -> MultipleScattering {
    let grid = medium.grid;
    assert_eq!(
        s0.mean.len(),
        grid.len(),
        "s0 must have one entry per voxel"
    );
    // The paper's stencil is isotropic.
    let s0 = match stencil {
        ScatterStencil::DiscreteOrdinates => s0.clone(),
        ScatterStencil::Paper => Moments::isotropic(s0.mean.clone()),
    };
    let zero = s0.plus(&s0, DVec3::splat(-1.0));
    let (mut total, mut last, mut before) = (zero.clone(), s0.clone(), zero.clone());
    let mut orders: Vec<Vec<DVec3>> = Vec::with_capacity(iterations as usize);
    // |S_0|, |S_1|, ..., |S_M|: a single iteration is closed with the ratio |S_1| / |S_0|.
    let mut sizes = vec![order_size(grid, &s0.mean)];
    for k in 0..iterations {
        let entering = if k == 0 { boundary } else { Boundary::NONE };
        let next = scatter_once(medium, stencil, &last, entering);
        total = total.plus(&next, DVec3::ONE);
        before = std::mem::replace(&mut last, next);
        orders.push(last.mean.clone());
        sizes.push(order_size(grid, &last.mean));
    }
    // The two modes fit orders 1 to M only: S_0 is no order of the series under a sky.
    let closure = match tail {
        Tail::TwoModes if iterations >= 4 => SeriesClosure::two_mode(&sizes),
        _ => SeriesClosure::geometric(&sizes),
    };
    if iterations > 0 {
        total = total.plus(&closure.tail(&zero, &last, &before), DVec3::ONE);
    }
    MultipleScattering {
        orders,
        closure,
        total: total.mean,
        flux: total.flux,
        quadrupole: total.quadrupole,
        cycles: 0,
    }
}

/// One iteration of `stencil`: `K s`, with the radiance `sky` entering the grid (the sweep only;
/// the paper's stencil sees the cloud's own medium only, isotropically).
fn scatter_once(
    medium: SweptMedium,
    stencil: ScatterStencil,
    s: &Moments,
    boundary: Boundary,
) -> Moments {
    match stencil {
        ScatterStencil::DiscreteOrdinates => sweep(medium, s, boundary),
        ScatterStencil::Paper => Moments::isotropic(paper_stencil(
            medium.grid,
            medium.k_local,
            medium.albedo,
            &s.mean,
        )),
    }
}

/// The multiple scattering for the source `s0`, restarted from the solution `previous` (a warm
/// restart, docs/illumination.md §4): since `S_m = K (s0 + S_m)`, the correction
/// `W_0 = K (s0 + previous) - previous` and its series `W_k = K^k W_0` sum to `S_m - previous`.
/// `iterations` orders in all (`W_0` the first), closed like [`scatter`]'s series:
/// `total = max(previous + sum_k W_k + W_last lambda / (1 - lambda), 0)`. `orders` holds the
/// `W_k`. Under a sky of radiance `sky` (black: `DVec3::ZERO`), the first sweep
/// `K (s0 + previous)` takes it in, as [`scatter_under_sky`]'s first iteration does.
///
/// # Panics
/// If `iterations < 2`, or `s0` and `previous` do not have one entry per voxel.
#[allow(clippy::too_many_arguments)]
pub fn scatter_warm(
    grid: &DensityGrid,
    k_local: f64,
    albedo: f64,
    stencil: ScatterStencil,
    s0: &[DVec3],
    previous: &[DVec3],
    sky: DVec3,
    iterations: u32,
) -> MultipleScattering {
    let (s0, previous) = (
        Moments::isotropic(s0.to_vec()),
        Moments::isotropic(previous.to_vec()),
    );
    let medium = (albedo, 0.0);
    scatter_warm_medium(
        grid, k_local, medium, stencil, &s0, &previous, sky, iterations,
    )
}

/// [`scatter_warm`] for a medium of anisotropy `g` ([`scatter_medium`]), from the moments of the
/// solution held ([`MultipleScattering::moments`]), its flux and quadrupole restarted like its
/// mean.
#[allow(clippy::too_many_arguments)]
pub fn scatter_warm_medium(
    grid: &DensityGrid,
    k_local: f64,
    (albedo, g): (f64, f64),
    stencil: ScatterStencil,
    s0: &Moments,
    previous: &Moments,
    sky: DVec3,
    iterations: u32,
) -> MultipleScattering {
    let medium = SweptMedium::alone(grid, k_local, albedo, g);
    assert!(
        iterations >= 2,
        "a warm restart takes at least 2 iterations"
    );
    assert_eq!(
        previous.mean.len(),
        s0.mean.len(),
        "one previous value per voxel"
    );
    let entering = Boundary::sky(sky);
    let once = scatter_once(medium, stencil, &s0.plus(previous, DVec3::ONE), entering);
    let correction = once.plus(previous, DVec3::splat(-1.0));
    let series = scatter_series(
        medium,
        stencil,
        &correction,
        Boundary::NONE,
        iterations - 1,
        Tail::Geometric,
    );
    // Clamped at 0 like the GPU's: the truncated correction may overshoot where the light fell.
    let total = zip_with(&once.mean, &series.total, |k, t| (*k + *t).max(DVec3::ZERO));
    let flux = zip_with(&once.flux, &series.flux, |k, t| {
        std::array::from_fn(|i| k[i] + t[i])
    });
    let quadrupole = zip_with(&once.quadrupole, &series.quadrupole, |k, t| {
        std::array::from_fn(|i| k[i] + t[i])
    });
    let mut orders = vec![correction.mean];
    orders.extend(series.orders);
    MultipleScattering {
        orders,
        closure: series.closure,
        total,
        flux,
        quadrupole,
        cycles: 0,
    }
}

/// The documented upper bound on `max S_m` (any channel) after `iterations` orders and the
/// closure. Every order is at most `q` times the previous one's maximum, with
/// `q = 4/3 albedo (1 - exp(-tau_line))` and `tau_line = K_local rho_max h sqrt(3) n` the optical
/// depth of the longest lattice line: a sweep's radiance is a transmittance-weighted sum of
/// `albedo S` along its line whose weights sum to `1 - exp(-tau_line)` at most, and whose
/// negative part (the parabola's second differences) is at most a sixth of that; the paper's
/// coefficients sum to at most `albedo (1 - exp(-K_local rho_max h))`. So
/// `max S_m <= max S_0 (sum_{k=1..M} q^k + q^M MAX_ORDER_RATIO / (1 - MAX_ORDER_RATIO))`. Finite
/// for any albedo and number of iterations (the closure's ratio is clamped), though for `q > 1`
/// it grows with them.
pub fn energy_bound(
    grid: &DensityGrid,
    k_local: f64,
    albedo: f64,
    iterations: u32,
    max_s0: f64,
) -> f64 {
    let tau_line = k_local * grid.max() * grid.h * 3f64.sqrt() * grid.n as f64;
    let q = 4.0 / 3.0 * albedo * -(-tau_line).exp_m1();
    let orders: f64 = (1..=iterations).map(|k| q.powi(k as i32)).sum();
    let tail = q.powi(iterations as i32) * MAX_ORDER_RATIO / (1.0 - MAX_ORDER_RATIO);
    max_s0 * (orders + if iterations > 0 { tail } else { 0.0 })
}

#[cfg(test)]
mod tests;
