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

/// The 26 lattice directions `o` (components in {-1, 0, 1}, not all 0).
pub fn lattice_directions() -> Vec<[i64; 3]> {
    SweepDirections::Lattice26
        .directions()
        .into_iter()
        .map(|d| d.o.map(i64::from))
        .collect()
}

/// `(1 - e, (1 - e) / tau - e)` with `e = exp(-tau)`: the weights of a segment's constant and
/// linear source terms. Series for small `tau`, where both differences cancel (the GPU uses the
/// same switch, in f32).
pub fn segment_weights(tau: f64) -> (f64, f64) {
    if tau < SERIES_BELOW {
        let t2 = tau * tau;
        (
            tau - t2 / 2.0 + t2 * tau / 6.0,
            tau / 2.0 - t2 / 3.0 + t2 * tau / 8.0,
        )
    } else {
        let e = (-tau).exp();
        (1.0 - e, (1.0 - e) / tau - e)
    }
}

/// `int_0^tau exp(-t) u (1 - u) dt` with `u = t / tau`: the weight of a segment's parabolic
/// source term (`J(u) = J_v (1 - u) + J_u u - C / 2 u (1 - u)`, `C` its second difference).
pub fn curvature_weight(tau: f64) -> f64 {
    if tau < 0.5 {
        // sum_k (-tau)^k / k! tau / ((k + 2)(k + 3))
        let mut term = tau;
        let mut sum = 0.0;
        for k in 0..12 {
            let kf = k as f64;
            sum += term / ((kf + 2.0) * (kf + 3.0));
            term *= -tau / (kf + 1.0);
        }
        sum
    } else {
        let e = (-tau).exp();
        let (_, linear) = segment_weights(tau);
        linear - (2.0 - e * (tau * tau + 2.0 * tau + 2.0)) / (tau * tau)
    }
}

/// Optical depth below which [`segment_weights`] uses its series (relative error < 1e-5 there).
pub const SERIES_BELOW: f64 = 0.02;

/// What the multiple scattering sweeps through on a cloud's scattering grid (section 4): the
/// cloud's density and its medium's δ-M transform, and the media of other clouds where
/// they reach into its cube (section 4, "Clouds that overlap").
#[derive(Clone, Copy)]
pub(super) struct SweptMedium<'a> {
    pub(super) grid: &'a DensityGrid,
    pub(super) k_local: f64,
    /// The cloud's own albedo (the paper's stencil takes it untransformed).
    pub(super) albedo: f64,
    /// The cloud's own medium, transformed (its true albedo for an isotropic one).
    pub(super) delta: DeltaM,
    /// Per voxel, other clouds' transformed extinction and scattering coefficients in units of
    /// the cloud's own (untransformed) extinction at density 1
    /// (`sum_c c_c K_c rho_c / K`, `sum_c c_c albedo'_c K_c rho_c / K`).
    pub(super) foreign: Option<&'a [[f64; 2]]>,
    /// The directions the sweep carries radiance along.
    pub(super) directions: SweepDirections,
}

impl<'a> SweptMedium<'a> {
    /// A cloud alone: local extinction `k_local`, albedo `albedo`, anisotropy `g`.
    pub(super) fn alone(grid: &'a DensityGrid, k_local: f64, albedo: f64, g: f64) -> Self {
        Self {
            grid,
            k_local,
            albedo,
            delta: DeltaM::new(albedo, g),
            foreign: None,
            directions: SweepDirections::default(),
        }
    }

    /// Extinction of voxel `i`, in units of `K_local`.
    fn density(&self, i: usize) -> f64 {
        self.delta.depth_scale * self.grid.rho[i] + self.foreign.map_or(0.0, |f| f[i][0])
    }

    /// Albedo of voxel `i`: the cloud's own where no other cloud's medium reaches.
    fn albedo(&self, i: usize) -> f64 {
        match self.foreign {
            Some(f) if f[i][0] > 0.0 => {
                let own = self.delta.albedo * self.delta.depth_scale * self.grid.rho[i];
                (own + f[i][1]) / self.density(i)
            }
            _ => self.delta.albedo,
        }
    }

    /// Scattering coefficient of voxel `i`, in units of `K_local`: the cloud's own and other
    /// clouds'.
    pub(super) fn scattering(&self, i: usize) -> f64 {
        let own = self.delta.albedo * self.delta.depth_scale * self.grid.rho[i];
        own + self.foreign.map_or(0.0, |f| f[i][1])
    }

