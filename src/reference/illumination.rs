//! f64 CPU reference of the illumination discretization (`docs/illumination.md`).
//!
//! Every stage follows the contract literally so that the GPU passes can be compared with it voxel by
//! voxel: [`voxelize`] (section 1), [`shade`] (section 2), [`gather`] (section 3), [`scatter`]
//! (section 4) and [`CloudIllumination::particle_colours`] (section 5). [`illuminate`] runs them all.
//!
//! All positions and lengths are in cloud-local space (metres of the particle file); extinctions passed
//! in are *local* extinctions `K_local = K * s` (1 per local metre). Radiance-like quantities (`S`,
//! `A`, colours) are in the units of the lights' irradiance `E`.

use std::f64::consts::PI;
use std::ops::{Add, Mul};

use bevy::math::{DQuat, DVec3};
use rayon::prelude::*;

use crate::particle::{LightSample, Medium, Particle, kernel_u2};
use crate::settings::{CloudQualitySettings, ScatterStencil};

// ---------------------------------------------------------------------------------------------
// Trilinear interpolation helpers
// ---------------------------------------------------------------------------------------------

/// The two voxels (index, weight) that one axis of a trilinear lookup touches. `None` is a voxel
/// outside the volume.
type AxisFootprint = [(Option<usize>, f64); 2];

/// Footprint of continuous voxel coordinate `g` (voxel `i` has its centre at `g = i`) with a zero
/// border: voxels outside `0..n` are reported as `None` and the caller treats them as 0.
fn axis_zero_border(g: f64, n: usize) -> AxisFootprint {
    let i0 = g.floor();
    let f = g - i0;
    let inside = |i: f64| (i >= 0.0 && i < n as f64).then_some(i as usize);
    [(inside(i0), 1.0 - f), (inside(i0 + 1.0), f)]
}

/// Footprint of `g` clamped to the edge voxels (a texture's clamp-to-edge addressing).
fn axis_clamped(g: f64, n: usize) -> AxisFootprint {
    let g = g.clamp(0.0, (n - 1) as f64);
    let i0 = g.floor();
    let f = g - i0;
    let i0 = i0 as usize;
    [(Some(i0), 1.0 - f), (Some((i0 + 1).min(n - 1)), f)]
}

/// Trilinear combination over the 8 corners of `axes` (x, y, z footprints) of a volume of side `n`
/// stored with linear index `i + n * (j + n * k)`. Corners outside (`None`) or of zero weight are
/// skipped, so out-of-range indices are never touched.
fn trilinear<T>(axes: [AxisFootprint; 3], n: usize, values: &[T]) -> T
where
    T: Copy + Default + Add<Output = T> + Mul<f64, Output = T>,
{
    let mut acc = T::default();
    for &(k, wk) in &axes[2] {
        for &(j, wj) in &axes[1] {
            for &(i, wi) in &axes[0] {
                let (Some(i), Some(j), Some(k)) = (i, j, k) else {
                    continue;
                };
                let w = wi * wj * wk;
                if w != 0.0 {
                    acc = acc + values[i + n * (j + n * k)] * w;
                }
            }
        }
    }
    acc
}

/// Splits a linear index `i + n * (j + n * k)` into `(i, j, k)`.
#[inline]
fn unravel(idx: usize, n: usize) -> (usize, usize, usize) {
    (idx % n, (idx / n) % n, idx / (n * n))
}

// ---------------------------------------------------------------------------------------------
// 1. Density grid
// ---------------------------------------------------------------------------------------------

/// The cloud's density voxelized on an `n³` cube (contract section 1).
#[derive(Clone, Debug, PartialEq)]
pub struct DensityGrid {
    /// Voxels per side.
    pub n: usize,
    /// Centre `C` of the cube, local metres.
    pub centre: DVec3,
    /// Side `L` of the cube, local metres.
    pub side: f64,
    /// Voxel size `h = L / n`, local metres.
    pub h: f64,
    /// Dimensionless density `rho` at each voxel centre, index `i + n * (j + n * k)`.
    pub rho: Vec<f64>,
}

impl DensityGrid {
    /// Corner `O = C - L/2` of the cube with the smallest coordinates.
    pub fn origin(&self) -> DVec3 {
        self.centre - DVec3::splat(self.side * 0.5)
    }

    /// Linear index of voxel `(i, j, k)`.
    #[inline]
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.n * (j + self.n * k)
    }

    /// Number of voxels, `n³`.
    pub fn len(&self) -> usize {
        self.n * self.n * self.n
    }

    /// Always false: a grid has at least one voxel. (Present for the `len` convention.)
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Centre of voxel `(i, j, k)`: `O + (idx + 0.5) h`.
    pub fn voxel_centre(&self, i: usize, j: usize, k: usize) -> DVec3 {
        self.origin() + (DVec3::new(i as f64, j as f64, k as f64) + 0.5) * self.h
    }

    /// Centre of the voxel with linear index `idx`.
    pub fn voxel_centre_linear(&self, idx: usize) -> DVec3 {
        let (i, j, k) = unravel(idx, self.n);
        self.voxel_centre(i, j, k)
    }

    /// Continuous voxel coordinates of `p` (voxel `(i, j, k)`'s centre maps to `(i, j, k)`).
    pub fn grid_coords(&self, p: DVec3) -> DVec3 {
        (p - self.origin()) / self.h - 0.5
    }

    /// Density at local point `p`: trilinear between voxel centres, voxels outside count as 0.
    pub fn sample(&self, p: DVec3) -> f64 {
        let g = self.grid_coords(p);
        let axes = [0, 1, 2].map(|a| axis_zero_border(g[a], self.n));
        trilinear(axes, self.n, &self.rho)
    }

    /// Any per-voxel quantity `values` (same layout as `rho`) at `p`: trilinear, clamped to the edge
    /// voxels (how the GPU samples the illumination volume).
    pub fn sample_clamped<T>(&self, values: &[T], p: DVec3) -> T
    where
        T: Copy + Default + Add<Output = T> + Mul<f64, Output = T>,
    {
        assert_eq!(
            values.len(),
            self.len(),
            "values must have one entry per voxel"
        );
        let g = self.grid_coords(p);
        let axes = [0, 1, 2].map(|a| axis_clamped(g[a], self.n));
        trilinear(axes, self.n, values)
    }

    /// Largest voxel density `rho_max` (0 for an empty grid).
    pub fn max(&self) -> f64 {
        self.rho.iter().copied().fold(0.0, f64::max)
    }

    /// Total mass `sum rho h³` (m³ times density), the integral of the voxelized field.
    pub fn mass(&self) -> f64 {
        self.rho.iter().sum::<f64>() * self.h.powi(3)
    }
}

