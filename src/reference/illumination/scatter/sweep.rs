//! One scattering order swept along the lattice directions (or the paper's stencil), and how a
//! sweep carries detail of each spatial frequency.

use super::*;

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
pub(in crate::reference::illumination) struct SweptMedium<'a> {
    pub(in crate::reference::illumination) grid: &'a DensityGrid,
    pub(in crate::reference::illumination) k_local: f64,
    /// The cloud's own albedo (the paper's stencil takes it untransformed).
    pub(in crate::reference::illumination) albedo: f64,
    /// The cloud's own medium, transformed (its true albedo for an isotropic one).
    pub(in crate::reference::illumination) delta: DeltaM,
    /// Per voxel, other clouds' transformed extinction and scattering coefficients in units of
    /// the cloud's own (untransformed) extinction at density 1
    /// (`sum_c c_c K_c rho_c / K`, `sum_c c_c albedo'_c K_c rho_c / K`).
    pub(in crate::reference::illumination) foreign: Option<&'a [[f64; 2]]>,
    /// The directions the sweep carries radiance along.
    pub(in crate::reference::illumination) directions: SweepDirections,
}

impl<'a> SweptMedium<'a> {
    /// A cloud alone: local extinction `k_local`, albedo `albedo`, anisotropy `g`.
    pub(in crate::reference::illumination) fn alone(
        grid: &'a DensityGrid,
        k_local: f64,
        albedo: f64,
        g: f64,
    ) -> Self {
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
    pub(in crate::reference::illumination) fn scattering(&self, i: usize) -> f64 {
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
pub(in crate::reference::illumination) struct Boundary<'a> {
    pub(in crate::reference::illumination) sky: DVec3,
    pub(in crate::reference::illumination) ground: Option<&'a GroundLight>,
}

impl Boundary<'_> {
    /// Nothing enters: the later iterations.
    pub(in crate::reference::illumination) const NONE: Self = Self {
        sky: DVec3::ZERO,
        ground: None,
    };

    /// The sky alone.
    pub(in crate::reference::illumination) fn sky(sky: DVec3) -> Self {
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

pub(in crate::reference::illumination) fn travel(o: [i64; 3]) -> DVec3 {
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
pub(super) fn sweep_direction(
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
pub(in crate::reference::illumination) fn sweep(
    medium: SweptMedium,
    s: &Moments,
    boundary: Boundary,
) -> Moments {
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
pub(super) struct Swept {
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
pub(super) fn paper_stencil(
    grid: &DensityGrid,
    k_local: f64,
    albedo: f64,
    s: &[DVec3],
) -> Vec<DVec3> {
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