    /// `J = albedo S(w)` at voxel `i` towards the unit direction `w`, with the P2 phase function
    /// of the cloud's transformed medium, whose moments are `g'` and `chi'_2`:
    /// `albedo (mean + 3 g' F . w + (15/2) chi'_2 w^T Q w)`.
    fn source(&self, s: &Moments, i: usize, w: DVec3) -> DVec3 {
        let mut j = s.mean[i];
        if let Some(f) = s.flux.get(i) {
            j += flux_along(f, w) * (3.0 * self.delta.anisotropy);
        }
        if let Some(q) = s.quadrupole.get(i) {
            j += quadrupole_along(q, w) * (7.5 * self.delta.second_moment);
        }
        j * self.albedo(i)
    }
}

/// What enters a cloud's grid from outside in an iteration that brings the boundary in (section
/// 4): the sky's radiance from every side, and with a ground, the ground's on the lattice lines
/// that climb.
#[derive(Clone, Copy)]
pub(super) struct Boundary<'a> {
    pub(super) sky: DVec3,
    pub(super) ground: Option<&'a GroundLight>,
}

impl Boundary<'_> {
    /// Nothing enters: the later iterations.
    pub(super) const NONE: Self = Self {
        sky: DVec3::ZERO,
        ground: None,
    };

    /// The sky alone.
    pub(super) fn sky(sky: DVec3) -> Self {
        Self { sky, ground: None }
    }

    /// The radiance entering `grid` on the line whose first voxel is `v`, travelling along `w`.
    fn entering(&self, grid: &DensityGrid, v: [usize; 3], w: DVec3, half_step: f64) -> DVec3 {
        self.ground
            .and_then(|g| g.entering(grid, v, w, half_step))
            .unwrap_or(self.sky)
    }
}

/// The unit direction the radiance of sweep direction `o` travels in: `-o / |o|` (it arrives
/// from the `+o` side).
/// The 26-point Lebedev rule's weight of the lattice direction `o` (exact to degree 7): 1/21
/// along an axis, 4/105 along a face diagonal, 9/280 along a body diagonal. The quadrupole is
/// gathered with it: a P2 radiance's quadrupole is a degree-4 integral, which the equal weights
/// `1/26` (exact to degree 3) get wrong, keeping 0.87 of an axis-aligned quadrupole and 1.09 of
/// an off-diagonal one per order. The mean and the flux of a P2 radiance are exact either way.
pub fn lebedev_weight(o: [i64; 3]) -> f64 {
    SweepDirections::Lattice26
        .directions()
        .into_iter()
        .find(|d| d.o.map(i64::from) == o)
        .map_or(0.0, |d| d.quadrupole)
}

pub(super) fn travel(o: [i64; 3]) -> DVec3 {
    -DVec3::new(o[0] as f64, o[1] as f64, o[2] as f64).normalize()
}