/// Bounds `(lo, hi)` of the supports of the particles with `density > 0`, if any.
fn support_bounds(particles: &[Particle]) -> Option<(DVec3, DVec3)> {
    particles
        .iter()
        .filter(|p| p.density > 0.0)
        .fold(None, |acc, p| {
            let c = p.position.as_dvec3();
            let r = DVec3::splat(p.radius as f64);
            let (lo, hi) = (c - r, c + r);
            Some(match acc {
                None => (lo, hi),
                Some((alo, ahi)) => (alo.min(lo), ahi.max(hi)),
            })
        })
}

/// Voxelizes the particles with `density > 0` on an `n³` grid (contract section 1).
///
/// Each particle deposits exactly its mass `Particle::mass()`: large particles (`r >= h`) spread it
/// with kernel-shaped weights over the voxel centres inside their support, sub-voxel particles
/// (`r < h`) with the trilinear weights of their centre. Returns `None` when no particle has
/// `density > 0` (there is no medium to bound). Panics if `n == 0`.
pub fn voxelize(particles: &[Particle], n: usize) -> Option<DensityGrid> {
    assert!(n > 0, "volume resolution must be > 0");
    let (lo, hi) = support_bounds(particles)?;
    let side = (hi - lo).max_element();
    let h = side / n as f64;
    let mut grid = DensityGrid {
        n,
        centre: (lo + hi) * 0.5,
        side,
        h,
        rho: vec![0.0; n * n * n],
    };
    // `rho` holds deposited mass until the final division by the voxel volume.
    for p in particles.iter().filter(|p| p.density > 0.0) {
        let (c, r, m) = (p.position.as_dvec3(), p.radius as f64, p.mass());
        if r < h || !deposit_kernel(&mut grid, c, r, m) {
            deposit_trilinear(&mut grid, c, m);
        }
    }
    let inv_volume = 1.0 / (h * h * h);
    grid.rho.iter_mut().for_each(|v| *v *= inv_volume);
    Some(grid)
}

/// Range of voxel indices on one axis whose centres lie within `[lo, hi]` (grid coordinates, so
/// `lo`/`hi` are already `(x - O) / h - 0.5`), clipped to the grid. Empty when `start > end`.
fn index_range(lo: f64, hi: f64, n: usize) -> (usize, usize) {
    let start = lo.ceil().max(0.0) as usize;
    let end = hi.floor().min((n - 1) as f64);
    if end < 0.0 {
        (1, 0)
    } else {
        (start, end as usize)
    }
}

/// Calls `f(linear index, k(|x_v - c| / r))` for every voxel centre strictly inside the support
/// ball of a particle; only the voxel index box of the support is visited.
fn for_each_support_voxel(grid: &DensityGrid, c: DVec3, r: f64, mut f: impl FnMut(usize, f64)) {
    let (g_lo, g_hi) = (grid.grid_coords(c - r), grid.grid_coords(c + r));
    let ranges = [0, 1, 2].map(|a| index_range(g_lo[a], g_hi[a], grid.n));
    let inv_r2 = 1.0 / (r * r);
    for k in ranges[2].0..=ranges[2].1 {
        for j in ranges[1].0..=ranges[1].1 {
            for i in ranges[0].0..=ranges[0].1 {
                let w = kernel_u2(grid.voxel_centre(i, j, k).distance_squared(c) * inv_r2);
                if w > 0.0 {
                    f(grid.index(i, j, k), w);
                }
            }
        }
    }
}

/// Deposits mass `m` with normalised kernel weights `w_v / W`. Returns false (depositing nothing)
/// if no voxel centre lies inside the support, which cannot happen for `r >= h` (every point of the
/// cube is within `h sqrt(3) / 2 < h` of a voxel centre) but is guarded against rounding.
fn deposit_kernel(grid: &mut DensityGrid, c: DVec3, r: f64, m: f64) -> bool {
    let mut total = 0.0;
    for_each_support_voxel(grid, c, r, |_, w| total += w);
    if total <= 0.0 {
        return false;
    }
    let scale = m / total;
    let mut deposits = Vec::new();
    for_each_support_voxel(grid, c, r, |idx, w| deposits.push((idx, w * scale)));
    deposits
        .into_iter()
        .for_each(|(idx, dm)| grid.rho[idx] += dm);
    true
}

/// Deposits mass `m` on the (up to 8) voxel centres around `c` with trilinear weights; corners
/// outside the grid are dropped and the rest renormalised so the mass is kept exactly.
fn deposit_trilinear(grid: &mut DensityGrid, c: DVec3, m: f64) {
    let g = grid.grid_coords(c);
    let axes = [0, 1, 2].map(|a| axis_zero_border(g[a], grid.n));
    let mut corners = Vec::with_capacity(8);
    for &(k, wk) in &axes[2] {
        for &(j, wj) in &axes[1] {
            for &(i, wi) in &axes[0] {
                if let (Some(i), Some(j), Some(k)) = (i, j, k) {
                    corners.push((grid.index(i, j, k), wi * wj * wk));
                }
            }
        }
    }
    let total: f64 = corners.iter().map(|c| c.1).sum();
    // A centre inside the cube always has an in-grid corner of weight >= 1/8; `total > 0` holds.
    if total > 0.0 {
        corners
            .into_iter()
            .for_each(|(idx, w)| grid.rho[idx] += m * w / total);
    }
}

// ---------------------------------------------------------------------------------------------
// 2. Shade: the light-aligned volume
// ---------------------------------------------------------------------------------------------

/// Orthonormal basis `[u, v, w]` with `w` the given unit vector (Duff et al. 2017, branchless, with
/// `sign(0) = +1` so that `w.z = ±0` is handled like the contract and the WGSL `select`).
pub fn light_basis(w: DVec3) -> [DVec3; 3] {
    let sg = if w.z >= 0.0 { 1.0 } else { -1.0 };
    let a = -1.0 / (sg + w.z);
    let b = w.x * w.y * a;
    let u = DVec3::new(1.0 + sg * w.x * w.x * a, sg * b, -sg * w.x);
    let v = DVec3::new(b, sg + w.y * w.y * a, -w.y);
    [u, v, w]
}