/// `I_o` over the whole grid for one direction `o`: the radiance arriving at each voxel from
/// direction `o` (from `v + o`, `v + 2o`, ...), divided by nothing yet. Marched from the downwind
/// side, `I_o(v) = e I_o(v+o) + J(v)(1-e) + (J(v+o) - J(v))((1-e)/tau - e) - C/2 W_2(tau)`, `J`
/// the voxel's [`SweptMedium::source`] towards the radiance's travel direction `-o`, parabolic
/// along the segment with `C` the mean of its ends' second differences along the line (those
/// whose neighbours are both inside; [`curvature_weight`]), with
/// `tau = K_local (rho_v + rho_{v+o}) / 2 h |o|` and density, `S` and `I_o` zero outside the grid
/// (with other clouds' media, `rho` and `albedo` are the voxel's over all of them).
fn sweep_direction(
    medium: SweptMedium,
    o: [i64; 3],
    s: &Moments,
    boundary: Boundary,
) -> Vec<DVec3> {
    let grid = medium.grid;
    let n = grid.n as i64;
    let step = grid.h * ((o[0] * o[0] + o[1] * o[1] + o[2] * o[2]) as f64).sqrt();
    let w = travel(o);
    let mut radiance = vec![DVec3::ZERO; grid.len()];
    let sources: Vec<DVec3> = (0..grid.len()).map(|i| medium.source(s, i, w)).collect();
    let inside = |x: [i64; 3]| {
        x.iter()
            .all(|&c| (0..n).contains(&c))
            .then(|| grid.index(x[0] as usize, x[1] as usize, x[2] as usize))
    };
    let shifted = |x: [i64; 3], k: i64| [x[0] + k * o[0], x[1] + k * o[1], x[2] + k * o[2]];
    // The source's second difference along the line at x, where both neighbours are inside.
    let second_difference = |x: [i64; 3]| -> Option<DVec3> {
        let (a, b, c) = (inside(shifted(x, -1))?, inside(x)?, inside(shifted(x, 1))?);
        Some(sources[a] - sources[b] * 2.0 + sources[c])
    };
    // Visit voxels so that v + o is always visited before v: along each axis, descending where
    // o is positive.
    let order = |a: usize, i: i64| if o[a] > 0 { n - 1 - i } else { i };
    for kk in 0..n {
        for jj in 0..n {
            for ii in 0..n {
                let v = [order(0, ii), order(1, jj), order(2, kk)];
                let idx = grid.index(v[0] as usize, v[1] as usize, v[2] as usize);
                let upwind = inside(shifted(v, 1));
                // Outside the grid: no medium, and the boundary's radiance arriving.
                let (rho_u, j_u, i_u) = match upwind {
                    Some(j) => (medium.density(j), sources[j], radiance[j]),
                    None => {
                        let first = v.map(|c| c as usize);
                        let entering = boundary.entering(grid, first, w, 0.5 * step);
                        (0.0, DVec3::ZERO, entering)
                    }
                };
                let j = sources[idx];
                // The segment's curvature: the mean of its ends' second differences (none where
                // the upwind end is outside, for both need v + o).
                let curvature = match (second_difference(v), second_difference(shifted(v, 1))) {
                    (Some(a), Some(b)) => (a + b) * 0.5,
                    (Some(a), None) | (None, Some(a)) => a,
                    (None, None) => DVec3::ZERO,
                };
                let tau = medium.k_local * (medium.density(idx) + rho_u) * 0.5 * step;
                let (constant, linear) = segment_weights(tau);
                let e = 1.0 - constant;
                radiance[idx] = i_u * e + j * constant + (j_u - j) * linear
                    - curvature * (0.5 * curvature_weight(tau));
            }
        }
    }
    radiance
}

/// One discrete-ordinates iteration (section 4): the next order's moments over the medium's
/// lattice directions, `mean = sum_o m_o I_o`, and for an anisotropic medium (one whose source
/// has a flux) `F = sum_o m_o I_o w_o` and `Q = sum_o u_o I_o (w_o w_o^T - I/3)`, `m_o` and
/// `u_o` the direction's mean and quadrupole weights (`1/26` and the [`lebedev_weight`] for the
/// 26 directions; `crate::lattice`), `w_o` the radiance's travel direction; the radiance
/// `boundary` gives entering the grid from outside.
pub(super) fn sweep(medium: SweptMedium, s: &Moments, boundary: Boundary) -> Moments {
    let directional = !s.flux.is_empty();
    let voxels = s.mean.len();
    let empty = || Swept {
        mean: vec![DVec3::ZERO; voxels],
        flux: vec![[DVec3::ZERO; 3]; if directional { voxels } else { 0 }],
        quadrupole: vec![[DVec3::ZERO; 5]; if directional { voxels } else { 0 }],
    };
    let swept = medium
        .directions
        .directions()
        .into_par_iter()
        .map(|d| {
            let o = d.o.map(i64::from);
            let radiance = sweep_direction(medium, o, s, boundary);
            let mut out = empty();
            let w = travel(o);
            let q = quadrupole_basis(w);
            let weight = d.quadrupole;
            for (i, r) in radiance.into_iter().enumerate() {
                let share = r * d.mean;
                out.mean[i] = share;
                if directional {
                    out.flux[i] = [share * w.x, share * w.y, share * w.z];
                    out.quadrupole[i] = q.map(|q| r * weight * q);
                }
            }
            out
        })
        .reduce(empty, Swept::add);
    Moments {
        mean: swept.mean,
        flux: swept.flux,
        quadrupole: swept.quadrupole,
    }
}

/// What one sweep accumulates (see [`sweep`]).
struct Swept {
    mean: Vec<DVec3>,
    flux: Vec<Flux>,
    quadrupole: Vec<Quadrupole>,
}

impl Swept {
    fn add(mut self, other: Swept) -> Swept {
        self.mean
            .iter_mut()
            .zip(&other.mean)
            .for_each(|(a, b)| *a += *b);
        for (a, b) in self.flux.iter_mut().zip(&other.flux) {
            (0..3).for_each(|i| a[i] += b[i]);
        }
        for (a, b) in self.quadrupole.iter_mut().zip(&other.quadrupole) {
            (0..5).for_each(|i| a[i] += b[i]);
        }
        self
    }
}

/// One iteration of the paper's Algorithm 2:
/// `S_{n+1}(v) = (albedo / 26) (1 - exp(-K_local rho_v h)) sum_j S_n(j)` over the neighbours `j`
/// inside the grid.
fn paper_stencil(grid: &DensityGrid, k_local: f64, albedo: f64, s: &[DVec3]) -> Vec<DVec3> {
    let n = grid.n as i64;
    let directions = lattice_directions();
    (0..grid.len())
        .into_par_iter()
        .map(|idx| {
            let (i, j, k) = unravel(idx, grid.n);
            let v = [i as i64, j as i64, k as i64];
            let sum = directions.iter().fold(DVec3::ZERO, |acc, o| {
                let u = [v[0] + o[0], v[1] + o[1], v[2] + o[2]];
                if u.iter().all(|&c| (0..n).contains(&c)) {
                    acc + s[grid.index(u[0] as usize, u[1] as usize, u[2] as usize)]
                } else {
                    acc
                }
            });
            sum * (albedo / 26.0 * -(-k_local * grid.rho[idx] * grid.h).exp_m1())
        })
        .collect()
}

/// One discrete-ordinates sweep's gain of a source's Fourier mode (docs/illumination.md §4,
/// "Detail finer than a mean free path"): over a uniform grid of `side³` voxels of optical depth
/// `sigma_h` each and albedo 1, the source `1 + cos(k . v)`, `k = 2 pi / period direction` per
/// voxel (`period` in voxels along an axis), swept once; returns the mode's amplitude over the
/// mean's in the central 8³ voxels (far from the edges for `side >= 32`, `sigma_h >= 0.5`, or
/// larger grids at thinner voxels; all of a grid smaller than 8). The exact transport of an
/// infinite medium gives `atan(x) / x`, `x = |k| / sigma`.
pub fn sweep_mode_gain(side: usize, sigma_h: f64, direction: [f64; 3], period: f64) -> f64 {
    let grid = DensityGrid {
        n: side,
        centre: DVec3::ZERO,
        side: side as f64,
        h: 1.0,
        rho: vec![1.0; side.pow(3)],
    };
    let k = 2.0 * std::f64::consts::PI / period;
    let phase = |idx: usize| {
        let (i, j, l) = unravel(idx, side);
        k * (direction[0] * i as f64 + direction[1] * j as f64 + direction[2] * l as f64)
    };
    // x: the uniform source, y: the mode.
    let s0: Vec<DVec3> = (0..grid.len())
        .map(|idx| DVec3::new(1.0, phase(idx).cos(), 0.0))
        .collect();
    let s1 = &scatter(
        &grid,
        sigma_h,
        1.0,
        ScatterStencil::DiscreteOrdinates,
        &s0,
        1,
    )
    .orders[0];
    // The central 8³ voxels, or the whole of a smaller grid.
    let width = side.min(8);
    let centre = side / 2 - width / 2..side / 2 - width / 2 + width;
    let (mut projected, mut norm, mut mean) = (0.0, 0.0, 0.0);
    for l in centre.clone() {
        for j in centre.clone() {
            for i in centre.clone() {
                let idx = grid.index(i, j, l);
                let mode = phase(idx).cos();
                projected += s1[idx].y * mode;
                norm += mode * mode;
                mean += s1[idx].x;
            }
        }
    }
    projected / norm / (mean / width.pow(3) as f64)
}

/// Largest per-order ratio `lambda` the series closure assumes.
pub const MAX_ORDER_RATIO: f64 = 0.995;

/// The two-mode closure's slower ratio must leave at least this many times the faster one's
/// distance to 1: nearer, its coefficients cancel so strongly that the tail follows the last two
/// orders' differences rather than their sum, and the geometric closure is taken instead. The
/// two-mode tail takes its full weight from [`MODE_SEPARATION_FULL`] on.
pub const MODE_SEPARATION: f64 = 1.5;

/// The modes' separation from which the two-mode tail takes its full weight.
pub const MODE_SEPARATION_FULL: f64 = 2.0;