/// One light's transmittance sampled on its light-aligned box (contract section 2).
#[derive(Clone, Debug, PartialEq)]
pub struct LightVolume {
    /// Voxels per axis.
    pub n: usize,
    /// Centre of the box: the density cube's centre `C`, local metres.
    pub centre: DVec3,
    /// `[u, v, w]`, `w` the unit local direction the light travels.
    pub basis: [DVec3; 3],
    /// Half-extents `e` of the box along `u`, `v`, `w`, local metres.
    pub half_extents: DVec3,
    /// Transmittance `T` (dimensionless) at voxel `(a, b, c)`, index `a + n * (b + n * c)`; slice
    /// `c = 0` is nearest the light.
    pub transmittance: Vec<f64>,
}

impl LightVolume {
    /// Voxel sizes `h_a = 2 e_a / n` along `u`, `v`, `w`, local metres.
    pub fn voxel_size(&self) -> DVec3 {
        self.half_extents * 2.0 / self.n as f64
    }

    /// Linear index of voxel `(a, b, c)`.
    #[inline]
    pub fn index(&self, a: usize, b: usize, c: usize) -> usize {
        a + self.n * (b + self.n * c)
    }

    /// Box coordinates `xi = ((p - C).u, (p - C).v, (p - C).w)` of local point `p`.
    pub fn light_coords(&self, p: DVec3) -> DVec3 {
        let d = p - self.centre;
        DVec3::new(
            d.dot(self.basis[0]),
            d.dot(self.basis[1]),
            d.dot(self.basis[2]),
        )
    }

    /// Local position of voxel `(a, b, c)`'s centre, `C + xi_u u + xi_v v + xi_w w`,
    /// `xi = -e + (idx + 0.5) h`.
    pub fn voxel_centre(&self, a: usize, b: usize, c: usize) -> DVec3 {
        let xi = -self.half_extents
            + (DVec3::new(a as f64, b as f64, c as f64) + 0.5) * self.voxel_size();
        self.centre + self.basis[0] * xi.x + self.basis[1] * xi.y + self.basis[2] * xi.z
    }

    /// Transmittance at local point `p`: trilinear in the light box, clamped to the edge voxels.
    pub fn sample_clamped(&self, p: DVec3) -> f64 {
        let g = (self.light_coords(p) + self.half_extents) / self.voxel_size() - 0.5;
        let axes = [0, 1, 2].map(|a| axis_clamped(g[a], self.n));
        trilinear(axes, self.n, &self.transmittance)
    }
}

/// An empty light box for `grid` and the light direction `direction_local` (any non-zero length).
fn light_box(grid: &DensityGrid, direction_local: DVec3) -> LightVolume {
    let w = direction_local
        .try_normalize()
        .expect("light direction must be finite and non-zero");
    let basis = light_basis(w);
    // The cube of side L projected on each axis: (L/2) * |axis|_1.
    let l1 = |a: DVec3| a.abs().element_sum();
    let half_extents = DVec3::new(l1(basis[0]), l1(basis[1]), l1(basis[2])) * (grid.side * 0.5);
    let n = grid.n;
    LightVolume {
        n,
        centre: grid.centre,
        basis,
        half_extents,
        transmittance: vec![0.0; n * n * n],
    }
}

/// Attenuation coefficients `sigma = K_local (1 - f albedo) rho` (1 per local metre) of slice `c`
/// of `vol`, indexed `a + n * b`.
fn slice_sigma(grid: &DensityGrid, vol: &LightVolume, attenuation: f64, c: usize) -> Vec<f64> {
    let n = vol.n;
    (0..n * n)
        .into_par_iter()
        .map(|ab| attenuation * grid.sample(vol.voxel_centre(ab % n, ab / n, c)))
        .collect()
}

/// Transmittance of one light through the cloud on its light-aligned box (contract section 2).
///
/// `k_local`: local extinction (1/local metre); `albedo` in [0, 1]; `forward_scattering` the
/// fraction `f` in [0, 1]; `direction_local`: the direction the light travels, local space, any
/// non-zero length (panics if zero or non-finite). Computed slice by slice away from the light,
/// `T_c = T_{c-1} exp(-(sigma_{c-1} + sigma_c) h_w / 2)`, as the GPU pass does.
pub fn shade(
    grid: &DensityGrid,
    k_local: f64,
    albedo: f64,
    forward_scattering: f64,
    direction_local: DVec3,
) -> LightVolume {
    let mut vol = light_box(grid, direction_local);
    let attenuation = k_local * (1.0 - forward_scattering * albedo);
    let half_step = vol.voxel_size().z * 0.5;
    let slice = vol.n * vol.n;
    let mut prev_sigma = slice_sigma(grid, &vol, attenuation, 0);
    // Slice 0: light enters at the box face, half a voxel before the first centre; sigma is taken
    // constant over that half voxel (the trapezoid's first half step).
    let mut transmittance = std::mem::take(&mut vol.transmittance);
    transmittance[..slice]
        .par_iter_mut()
        .zip(&prev_sigma)
        .for_each(|(t, s)| *t = (-s * half_step).exp());
    for c in 1..vol.n {
        let sigma = slice_sigma(grid, &vol, attenuation, c);
        let (before, after) = transmittance.split_at_mut(c * slice);
        let prev_t = &before[(c - 1) * slice..];
        after[..slice]
            .par_iter_mut()
            .zip(prev_t)
            .zip(prev_sigma.par_iter().zip(&sigma))
            .for_each(|((t, tp), (sp, sc))| *t = tp * (-(sp + sc) * half_step).exp());
        prev_sigma = sigma;
    }
    vol.transmittance = transmittance;
    vol
}