/// The two-mode fit divides by `det = N_{M-2}^2 - N_{M-1} N_{M-3}`, which vanishes as the faster
/// mode dies out, and its tail grows as `1 / (1 - r1)`: a relative change `e` of the sizes (their
/// f32 rounding, the order of a GPU's atomic adds, a particle that moved) moves the tail by
/// about `e / y`, `y = |det| / N_{M-2}^2 (1 - r1)` (measured on thick, bright clouds). Below
/// this `y` the geometric closure is taken, which the two-mode tail has come close to by then
/// (within 3 % at `y` = 6e-6 on such clouds). The two-mode tail takes its full weight from
/// [`CONDITIONING_FULL`] on, log-linearly between: an `e` of 1e-7 then moves the tail by at
/// most 1e-3.
pub const CONDITIONING: f64 = 1e-5;

/// The conditioning `y` from which the two-mode tail takes its full weight.
pub const CONDITIONING_FULL: f64 = 1e-4;

/// The ratio of the slower mode from which (down) the two-mode tail takes its full weight; it
/// takes none at [`MAX_ORDER_RATIO`].
pub const ORDER_RATIO_FULL: f64 = 0.99;

/// The ratio of the faster mode from which (up) the two-mode tail takes its full weight; it
/// takes none at 0 (an alternating mode).
pub const FAST_RATIO_FULL: f64 = 0.02;

/// An order's size for the closure, per channel: `sum rho |S_k|` over the voxels. The orders of
/// the full series are never negative; those of a warm restart's correction may be, and their
/// absolute values keep the ratio from cancelling.
pub fn order_size(grid: &DensityGrid, order: &[DVec3]) -> DVec3 {
    grid.rho
        .iter()
        .zip(order)
        .fold(DVec3::ZERO, |acc, (rho, s)| acc + s.abs() * *rho)
}

/// The per-order ratio of the last two orders, per channel: `lambda = |S_M| / |S_{M-1}|`
/// ([`order_size`]), clamped to `[0, MAX_ORDER_RATIO]` (0 where the earlier order carries
/// nothing).
pub fn order_ratio(grid: &DensityGrid, last: &[DVec3], before: &[DVec3]) -> DVec3 {
    let (num, den) = (order_size(grid, last), order_size(grid, before));
    DVec3::from_array(std::array::from_fn(|c| geometric_ratio(num[c], den[c])))
}

fn geometric_ratio(last: f64, before: f64) -> f64 {
    if before > 0.0 {
        (last / before).clamp(0.0, MAX_ORDER_RATIO)
    } else {
        0.0
    }
}

/// How the scattering series is closed past its last order `S_M` (docs/illumination.md §4): the
/// orders left over sum to `last S_M + before S_{M-1}`, per channel.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SeriesClosure {
    /// The coefficient of `S_M`.
    pub last: DVec3,
    /// The coefficient of `S_{M-1}`.
    pub before: DVec3,
}

impl SeriesClosure {
    /// The orders past `S_M` taken as geometric with the ratio of the last two order sizes:
    /// `S_M lambda / (1 - lambda)`. `sizes` ends with `|S_{M-1}|, |S_M|`.
    pub fn geometric(sizes: &[DVec3]) -> Self {
        let mut closure = Self::default();
        if let [.., before, last] = sizes {
            for c in 0..3 {
                let lambda = geometric_ratio(last[c], before[c]);
                closure.last[c] = lambda / (1.0 - lambda);
            }
        }
        closure
    }

    /// The orders past `S_M` taken as the sum of two geometric modes, `A r1^k + B r2^k` per
    /// voxel, whose ratios fit the last four order sizes exactly (`sizes` ends with
    /// `|S_{M-3}|, ..., |S_M|`). Their sizes obey `N_{k+2} = p N_{k+1} - q N_k`
    /// (`p = r1 + r2`, `q = r1 r2`), so the tail is `((p - q) S_M - q S_{M-1}) / (1 - p + q)`.
    /// The per-order ratio still rises after the first orders (light reaching the cloud's
    /// inside); one geometric mode holds it at its last value, and shapes the tail like the
    /// last order. Per channel, the two-mode tail is blended with the geometric one by
    /// [`two_mode_weight`], which falls continuously to 0 where the fit stops being two
    /// well-conditioned modes with `0 <= r2 < r1 <= MAX_ORDER_RATIO`, so that the tail never
    /// jumps as the sizes change a little; every channel is closed geometrically where `sizes`
    /// holds fewer than four.
    pub fn two_mode(sizes: &[DVec3]) -> Self {
        let mut closure = Self::geometric(sizes);
        let [.., n0, n1, n2, n3] = sizes else {
            return closure;
        };
        for c in 0..3 {
            if let Some(fit) = TwoModes::fit([n0[c], n1[c], n2[c], n3[c]]) {
                let w = fit.weight;
                closure.last[c] = w * fit.last + (1.0 - w) * closure.last[c];
                closure.before[c] = w * fit.before;
            }
        }
        closure
    }

    /// The orders past `last` (`S_M`; `before`: `S_{M-1}`): `last S_M + before S_{M-1}`, every
    /// moment alike. Where a channel has two modes, its mean is kept between 0 and
    /// `MAX_ORDER_RATIO / (1 - MAX_ORDER_RATIO) S_M`, the tails of one geometric mode from
    /// ratio 0 to the largest, so that no fit can take the solution past the energy bound
    /// ([`energy_bound`]); a geometric tail lies there already, so the bound does not jump as a
    /// channel's two-mode weight reaches 0. `zero`: moments of zeros shaped like the orders.
    pub(super) fn tail(&self, zero: &Moments, last: &Moments, before: &Moments) -> Moments {
        let mut tail = zero.plus(last, self.last).plus(before, self.before);
        let most = MAX_ORDER_RATIO / (1.0 - MAX_ORDER_RATIO);
        for (t, s) in tail.mean.iter_mut().zip(&last.mean) {
            for c in 0..3 {
                if self.before[c] != 0.0 {
                    let bound = most * s[c];
                    t[c] = t[c].clamp(bound.min(0.0), bound.max(0.0));
                }
            }
        }
        tail
    }
}

/// A two-mode fit of one channel's last four order sizes: the tail's coefficients of `S_M` and
/// `S_{M-1}`, and the weight in `(0, 1]` the closure gives them (the geometric tail the rest).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TwoModes {
    /// The coefficient of `S_M`: `(p - q) / (1 - p + q)`.
    pub last: f64,
    /// The coefficient of `S_{M-1}`: `-q / (1 - p + q)`.
    pub before: f64,
    /// [`two_mode_weight`] of the fit.
    pub weight: f64,
}

impl TwoModes {
    /// The fit of the sizes `[N_{M-3}, N_{M-2}, N_{M-1}, N_M]`, or `None` where its weight is 0.
    pub fn fit([n0, n1, n2, n3]: [f64; 4]) -> Option<Self> {
        // N_M = p N_{M-1} - q N_{M-2} and N_{M-1} = p N_{M-2} - q N_{M-3}.
        let det = n1 * n1 - n2 * n0;
        let p = (n1 * n2 - n3 * n0) / det;
        let q = (n2 * n2 - n1 * n3) / det;
        let disc = p * p - 4.0 * q;
        // No real modes (or no fit: NaN).
        if disc.is_nan() || disc < 0.0 {
            return None;
        }
        let (r1, r2) = ((p + disc.sqrt()) / 2.0, (p - disc.sqrt()) / 2.0);
        let weight = two_mode_weight(det.abs() / (n1 * n1), r1, r2);
        let d = 1.0 - p + q;
        (weight > 0.0).then(|| Self {
            last: (p - q) / d,
            before: -q / d,
            weight,
        })
    }
}

/// How much the closure trusts a two-mode fit with `x = |det| / N_{M-2}^2` and ratios
/// `r1 >= r2`: 1 for two well-separated, well-conditioned modes with
/// `FAST_RATIO_FULL <= r2`, `r1 <= ORDER_RATIO_FULL`, `1 - r2 >= MODE_SEPARATION_FULL (1 - r1)`
/// and `x (1 - r1) >= CONDITIONING_FULL`; 0 past `MAX_ORDER_RATIO`, `MODE_SEPARATION` or
/// `CONDITIONING`; a product of ramps between. A switch between the two tails would let a tiny
/// change of the orders (f32 rounding, the order of a GPU's atomic adds) move a bright, thick
/// cloud's light by a few per cent (docs/illumination.md §4).
pub fn two_mode_weight(x: f64, r1: f64, r2: f64) -> f64 {
    let ramp = |v: f64, zero: f64, one: f64| ((v - zero) / (one - zero)).clamp(0.0, 1.0);
    let conditioning = x * (1.0 - r1);
    if !(r1 < 1.0 && conditioning > CONDITIONING) {
        return 0.0;
    }
    ramp(conditioning.ln(), CONDITIONING.ln(), CONDITIONING_FULL.ln())
        * ramp(
            (1.0 - r2) / (1.0 - r1),
            MODE_SEPARATION,
            MODE_SEPARATION_FULL,
        )
        * ramp(r1, MAX_ORDER_RATIO, ORDER_RATIO_FULL)
        * ramp(r2, 0.0, FAST_RATIO_FULL)
}

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