/// The same transmittance as [`shade`], but every voxel marches on its own towards the light through
/// the same sample points (the voxel centres of its column) with the same trapezoid rule, summing
/// the optical depth before a single `exp`. `O(n⁴)`: for verifying [`shade`] only.
pub fn shade_brute_force(
    grid: &DensityGrid,
    k_local: f64,
    albedo: f64,
    forward_scattering: f64,
    direction_local: DVec3,
) -> LightVolume {
    let mut vol = light_box(grid, direction_local);
    let attenuation = k_local * (1.0 - forward_scattering * albedo);
    let h_w = vol.voxel_size().z;
    let n = vol.n;
    let transmittance = (0..n * n * n)
        .into_par_iter()
        .map(|idx| {
            let (a, b, c) = unravel(idx, n);
            let sigma = |k: usize| attenuation * grid.sample(vol.voxel_centre(a, b, k));
            let mut tau = sigma(0) * h_w * 0.5;
            for k in 1..=c {
                tau += (sigma(k - 1) + sigma(k)) * h_w * 0.5;
            }
            (-tau).exp()
        })
        .collect();
    vol.transmittance = transmittance;
    vol
}

// ---------------------------------------------------------------------------------------------
// 3. Gather
// ---------------------------------------------------------------------------------------------

/// Single-scattering source at every density voxel centre (contract section 3):
/// `S_0 = (1 / 4 pi) sum_l E_l T_l(x)`, `T_l` clamped-trilinear in light `l`'s box. Each light is
/// `(volume, irradiance E in linear RGB)`; lights with zero irradiance are skipped. Result in the
/// units of `E` per steradian, one entry per voxel of `grid`.
pub fn gather(grid: &DensityGrid, lights: &[(LightVolume, DVec3)]) -> Vec<DVec3> {
    let lit: Vec<&(LightVolume, DVec3)> =
        lights.iter().filter(|(_, e)| *e != DVec3::ZERO).collect();
    (0..grid.len())
        .into_par_iter()
        .map(|idx| {
            let x = grid.voxel_centre_linear(idx);
            let sum = lit.iter().fold(DVec3::ZERO, |acc, (vol, e)| {
                acc + *e * vol.sample_clamped(x)
            });
            sum / (4.0 * PI)
        })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// 4. Multiple scattering
// ---------------------------------------------------------------------------------------------

/// The 26 neighbour offsets with their length `|o|` in voxels (1, sqrt 2 or sqrt 3).
fn neighbour_offsets() -> Vec<([i64; 3], f64)> {
    let mut out = Vec::with_capacity(26);
    for dz in -1i64..=1 {
        for dy in -1i64..=1 {
            for dx in -1i64..=1 {
                if (dx, dy, dz) != (0, 0, 0) {
                    out.push(([dx, dy, dz], ((dx * dx + dy * dy + dz * dz) as f64).sqrt()));
                }
            }
        }
    }
    out
}

/// `S_{n+1}(v)` for voxel `idx` from the previous order `s` (contract section 4).
fn scatter_voxel(
    grid: &DensityGrid,
    k_local: f64,
    albedo: f64,
    stencil: ScatterStencil,
    offsets: &[([i64; 3], f64)],
    s: &[DVec3],
    idx: usize,
) -> DVec3 {
    let n = grid.n as i64;
    let (i, j, k) = unravel(idx, grid.n);
    let rho_v = grid.rho[idx];
    let weight = albedo / 26.0;
    // 1 - exp(-x), computed without cancellation for small x.
    let opacity = |tau: f64| -(-tau).exp_m1();
    // The paper's stencil weighs every neighbour by the voxel's own opacity over one voxel size.
    let paper_coefficient = weight * opacity(k_local * rho_v * grid.h);
    let mut sum = DVec3::ZERO;
    for &(o, length) in offsets {
        let v = [i as i64, j as i64, k as i64];
        // Hops along `o` that stay inside the grid; none: the neighbour is outside and adds 0.
        let reach = (0..3)
            .map(|a| match o[a].signum() {
                1 => n - 1 - v[a],
                -1 => v[a],
                _ => n,
            })
            .min()
            .unwrap_or(n);
        if reach < 1 {
            continue;
        }
        let step = grid.h * length;
        let hops = match stencil {
            ScatterStencil::FreePath => free_path_hops(k_local * rho_v * step, reach),
            _ => 1,
        };
        let target = [v[0] + hops * o[0], v[1] + hops * o[1], v[2] + hops * o[2]];
        let nidx = grid.index(target[0] as usize, target[1] as usize, target[2] as usize);
        let tau = k_local * (rho_v + grid.rho[nidx]) * 0.5 * step * hops as f64;
        let coefficient = match stencil {
            ScatterStencil::Transmittance => weight * opacity(tau),
            ScatterStencil::Paper => paper_coefficient,
            // The sample stands for the segment twice as long (midpoint rule), cut at the grid's
            // edge: beyond it there is no medium to scatter. (f32 ratio, as on the GPU.)
            ScatterStencil::FreePath => {
                weight * opacity(tau * (reach as f32 / hops as f32).min(2.0) as f64)
            }
        };
        sum += s[nidx] * coefficient;
    }
    sum
}

/// Hops of one lattice step (optical depth `tau_step` each) that make about one mean free path:
/// `floor(1 / tau_step)`, at least 1, at most `reach` (the grid's edge). f32 on the GPU; the
/// floor is taken of the same quotient here.
fn free_path_hops(tau_step: f64, reach: i64) -> i64 {
    let per_hop = tau_step as f32;
    let free = if per_hop * reach as f32 > 1.0 {
        (1.0 / per_hop).floor() as i64
    } else {
        reach
    };
    free.clamp(1, reach)
}

/// Multiple scattering (contract section 4): iterates `S_{n+1} = stencil(S_n)` `iterations` times
/// from `s0` (one entry per voxel) and returns the accumulation `A = S_0 + ... + S_M` (units of
/// `s0`). `k_local` in 1/local metre, `albedo` in [0, 1].
pub fn scatter(
    grid: &DensityGrid,
    k_local: f64,
    albedo: f64,
    stencil: ScatterStencil,
    s0: &[DVec3],
    iterations: u32,
) -> Vec<DVec3> {
    assert_eq!(s0.len(), grid.len(), "s0 must have one entry per voxel");
    let offsets = neighbour_offsets();
    let mut accumulated = s0.to_vec();
    let mut current = s0.to_vec();
    let mut next = vec![DVec3::ZERO; s0.len()];
    for _ in 0..iterations {
        // Once an order is exactly zero every later one is too (the stencil is linear).
        if current.iter().all(|s| *s == DVec3::ZERO) {
            break;
        }
        next.par_iter_mut().enumerate().for_each(|(idx, out)| {
            *out = scatter_voxel(grid, k_local, albedo, stencil, &offsets, &current, idx);
        });
        std::mem::swap(&mut current, &mut next);
        accumulated
            .par_iter_mut()
            .zip(&current)
            .for_each(|(a, s)| *a += *s);
    }
    accumulated
}

/// The documented upper bound on `max A` (any channel): with
/// `q_max = albedo (1 - exp(-K_local rho_max h sqrt 3 * reach))` (`reach` = 1, or `2 n` for
/// free-path hops),
/// `max A <= max_s0 * min(iterations + 1, 1 / (1 - q_max))`. `max_s0` is the largest `S_0` component.
pub fn energy_bound(
    grid: &DensityGrid,
    k_local: f64,
    albedo: f64,
    stencil: ScatterStencil,
    iterations: u32,
    max_s0: f64,
) -> f64 {
    // The longest segment a coefficient stands for: a diagonal neighbour, or for free-path hops
    // twice the grid's diagonal.
    let reach = match stencil {
        ScatterStencil::FreePath => 2.0 * grid.n as f64,
        _ => 1.0,
    };
    let tau_max = k_local * grid.max() * grid.h * 3f64.sqrt() * reach;
    let q_max = albedo * -(-tau_max).exp_m1();
    // For q_max = 1 the geometric factor is infinite and the iteration count bounds A instead.
    let geometric = 1.0 / (1.0 - q_max);
    max_s0 * (iterations as f64 + 1.0).min(geometric)
}

// ---------------------------------------------------------------------------------------------
// All stages and 5. per-particle colours
// ---------------------------------------------------------------------------------------------

/// A directional light in the cloud's local space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalLight {
    /// Direction the light travels, local space; any non-zero length.
    pub direction: DVec3,
    /// Linear RGB irradiance `E` perpendicular to the direction.
    pub irradiance: DVec3,
}

impl LocalLight {
    /// The local light of a world light for a cloud with rotation `rotation`: direction
    /// `normalize(R^-1 d)` (zero if `d` is zero), irradiance unchanged.
    pub fn from_world(light: &LightSample, rotation: DQuat) -> Self {
        Self {
            direction: (rotation.inverse() * light.direction.as_dvec3()).normalize_or_zero(),
            irradiance: light.irradiance.as_dvec3(),
        }
    }
}

/// Everything [`illuminate`] computed for one cloud.
#[derive(Clone, Debug, PartialEq)]
pub struct CloudIllumination {
    /// The density grid (section 1).
    pub grid: DensityGrid,
    /// Local extinction `K_local = K s` used, 1/local metre.
    pub k_local: f64,
    /// The medium's albedo used.
    pub albedo: f64,
    /// Each shaded light's volume with its irradiance (section 2), in input order; lights with zero
    /// irradiance or zero direction are left out.
    pub lights: Vec<(LightVolume, DVec3)>,
    /// Single-scattering source `S_0` per voxel (section 3).
    pub single_scattering: Vec<DVec3>,
    /// Accumulation `A = S_0 + ... + S_M` per voxel (section 4).
    pub accumulated: Vec<DVec3>,
}

/// Runs every stage of the contract for one cloud.
///
/// `scale`: the cloud's uniform world scale `s > 0` (so `K_local = medium.extinction * s`);
/// `lights_local`: directions already in local space (see [`LocalLight::from_world`]). Lights with
/// zero irradiance, or a zero / non-finite direction, are skipped. Returns `None` when no particle
/// has `density > 0`. With no lights everything is zero; with zero extinction `T = 1` and
/// `A = S_0 = sum E / 4 pi`.
pub fn illuminate(
    particles: &[Particle],
    medium: &Medium,
    scale: f64,
    lights_local: &[LocalLight],
    settings: &CloudQualitySettings,
) -> Option<CloudIllumination> {
    let grid = voxelize(particles, settings.volume_resolution as usize)?;
    let k_local = medium.extinction as f64 * scale;
    let albedo = medium.albedo as f64;
    let forward = settings.forward_scattering as f64;
    let lights: Vec<(LightVolume, DVec3)> = lights_local
        .iter()
        .filter(|l| l.irradiance != DVec3::ZERO && l.direction.try_normalize().is_some())
        .map(|l| {
            (
                shade(&grid, k_local, albedo, forward, l.direction),
                l.irradiance,
            )
        })
        .collect();
    let single_scattering = gather(&grid, &lights);
    let accumulated = scatter(
        &grid,
        k_local,
        albedo,
        settings.scatter_stencil,
        &single_scattering,
        settings.scatter_iterations,
    );
    Some(CloudIllumination {
        grid,
        k_local,
        albedo,
        lights,
        single_scattering,
        accumulated,
    })
}

impl CloudIllumination {
    /// Colour of each particle (section 5): `albedo * A(c_i)`, `A` clamped-trilinear at the particle's
    /// local centre. Radiance in the units of `E`.
    pub fn particle_colours(&self, particles: &[Particle], albedo: f64) -> Vec<DVec3> {
        particles
            .par_iter()
            .map(|p| {
                self.grid
                    .sample_clamped(&self.accumulated, p.position.as_dvec3())
                    * albedo
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::math::Vec3;

    fn particle(x: f32, y: f32, z: f32, radius: f32, density: f32) -> Particle {
        Particle {
            position: Vec3::new(x, y, z),
            radius,
            density,
        }
    }

    /// A uniform grid `rho = value` of `n³` voxels of size 1 centred at the origin.
    fn uniform_grid(n: usize, value: f64) -> DensityGrid {
        DensityGrid {
            n,
            centre: DVec3::ZERO,
            side: n as f64,
            h: 1.0,
            rho: vec![value; n * n * n],
        }
    }

    /// Deterministic pseudo-random numbers in [0, 1) (xorshift), so tests need no extra crate.
    fn rng(seed: &mut u64) -> f64 {
        *seed ^= *seed << 13;
        *seed ^= *seed >> 7;
        *seed ^= *seed << 17;
        (*seed >> 11) as f64 / (1u64 << 53) as f64
    }

    fn random_cloud(count: usize, seed: u64) -> Vec<Particle> {
        let mut s = seed;
        (0..count)
            .map(|_| {
                let mut r = || rng(&mut s) as f32;
                particle(
                    r() * 2.0 - 1.0,
                    r() - 0.5,
                    r() * 2.0 - 1.0,
                    0.2 + 0.5 * r(),
                    0.5 + r(),
                )
            })
            .collect()
    }

    fn max_component(values: &[DVec3]) -> f64 {
        values.iter().map(|v| v.max_element()).fold(0.0, f64::max)
    }

    #[test]
    fn light_basis_is_orthonormal_for_axes_and_random_directions() {
        let mut dirs = vec![
            DVec3::X,
            DVec3::NEG_X,
            DVec3::Y,
            DVec3::NEG_Y,
            DVec3::Z,
            DVec3::NEG_Z,
            DVec3::new(0.0, -1.0, 0.0),
            DVec3::new(0.0, 0.0, -1.0),
            DVec3::new(1e-9, -1e-9, -1.0).normalize(),
        ];
        let mut seed = 7;
        for _ in 0..100 {
            let v = DVec3::new(rng(&mut seed), rng(&mut seed), rng(&mut seed)) * 2.0 - 1.0;
            dirs.push(v.normalize());
        }
        for w in dirs {
            let [u, v, w2] = light_basis(w);
            assert_eq!(w2, w);
            for (a, b) in [(u, v), (u, w), (v, w)] {
                assert!(a.dot(b).abs() < 1e-12, "{w}: not orthogonal");
            }
            for a in [u, v] {
                assert!((a.length() - 1.0).abs() < 1e-12, "{w}: not unit");
            }
            assert!((u.cross(v) - w).length() < 1e-12, "{w}: not right-handed");
        }
        // The contract's formula for straight down (w.z = 0, sign(0) = +1): u = +X, v = +Z.
        let [u, v, _] = light_basis(DVec3::NEG_Y);
        assert_eq!((u, v), (DVec3::X, DVec3::Z));
    }

    #[test]
    fn homogeneous_slab_follows_beer_lambert_along_every_axis() {
        // Uniform rho over the cube; for axis-aligned light the light box coincides with the cube,
        // so a voxel at depth (c + 1/2) h from the lit face has T = exp(-K rho depth) exactly (the
        // trapezoid rule is exact for constant sigma).
        let (n, k, rho) = (12, 0.3, 2.0);
        let grid = uniform_grid(n, rho);
        for d in [
            DVec3::X,
            DVec3::NEG_X,
            DVec3::Y,
            DVec3::NEG_Y,
            DVec3::Z,
            DVec3::NEG_Z,
        ] {
            let vol = shade(&grid, k, 0.9, 0.0, d);
            assert_eq!(vol.half_extents, DVec3::splat(n as f64 / 2.0));
            for idx in 0..grid.len() {
                let x = grid.voxel_centre_linear(idx);
                // distance from the face the light enters through
                let depth = x.dot(d) + grid.side / 2.0;
                let expected = (-k * rho * depth).exp();
                let t = vol.sample_clamped(x);
                assert!(
                    (t - expected).abs() < 1e-12 * expected.max(1e-300),
                    "{d}: {t} vs {expected}"
                );
            }
        }
    }

    #[test]
    fn forward_scattering_reduces_attenuation() {
        let grid = uniform_grid(6, 1.0);
        let (k, albedo, f) = (0.5, 0.8, 0.25);
        let vol = shade(&grid, k, albedo, f, DVec3::NEG_Z);
        let x = grid.voxel_centre(0, 0, 0); // deepest for light travelling -Z: depth 5.5
        let expected = (-k * (1.0 - f * albedo) * 5.5).exp();
        assert!((vol.sample_clamped(x) - expected).abs() < 1e-13);
    }

    #[test]
    fn incremental_shade_equals_brute_force() {
        let particles = random_cloud(40, 3);
        let grid = voxelize(&particles, 16).unwrap();
        for d in [
            DVec3::new(0.3, -1.0, 0.2),
            DVec3::NEG_Y,
            DVec3::new(-1.0, 0.1, -0.7),
        ] {
            let fast = shade(&grid, 4.0, 0.9, 0.3, d);
            let slow = shade_brute_force(&grid, 4.0, 0.9, 0.3, d);
            assert_eq!(fast.basis, slow.basis);
            let max_diff = fast
                .transmittance
                .iter()
                .zip(&slow.transmittance)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(max_diff < 1e-12, "max |diff| = {max_diff}");
            // and the cloud does cast a shadow
            assert!(fast.transmittance.iter().copied().fold(1.0, f64::min) < 0.5);
        }
    }

    #[test]
    fn large_particle_keeps_mass_and_column_optical_depth() {
        let p = particle(0.3, -0.2, 0.1, 1.0, 2.0);
        let grid = voxelize(&[p], 64).unwrap();
        assert_eq!(grid.side, 2.0);
        assert!((grid.h - 2.0 / 64.0).abs() < 1e-15);
        assert!((grid.centre - DVec3::new(0.3, -0.2, 0.1)).length() < 1e-6);
        assert!(
            (grid.mass() - p.mass()).abs() < 1e-9 * p.mass(),
            "{} vs {}",
            grid.mass(),
            p.mass()
        );
        // Column optical depth through the centre: integral of rho along a line, times K, against
        // tau_i(0) = K eta r 16/15.
        let k = 3.0;
        let steps = 4000;
        let ds = 2.0 * p.radius as f64 / steps as f64;
        let c = p.position.as_dvec3();
        for axis in [
            DVec3::X,
            DVec3::new(1.0, 1.0, 1.0).normalize(),
            DVec3::new(0.2, -0.9, 0.4).normalize(),
        ] {
            let column: f64 = (0..steps)
                .map(|i| grid.sample(c + axis * (-1.0 + (i as f64 + 0.5) * ds)) * ds)
                .sum();
            let expected = crate::particle::particle_optical_depth(k, 2.0, 1.0, 0.0);
            assert!((expected - k * 2.0 * 16.0 / 15.0).abs() < 1e-12);
            let rel = (k * column - expected).abs() / expected;
            assert!(rel < 0.005, "axis {axis}: relative error {rel}");
        }
    }

    #[test]
    fn sub_voxel_particles_keep_their_mass_exactly() {
        // One large particle sets the grid; tiny ones (r < h) are splatted trilinearly, including
        // one at the very corner of the cube whose out-of-grid corners must be renormalised away.
        let big = particle(0.0, 0.0, 0.0, 1.0, 1.0);
        let grid_only_big = voxelize(&[big], 8).unwrap();
        let h = grid_only_big.h;
        let tiny = [
            particle(0.123, -0.456, 0.321, (h * 0.3) as f32, 50.0),
            // between the cube's corner and the first voxel centre (at -1 + h/2 = -0.875)
            particle(-0.95, -0.95, -0.95, 0.01, 70.0),
            particle(0.96, 0.2, 0.97, 0.001, 1000.0),
        ];
        for t in tiny {
            let grid = voxelize(&[big, t], 8).unwrap();
            assert_eq!(grid.h, h);
            let added = grid.mass() - grid_only_big.mass();
            assert!(
                (added - t.mass()).abs() < 1e-12 * grid.mass(),
                "{added} vs {}",
                t.mass()
            );
        }
        // Zero-density particles neither deposit nor extend the bounds.
        let ghost = particle(10.0, 0.0, 0.0, 5.0, 0.0);
        assert_eq!(voxelize(&[big, ghost], 8).unwrap(), grid_only_big);
        assert!(voxelize(&[ghost], 8).is_none());
        assert!(voxelize(&[], 8).is_none());
    }

    #[test]
    fn density_sampling_is_trilinear_with_zero_border() {
        let mut grid = uniform_grid(4, 0.0);
        let idx = grid.index(1, 2, 3);
        grid.rho[idx] = 8.0;
        let c = grid.voxel_centre(1, 2, 3);
        assert_eq!(grid.sample(c), 8.0);
        assert_eq!(grid.sample(c + DVec3::new(0.5, 0.0, 0.0)), 4.0);
        assert_eq!(
            grid.sample(c + DVec3::new(0.5, -0.5, 0.25)),
            8.0 * 0.5 * 0.5 * 0.75
        );
        // Half a voxel beyond the last centre the zero border gives half the value.
        assert_eq!(grid.sample(c + DVec3::new(0.0, 0.0, 0.5)), 4.0);
        assert_eq!(grid.sample(c + DVec3::new(0.0, 0.0, 1.0)), 0.0);
        // Clamped sampling holds the edge value instead.
        assert_eq!(
            grid.sample_clamped(&grid.rho, c + DVec3::new(0.0, 0.0, 5.0)),
            8.0
        );
        assert_eq!(grid.max(), 8.0);
    }

    #[test]
    fn one_scatter_iteration_matches_hand_computed_coefficients() {
        let (k, albedo, rho) = (0.7, 0.9, 1.5);
        let grid = uniform_grid(3, rho);
        let mut s0 = vec![DVec3::ZERO; 27];
        s0[grid.index(1, 1, 1)] = DVec3::new(1.0, 2.0, 3.0);
        let s1 = |stencil| {
            let a = scatter(&grid, k, albedo, stencil, &s0, 1);
            a.iter().zip(&s0).map(|(a, s)| *a - *s).collect::<Vec<_>>()
        };
        let t = s1(ScatterStencil::Transmittance);
        for (i, j, kk, d) in [
            (0, 1, 1, 1.0),
            (0, 0, 1, 2f64.sqrt()),
            (2, 2, 2, 3f64.sqrt()),
        ] {
            let expected =
                DVec3::new(1.0, 2.0, 3.0) * (albedo / 26.0) * (1.0 - (-k * rho * d).exp());
            assert!((t[grid.index(i, j, kk)] - expected).length() < 1e-15);
        }
        // The centre receives nothing (all its neighbours had S_0 = 0).
        assert_eq!(t[grid.index(1, 1, 1)], DVec3::ZERO);
        let p = s1(ScatterStencil::Paper);
        let expected = DVec3::new(1.0, 2.0, 3.0) * (albedo / 26.0) * (1.0 - (-k * rho).exp());
        for idx in (0..27).filter(|&i| i != grid.index(1, 1, 1)) {
            assert!((p[idx] - expected).length() < 1e-15);
        }
    }

    #[test]
    fn free_path_hops_reach_about_one_mean_free_path() {
        // h = 1, rho = 1, K = 0.3: a face step has optical depth 0.3 -> 3 hops, an edge step
        // 0.42 -> 2 hops, a corner step 0.52 -> 1 hop; each coefficient covers twice the hop.
        let grid = uniform_grid(9, 1.0);
        let s = vec![DVec3::ONE; grid.len()];
        let centre = grid.index(4, 4, 4);
        let out = scatter_voxel(
            &grid,
            0.3,
            0.9,
            ScatterStencil::FreePath,
            &neighbour_offsets(),
            &s,
            centre,
        );
        // Face hops (3 of 4 steps to the edge) cover 4 steps, not 6: the segment stops at the edge.
        let c = |tau: f64, factor: f64| 1.0 - (-tau * factor).exp();
        let expected = 0.9 / 26.0
            * (6.0 * c(0.3 * 3.0, 4.0 / 3.0)
                + 12.0 * c(0.3 * 2f64.sqrt() * 2.0, 2.0)
                + 8.0 * c(0.3 * 3f64.sqrt(), 2.0));
        // The cut ratio is an f32, as on the GPU.
        assert!((out.x - expected).abs() < 1e-8, "{} vs {expected}", out.x);
        // Near the edge hops stop at the last voxel inside; thin voxels hop to the grid's edge.
        assert_eq!(free_path_hops(0.3, 2), 2);
        assert_eq!(free_path_hops(1e-9, 7), 7);
        assert_eq!(free_path_hops(0.0, 7), 7);
        assert_eq!(free_path_hops(5.0, 7), 1);
        // In thin media, free-path hops carry more light per order than one-voxel steps.
        let thin = uniform_grid(9, 0.01);
        let step = scatter_voxel(
            &thin,
            1.0,
            1.0,
            ScatterStencil::Transmittance,
            &neighbour_offsets(),
            &s,
            centre,
        );
        let hop = scatter_voxel(
            &thin,
            1.0,
            1.0,
            ScatterStencil::FreePath,
            &neighbour_offsets(),
            &s,
            centre,
        );
        assert!(hop.x > 3.5 * step.x, "{} vs {}", hop.x, step.x);
    }

    #[test]
    fn scatter_with_albedo_one_stays_below_energy_bound() {
        let particles = random_cloud(30, 11);
        let grid = voxelize(&particles, 12).unwrap();
        // tau_max = 3 gives a geometric factor e^3 ~ 20 (binding after 1000 iterations); K = 50 makes
        // q_max round to ~1 so only the (M + 1) factor bounds A.
        let k_moderate = 3.0 / (grid.max() * grid.h * 3f64.sqrt());
        for k in [k_moderate, 50.0] {
            let vol = shade(&grid, k, 1.0, 0.0, DVec3::new(0.2, -1.0, 0.1));
            let s0 = gather(&grid, &[(vol, DVec3::new(1.0, 0.8, 0.5))]);
            let max_s0 = max_component(&s0);
            let bound = energy_bound(&grid, k, 1.0, ScatterStencil::Transmittance, 1000, max_s0);
            assert!(bound.is_finite());
            if k == k_moderate {
                assert!((bound / max_s0 - 3f64.exp()).abs() < 1e-9);
            }
            for stencil in [
                ScatterStencil::Transmittance,
                ScatterStencil::Paper,
                ScatterStencil::FreePath,
            ] {
                let bound = energy_bound(&grid, k, 1.0, stencil, 1000, max_s0);
                let a = scatter(&grid, k, 1.0, stencil, &s0, 1000);
                assert!(a.iter().all(|v| v.is_finite() && v.min_element() >= 0.0));
                let max_a = max_component(&a);
                assert!(max_a <= bound, "{stencil:?}: {max_a} > {bound}");
                // multiple scattering does add light
                assert!(max_a > 1.01 * max_s0, "{stencil:?}: {max_a} vs {max_s0}");
            }
        }
        // With q_max = 1 the bound falls back to (M + 1) max S_0.
        let opaque = uniform_grid(4, 1e6);
        assert_eq!(
            energy_bound(&opaque, 1e3, 1.0, ScatterStencil::Transmittance, 9, 2.0),
            20.0
        );
    }

    #[test]
    fn zero_extinction_gives_unattenuated_light_everywhere() {
        let particles = random_cloud(20, 5);
        let medium = Medium {
            extinction: 0.0,
            albedo: 0.8,
        };
        let lights = [
            LocalLight {
                direction: DVec3::new(0.0, -1.0, 0.0),
                irradiance: DVec3::new(2.0, 3.0, 4.0),
            },
            LocalLight {
                direction: DVec3::new(1.0, -1.0, 0.5),
                irradiance: DVec3::new(1.0, 0.0, 0.5),
            },
            LocalLight {
                direction: DVec3::X,
                irradiance: DVec3::ZERO,
            },
            LocalLight {
                direction: DVec3::ZERO,
                irradiance: DVec3::ONE,
            },
        ];
        let settings = CloudQualitySettings {
            volume_resolution: 8,
            ..Default::default()
        };
        let ill = illuminate(&particles, &medium, 2.0, &lights, &settings).unwrap();
        assert_eq!(
            ill.lights.len(),
            2,
            "zero irradiance and zero direction lights are skipped"
        );
        for (vol, _) in &ill.lights {
            assert!(vol.transmittance.iter().all(|&t| t == 1.0));
        }
        let expected = DVec3::new(3.0, 3.0, 4.5) / (4.0 * PI);
        for (s, a) in ill.single_scattering.iter().zip(&ill.accumulated) {
            assert!((*s - expected).length() < 1e-15);
            assert_eq!(s, a);
        }
        let colours = ill.particle_colours(&particles, 0.8);
        for c in colours {
            assert!((c - expected * 0.8).length() < 1e-15);
        }
    }

    #[test]
    fn illuminate_is_well_defined_without_lights_or_particles() {
        let settings = CloudQualitySettings {
            volume_resolution: 6,
            ..Default::default()
        };
        let medium = Medium::default();
        assert!(illuminate(&[], &medium, 1.0, &[], &settings).is_none());
        let particles = random_cloud(5, 1);
        let ill = illuminate(&particles, &medium, 1.0, &[], &settings).unwrap();
        assert!(ill.lights.is_empty());
        assert!(ill.accumulated.iter().all(|a| *a == DVec3::ZERO));
        assert!(
            ill.particle_colours(&particles, 0.99)
                .iter()
                .all(|c| *c == DVec3::ZERO)
        );
    }

    #[test]
    fn transmittance_at_centre_of_particle_matches_half_chord() {
        // T at the centre of one particle lit from an oblique direction ~ exp(-K eta r 8/15).
        let p = particle(0.0, 0.0, 0.0, 1.0, 1.0);
        let grid = voxelize(&[p], 64).unwrap();
        let k = 2.0;
        let vol = shade(&grid, k, 1.0, 0.0, DVec3::new(0.4, -1.0, 0.3));
        let tau = -vol.sample_clamped(DVec3::ZERO).ln();
        let expected = k * 8.0 / 15.0;
        assert!(
            (tau - expected).abs() < 0.01 * expected,
            "tau {tau} vs {expected}"
        );
    }

    #[test]
    fn particle_colour_is_albedo_times_accumulation_at_its_centre() {
        let particles = random_cloud(10, 9);
        let medium = Medium {
            extinction: 5.0,
            albedo: 0.7,
        };
        let settings = CloudQualitySettings {
            volume_resolution: 8,
            scatter_iterations: 4,
            ..Default::default()
        };
        let light = LocalLight::from_world(
            &LightSample {
                direction: Vec3::new(0.0, -2.0, 0.0),
                irradiance: Vec3::ONE,
            },
            DQuat::from_rotation_z(0.3),
        );
        assert!((light.direction.length() - 1.0).abs() < 1e-12);
        let ill = illuminate(&particles, &medium, 1.5, &[light], &settings).unwrap();
        assert_eq!(ill.k_local, 7.5);
        // A particle placed exactly on a voxel centre reads that voxel.
        let idx = ill.grid.index(3, 4, 5);
        let centre = ill.grid.voxel_centre(3, 4, 5).as_vec3();
        let probe = particle(centre.x, centre.y, centre.z, 0.1, 1.0);
        let c = ill.particle_colours(&[probe], 0.7)[0];
        let expected = ill.accumulated[idx] * 0.7;
        assert!(
            (c - expected).length() < 1e-4 * expected.length(),
            "{c} vs {expected}"
        );
        assert!(
            ill.accumulated
                .iter()
                .all(|a| a.is_finite() && a.min_element() >= 0.0)
        );
    }
}
