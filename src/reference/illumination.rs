//! f64 CPU reference of the illumination discretization (`docs/illumination.md`).
//!
//! Every stage follows the contract literally so that the GPU passes can be compared with it voxel by
//! voxel: [`voxelize`] (section 1), [`shade`] (section 2), [`gather`] (section 3), [`scatter`]
//! (section 4) and [`CloudIllumination::scattered_at`] (section 5). [`illuminate`] runs them all.
//!
//! All positions and lengths are in cloud-local space (metres of the particle file); extinctions passed
//! in are *local* extinctions `K_local = K * s` (1 per local metre). Radiance-like quantities (`S`,
//! `A`, colours) are in the units of the lights' irradiance `E`.

use std::f64::consts::PI;
use std::ops::{Add, Mul};

use bevy::math::{DQuat, DVec3};
use rayon::prelude::*;

use crate::beam_phase::BeamPhase;
use crate::ground::CloudGround;
use crate::math::{
    density_level, density_level_sizes, henyey_greenstein, kernel_u2, level_kernel_radius,
    light_basis,
};
use crate::particle::{DeltaEddington, LightSample, Medium, Particle};
use crate::reference::composite::CloudPlacement;
use crate::reference::ground::GroundLight;
use crate::settings::{CloudQualitySettings, Compositing, ScatterStencil};
use crate::shadow_maps::{SKY_MAP_DIRECTIONS, ShadowMapPlacement, sky_direction_among};

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
    trilinear_of(axes, n, |i| values[i])
}

/// [`trilinear`] of the values `value(i)` of the voxels `i`.
fn trilinear_of<T>(axes: [AxisFootprint; 3], n: usize, value: impl Fn(usize) -> T) -> T
where
    T: Default + Add<Output = T> + Mul<f64, Output = T>,
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
                    acc = acc + value(i + n * (j + n * k)) * w;
                }
            }
        }
    }
    acc
}

/// Per-voxel arrays as [`trilinear_of`] combines them.
struct Entries<const K: usize>([DVec3; K]);

impl<const K: usize> Default for Entries<K> {
    fn default() -> Self {
        Self([DVec3::ZERO; K])
    }
}

impl<const K: usize> Add for Entries<K> {
    type Output = Self;
    fn add(self, other: Self) -> Self {
        Self(std::array::from_fn(|i| self.0[i] + other.0[i]))
    }
}

impl<const K: usize> Mul<f64> for Entries<K> {
    type Output = Self;
    fn mul(self, w: f64) -> Self {
        Self(self.0.map(|v| v * w))
    }
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
        self.sample_clamped_of(values.len(), p, |i| values[i])
    }

    /// [`DensityGrid::sample_clamped`] of per-voxel arrays (a [`Flux`], a [`Quadrupole`]), entry
    /// by entry.
    pub fn sample_clamped_array<const K: usize>(
        &self,
        values: &[[DVec3; K]],
        p: DVec3,
    ) -> [DVec3; K] {
        self.sample_clamped_of(values.len(), p, |i| Entries(values[i]))
            .0
    }

    /// The trilinear, edge-clamped sample at `p` of the `len` per-voxel values `value(i)`.
    fn sample_clamped_of<T>(&self, len: usize, p: DVec3, value: impl Fn(usize) -> T) -> T
    where
        T: Default + Add<Output = T> + Mul<f64, Output = T>,
    {
        assert_eq!(len, self.len(), "values must have one entry per voxel");
        let g = self.grid_coords(p);
        let axes = [0, 1, 2].map(|a| axis_clamped(g[a], self.n));
        trilinear_of(axes, self.n, value)
    }

    /// Largest voxel density `rho_max` (0 for an empty grid).
    pub fn max(&self) -> f64 {
        self.rho.iter().copied().fold(0.0, f64::max)
    }

    /// Total mass `sum rho h³` (m³ times density), the integral of the voxelized field.
    pub fn mass(&self) -> f64 {
        self.rho.iter().sum::<f64>() * self.h.powi(3)
    }

    /// The same cube at `n / f` voxels per side, each the mean of its `f³` children (mass-exact;
    /// contract section 1). `f` must divide `n`.
    pub fn downsample(&self, f: usize) -> DensityGrid {
        assert!(
            f > 0 && self.n.is_multiple_of(f),
            "{f} must divide {}",
            self.n
        );
        let n = self.n / f;
        let mut rho = vec![0.0; n * n * n];
        for (idx, value) in self.rho.iter().enumerate() {
            let (i, j, k) = unravel(idx, self.n);
            rho[i / f + n * (j / f + n * (k / f))] += value;
        }
        let children = (f * f * f) as f64;
        rho.iter_mut().for_each(|r| *r /= children);
        DensityGrid {
            n,
            centre: self.centre,
            side: self.side,
            h: self.h * f as f64,
            rho,
        }
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
/// Each particle deposits exactly its mass `Particle::mass()` on its density level (the finest on
/// which its radius spans at most 16 voxels, [`density_level`]): large particles (`r >= h`) spread it
/// with kernel-shaped weights over the level's voxel centres inside their support, sub-voxel
/// particles (`r < h`) with the trilinear weights of their centre. The levels are then enlarged
/// into the fine grid, coarsest first (`upsample_into`), which keeps their mass. Returns `None`
/// when no particle has `density > 0` (there is no medium to bound). Panics if `n == 0`.
pub fn voxelize(particles: &[Particle], n: usize) -> Option<DensityGrid> {
    assert!(n > 0, "volume resolution must be > 0");
    let (lo, hi) = support_bounds(particles)?;
    let side = (hi - lo).max_element();
    let h = side / n as f64;
    let fine = DensityGrid {
        n,
        centre: (lo + hi) * 0.5,
        side,
        h,
        rho: vec![0.0; n * n * n],
    };
    let mut levels = density_levels(fine);
    // `rho` holds deposited mass until the division by each level's voxel volume.
    for p in particles.iter().filter(|p| p.density > 0.0) {
        let (c, r, m) = (p.position.as_dvec3(), p.radius as f64, p.mass());
        let level = density_level(r / h, levels.len());
        let grid = &mut levels[level];
        let shape = level_kernel_radius(r, h, grid.h);
        if r < grid.h || !deposit_kernel(grid, c, shape, m) {
            deposit_trilinear(grid, c, m);
        }
    }
    for grid in &mut levels {
        let inv_volume = 1.0 / grid.h.powi(3);
        grid.rho.iter_mut().for_each(|v| *v *= inv_volume);
    }
    while let Some(coarse) = levels.pop() {
        match levels.last_mut() {
            Some(finer) => upsample_into(finer, &coarse),
            None => return Some(coarse),
        }
    }
    unreachable!("there is at least the fine level")
}

/// The empty density levels of `fine` ([`density_level_sizes`]): level `l` has voxels `2^l` times
/// as wide, from the same origin (so an odd level's last voxel reaches past the cube).
fn density_levels(fine: DensityGrid) -> Vec<DensityGrid> {
    let origin = fine.origin();
    let sizes = density_level_sizes(fine.n as u32);
    let mut levels = vec![fine];
    for (l, &n) in sizes.iter().enumerate().skip(1) {
        let n = n as usize;
        let h = levels[0].h * (1u32 << l) as f64;
        let side = n as f64 * h;
        levels.push(DensityGrid {
            n,
            centre: origin + DVec3::splat(side * 0.5),
            side,
            h,
            rho: vec![0.0; n * n * n],
        });
    }
    levels
}

/// The coarse voxels `(index, density weight)` that fine voxel `i` of a level of `fine_n` takes its
/// density from, one axis of the level above (`coarse_n` voxels). Coarse voxel `J` gives 1/8, 3/8,
/// 3/8 and 1/8 of its mass to fine voxels `2J - 1 ..= 2J + 2`; a share that would leave the level
/// goes to its edge voxel instead, so no mass is lost. Density weights are twice the mass shares
/// (a fine voxel is half as wide); inside, they are trilinear interpolation's.
fn prolongation(i: usize, fine_n: usize, coarse_n: usize) -> Vec<(usize, f64)> {
    const SHARES: [(i64, f64); 4] = [(-1, 0.125), (0, 0.375), (1, 0.375), (2, 0.125)];
    let mut weights = Vec::with_capacity(3);
    for j in (i / 2).saturating_sub(1)..=(i / 2 + 1).min(coarse_n - 1) {
        let w: f64 = SHARES
            .iter()
            .filter(|(d, _)| (2 * j as i64 + d).clamp(0, fine_n as i64 - 1) == i as i64)
            .map(|(_, share)| 2.0 * share)
            .sum();
        if w > 0.0 {
            weights.push((j, w));
        }
    }
    weights
}

/// Adds level `coarse` (densities), enlarged by [`prolongation`] on every axis, to the level below.
fn upsample_into(fine: &mut DensityGrid, coarse: &DensityGrid) {
    let axis: Vec<Vec<(usize, f64)>> = (0..fine.n)
        .map(|i| prolongation(i, fine.n, coarse.n))
        .collect();
    let n = fine.n;
    for (idx, value) in fine.rho.iter_mut().enumerate() {
        let (i, j, k) = unravel(idx, n);
        for &(c, wk) in &axis[k] {
            for &(b, wj) in &axis[j] {
                for &(a, wi) in &axis[i] {
                    *value += wi * wj * wk * coarse.rho[coarse.index(a, b, c)];
                }
            }
        }
    }
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

/// One light's optical depth sampled on its light-aligned box (contract section 2).
#[derive(Clone, Debug, PartialEq)]
pub struct LightVolume {
    /// Voxels per axis, `m = volume_resolution * light_supersampling` (at most 256).
    pub n: usize,
    /// Centre of the box: the density cube's centre `C`, local metres.
    pub centre: DVec3,
    /// `[u, v, w]`, `w` the unit local direction the light travels.
    pub basis: [DVec3; 3],
    /// Half-extents `e` of the box along `u`, `v`, `w`, local metres.
    pub half_extents: DVec3,
    /// Optical depth `tau` (dimensionless) from the light to voxel `(a, b, c)`, index
    /// `a + n * (b + n * c)`; slice `c = 0` is nearest the light.
    pub optical_depth: Vec<f64>,
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

    /// Optical depth at local point `p`: trilinear in the light box, clamped to the edge voxels.
    /// Interpolating the optical depth rather than the transmittance keeps `exp`'s curvature out
    /// of the interpolation error.
    pub fn optical_depth_at(&self, p: DVec3) -> f64 {
        let g = (self.light_coords(p) + self.half_extents) / self.voxel_size() - 0.5;
        let axes = [0, 1, 2].map(|a| axis_clamped(g[a], self.n));
        trilinear(axes, self.n, &self.optical_depth)
    }

    /// Transmittance `exp(-tau)` towards the light at local point `p`.
    pub fn transmittance_at(&self, p: DVec3) -> f64 {
        (-self.optical_depth_at(p)).exp()
    }

    /// The optical depth this cloud casts on a point `p` of another cloud (in this cloud's local
    /// space; contract section 2, "Clouds shadow each other"): 0 beside the box (across the
    /// light) and before it (towards the light), where the light's column holds none of this
    /// cloud; inside and past the box, [`optical_depth_at`](Self::optical_depth_at), whose
    /// clamp carries the last slice (the whole column) on past the box.
    pub fn cast_depth_at(&self, p: DVec3) -> f64 {
        let g = (self.light_coords(p) + self.half_extents) / self.voxel_size() - 0.5;
        let edge = self.n as f64 - 0.5;
        if g.x < -0.5 || g.x > edge || g.y < -0.5 || g.y > edge || g.z < -0.5 {
            return 0.0;
        }
        self.optical_depth_at(p)
    }
}

/// An empty light box of `n` voxels per side for `grid` and the light direction `direction_local`
/// (any non-zero length).
fn light_box(grid: &DensityGrid, n: usize, direction_local: DVec3) -> LightVolume {
    let w = direction_local
        .try_normalize()
        .expect("light direction must be finite and non-zero");
    let basis = light_basis(w);
    // The cube of side L projected on each axis: (L/2) * |axis|_1.
    let l1 = |a: DVec3| a.abs().element_sum();
    let half_extents = DVec3::new(l1(basis[0]), l1(basis[1]), l1(basis[2])) * (grid.side * 0.5);
    LightVolume {
        n,
        centre: grid.centre,
        basis,
        half_extents,
        optical_depth: vec![0.0; n * n * n],
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

/// How one light is shaded (contract section 2).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ShadeInputs {
    /// Local extinction `K_local` (1/local metre).
    pub k_local: f64,
    /// Single-scattering albedo in [0, 1].
    pub albedo: f64,
    /// Forward-scattering fraction `f` in [0, 1].
    pub forward_scattering: f64,
    /// Voxels per side of the light box.
    pub resolution: usize,
}

impl ShadeInputs {
    fn attenuation(&self) -> f64 {
        self.k_local * (1.0 - self.forward_scattering * self.albedo)
    }
}

/// Optical depth of one light through the cloud on its light-aligned box (contract section 2).
///
/// `direction_local`: the direction the light travels, local space, any non-zero length (panics
/// if zero or non-finite). Computed slice by slice away from the light,
/// `tau_c = tau_{c-1} + (sigma_{c-1} + sigma_c) h_w / 2`, as the GPU pass does.
pub fn shade(grid: &DensityGrid, inputs: &ShadeInputs, direction_local: DVec3) -> LightVolume {
    let mut vol = light_box(grid, inputs.resolution, direction_local);
    let attenuation = inputs.attenuation();
    let half_step = vol.voxel_size().z * 0.5;
    let slice = vol.n * vol.n;
    let mut prev_sigma = slice_sigma(grid, &vol, attenuation, 0);
    // Slice 0: light enters at the box face, half a voxel before the first centre; sigma is taken
    // constant over that half voxel (the trapezoid's first half step).
    let mut depth = std::mem::take(&mut vol.optical_depth);
    depth[..slice]
        .par_iter_mut()
        .zip(&prev_sigma)
        .for_each(|(t, s)| *t = s * half_step);
    for c in 1..vol.n {
        let sigma = slice_sigma(grid, &vol, attenuation, c);
        let (before, after) = depth.split_at_mut(c * slice);
        let prev = &before[(c - 1) * slice..];
        after[..slice]
            .par_iter_mut()
            .zip(prev)
            .zip(prev_sigma.par_iter().zip(&sigma))
            .for_each(|((t, tp), (sp, sc))| *t = tp + (sp + sc) * half_step);
        prev_sigma = sigma;
    }
    vol.optical_depth = depth;
    vol
}

/// The same optical depth as [`shade`], but every voxel marches on its own towards the light
/// through the same sample points with the same trapezoid rule. `O(n⁴)`: for verifying [`shade`]
/// only.
pub fn shade_brute_force(
    grid: &DensityGrid,
    inputs: &ShadeInputs,
    direction_local: DVec3,
) -> LightVolume {
    let mut vol = light_box(grid, inputs.resolution, direction_local);
    let attenuation = inputs.attenuation();
    let h_w = vol.voxel_size().z;
    let n = vol.n;
    let depth = (0..n * n * n)
        .into_par_iter()
        .map(|idx| {
            let (a, b, c) = unravel(idx, n);
            let sigma = |k: usize| attenuation * grid.sample(vol.voxel_centre(a, b, k));
            let mut tau = sigma(0) * h_w * 0.5;
            for k in 1..=c {
                tau += (sigma(k - 1) + sigma(k)) * h_w * 0.5;
            }
            tau
        })
        .collect();
    vol.optical_depth = depth;
    vol
}

// ---------------------------------------------------------------------------------------------
// 3. Single scattering and the scattering source
// ---------------------------------------------------------------------------------------------

/// Single scattering `S_1(p) = (1 / 4 pi) sum_l E_l exp(-tau_l(p))` at local point `p`, straight
/// from the lights' volumes (each `(volume, irradiance E)`); units of `E` per steradian. The
/// isotropic medium's, seen from any direction.
pub fn single_scattering_at(lights: &[(LightVolume, DVec3)], p: DVec3) -> DVec3 {
    lights.iter().fold(DVec3::ZERO, |acc, (vol, e)| {
        acc + *e * vol.transmittance_at(p)
    }) / (4.0 * PI)
}

/// Single scattering towards the camera at local point `p` of a medium of albedo `albedo` and
/// anisotropy `g` (section 5): `S_1(p, w) = sum_l p_HG(g, d_l . (-w)) E_l (exp(-tau_l(p)) +
/// (exp(-c tau_l(p)) - exp(-tau_l(p))) r)`, `w` the unit local direction of the view ray (from
/// the camera), `d_l` the light's travel direction, `c` the δ-Eddington depth scale
/// ([`DeltaEddington::depth_scale`]) and `r` the `beam` table's spread of the excess at
/// `m = (1 - c) tau_l` (1 without a table). [`single_scattering_at`] for `g = 0`.
pub fn single_scattering_towards(
    lights: &[(LightVolume, DVec3)],
    p: DVec3,
    (albedo, g): (f64, f64),
    ray: DVec3,
    beam: Option<&BeamPhase>,
) -> DVec3 {
    let scale = DeltaEddington::new(albedo, g).depth_scale;
    lights.iter().fold(DVec3::ZERO, |acc, (vol, e)| {
        let cos = -vol.basis[2].dot(ray);
        let phase = henyey_greenstein(g, cos);
        let tau = vol.optical_depth_at(p);
        let unscattered = (-tau).exp();
        let excess = (-tau * scale).exp() - unscattered;
        let spread = beam.map_or(1.0, |table| table.ratio(cos, tau * (1.0 - scale)));
        acc + *e * ((unscattered + excess * spread) * phase)
    })
}

/// The first angular moment of a radiance field at a voxel, `(1/4π) ∫ L ω dω`: one RGB per axis
/// (x, y, z), in the units of `E` per steradian (contract section 4).
pub type Flux = [DVec3; 3];

/// The second angular moment of a radiance field at a voxel without its trace,
/// `(1/4π) ∫ L (ω ω^T - I/3) dω`: the RGB of its `xx, yy, xy, xz, yz` entries (`zz = -xx - yy`).
pub type Quadrupole = [DVec3; 5];

/// The entries of [`Quadrupole`] for one unit direction `w`: `w w^T - I/3` at `xx, yy, xy, xz, yz`.
pub fn quadrupole_basis(w: DVec3) -> [f64; 5] {
    [
        w.x * w.x - 1.0 / 3.0,
        w.y * w.y - 1.0 / 3.0,
        w.x * w.y,
        w.x * w.z,
        w.y * w.z,
    ]
}

/// `w^T Q w` for unit `w`.
fn quadrupole_along(q: &Quadrupole, w: DVec3) -> DVec3 {
    let zz = -(q[0] + q[1]);
    q[0] * (w.x * w.x)
        + q[1] * (w.y * w.y)
        + zz * (w.z * w.z)
        + (q[2] * (w.x * w.y) + q[3] * (w.x * w.z) + q[4] * (w.y * w.z)) * 2.0
}

/// `F . w` for unit `w`.
fn flux_along(f: &Flux, w: DVec3) -> DVec3 {
    f[0] * w.x + f[1] * w.y + f[2] * w.z
}

/// A source or an order of the multiple scattering over the scattering grid (contract
/// section 4): per voxel the mean radiance `(1/4π) ∫ L dω` (`S` of an isotropic medium) and, for
/// an anisotropic medium, the [`Flux`]; `flux` is empty for an isotropic one.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Moments {
    /// Mean radiance per voxel.
    pub mean: Vec<DVec3>,
    /// First angular moment per voxel; empty for an isotropic medium.
    pub flux: Vec<Flux>,
}

impl Moments {
    /// An isotropic source or order.
    pub fn isotropic(mean: Vec<DVec3>) -> Self {
        Self {
            mean,
            flux: Vec::new(),
        }
    }

    /// `self + k other`, voxel by voxel.
    fn plus(&self, other: &Moments, k: DVec3) -> Moments {
        Moments {
            mean: zip_with(&self.mean, &other.mean, |a, b| *a + *b * k),
            flux: zip_with(&self.flux, &other.flux, |a, b| {
                std::array::from_fn(|i| a[i] + b[i] * k)
            }),
        }
    }
}

fn zip_with<T, U>(a: &[T], b: &[T], f: impl Fn(&T, &T) -> U) -> Vec<U> {
    a.iter().zip(b).map(|(a, b)| f(a, b)).collect()
}

/// The multiple-scattering source `S_0` of every voxel of `grid` (contract section 3): the
/// density-weighted mean of [`single_scattering_at`] over the centres of its `f³` children in
/// `fine` (`f = fine.n / grid.n`), weighted by their density, or their plain mean where all of
/// them are empty. Lights with zero irradiance may be left out.
pub fn gather(
    grid: &DensityGrid,
    fine: &DensityGrid,
    lights: &[(LightVolume, DVec3)],
) -> Vec<DVec3> {
    gather_source(grid, fine, lights, DeltaEddington::new(1.0, 0.0)).mean
}

/// [`gather`] for a medium of δ-Eddington transform `delta` (contract section 3): the lights'
/// beams seen through `delta.depth_scale` of their optical depth, `E_l exp(-c tau_l) / 4π`, and,
/// for an anisotropic medium, their flux `E_l exp(-c tau_l) d_l / 4π` (the moments of a
/// collimated beam), density-weighted alike.
pub fn gather_source(
    grid: &DensityGrid,
    fine: &DensityGrid,
    lights: &[(LightVolume, DVec3)],
    delta: DeltaEddington,
) -> Moments {
    let f = fine.n / grid.n;
    let beams = |p: DVec3| {
        lights
            .iter()
            .fold((DVec3::ZERO, [DVec3::ZERO; 3]), |(m, fl), (vol, e)| {
                let t = *e * (-vol.optical_depth_at(p) * delta.depth_scale).exp() / (4.0 * PI);
                let d = vol.basis[2];
                (m + t, [fl[0] + t * d.x, fl[1] + t * d.y, fl[2] + t * d.z])
            })
    };
    let voxels: Vec<(DVec3, Flux)> = (0..grid.len())
        .into_par_iter()
        .map(|idx| {
            let (i, j, k) = unravel(idx, grid.n);
            let (mut weighted, mut mass, mut plain) = (
                (DVec3::ZERO, [DVec3::ZERO; 3]),
                0.0,
                (DVec3::ZERO, [DVec3::ZERO; 3]),
            );
            for child in 0..f * f * f {
                let (a, b, c) = unravel(child, f);
                let (fi, fj, fk) = (i * f + a, j * f + b, k * f + c);
                let (m, fl) = beams(fine.voxel_centre(fi, fj, fk));
                let rho = fine.rho[fine.index(fi, fj, fk)];
                weighted.0 += m * rho;
                plain.0 += m;
                for ((w, p), f) in weighted.1.iter_mut().zip(&mut plain.1).zip(fl) {
                    *w += f * rho;
                    *p += f;
                }
                mass += rho;
            }
            let (sum, count) = if mass > 0.0 {
                (weighted, mass)
            } else {
                (plain, (f * f * f) as f64)
            };
            (sum.0 / count, sum.1.map(|a| a / count))
        })
        .collect();
    let (mean, flux) = voxels.into_iter().unzip();
    Moments {
        mean,
        flux: if delta.anisotropy != 0.0 {
            flux
        } else {
            Vec::new()
        },
    }
}

// ---------------------------------------------------------------------------------------------
// 4. Multiple scattering
// ---------------------------------------------------------------------------------------------

/// The 26 lattice directions `o` (components in {-1, 0, 1}, not all 0).
pub fn lattice_directions() -> Vec<[i64; 3]> {
    let mut out = Vec::with_capacity(26);
    for dz in -1i64..=1 {
        for dy in -1i64..=1 {
            for dx in -1i64..=1 {
                if (dx, dy, dz) != (0, 0, 0) {
                    out.push([dx, dy, dz]);
                }
            }
        }
    }
    out
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
/// cloud's density and its medium's δ-Eddington transform, and the media of other clouds where
/// they reach into its cube (section 4, "Clouds that overlap").
#[derive(Clone, Copy)]
struct SweptMedium<'a> {
    grid: &'a DensityGrid,
    k_local: f64,
    /// The cloud's own albedo (the paper's stencil takes it untransformed).
    albedo: f64,
    /// The cloud's own medium, transformed (its true albedo for an isotropic one).
    delta: DeltaEddington,
    /// Per voxel, other clouds' transformed extinction and scattering coefficients in units of
    /// the cloud's own (untransformed) extinction at density 1
    /// (`sum_c c_c K_c rho_c / K`, `sum_c c_c albedo'_c K_c rho_c / K`).
    foreign: Option<&'a [[f64; 2]]>,
}

impl<'a> SweptMedium<'a> {
    /// A cloud alone: local extinction `k_local`, albedo `albedo`, anisotropy `g`.
    fn alone(grid: &'a DensityGrid, k_local: f64, albedo: f64, g: f64) -> Self {
        Self {
            grid,
            k_local,
            albedo,
            delta: DeltaEddington::new(albedo, g),
            foreign: None,
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

    /// `J = albedo S(w)` at voxel `i` towards the unit direction `w`, with the P1 phase function
    /// of the cloud's transformed anisotropy `g'`: `albedo (mean + 3 g' F . w)`.
    fn source(&self, s: &Moments, i: usize, w: DVec3) -> DVec3 {
        let mean = s.mean[i];
        let directional = match s.flux.get(i) {
            Some(f) => flux_along(f, w) * (3.0 * self.delta.anisotropy),
            None => DVec3::ZERO,
        };
        (mean + directional) * self.albedo(i)
    }
}

/// What enters a cloud's grid from outside in an iteration that brings the boundary in (section
/// 4): the sky's radiance from every side, and with a ground, the ground's on the lattice lines
/// that climb.
#[derive(Clone, Copy)]
struct Boundary<'a> {
    sky: DVec3,
    ground: Option<&'a GroundLight>,
}

impl Boundary<'_> {
    /// Nothing enters: the later iterations.
    const NONE: Self = Self {
        sky: DVec3::ZERO,
        ground: None,
    };

    /// The sky alone.
    fn sky(sky: DVec3) -> Self {
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
fn travel(o: [i64; 3]) -> DVec3 {
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

/// One discrete-ordinates iteration (section 4): the next order's moments over the 26 lattice
/// directions, each weighing `1/26`, `mean = sum_o I_o / 26`, and for an anisotropic medium (one
/// whose source has a flux) `F = sum_o I_o w_o / 26` and the quadrupole
/// `sum_o I_o (w_o w_o^T - I/3) / 26`, `w_o` the radiance's travel direction; the radiance
/// `boundary` gives entering the grid from outside.
fn sweep(medium: SweptMedium, s: &Moments, boundary: Boundary) -> (Moments, Vec<Quadrupole>) {
    let directional = !s.flux.is_empty();
    let voxels = s.mean.len();
    let empty = || Swept {
        mean: vec![DVec3::ZERO; voxels],
        flux: vec![[DVec3::ZERO; 3]; if directional { voxels } else { 0 }],
        quadrupole: vec![[DVec3::ZERO; 5]; if directional { voxels } else { 0 }],
    };
    let swept = lattice_directions()
        .into_par_iter()
        .map(|o| {
            let radiance = sweep_direction(medium, o, s, boundary);
            let mut out = empty();
            let w = travel(o);
            let q = quadrupole_basis(w);
            for (i, r) in radiance.into_iter().enumerate() {
                let share = r / 26.0;
                out.mean[i] = share;
                if directional {
                    out.flux[i] = [share * w.x, share * w.y, share * w.z];
                    out.quadrupole[i] = q.map(|q| share * q);
                }
            }
            out
        })
        .reduce(empty, Swept::add);
    (
        Moments {
            mean: swept.mean,
            flux: swept.flux,
        },
        swept.quadrupole,
    )
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

/// Largest per-order ratio `lambda` the series closure assumes.
pub const MAX_ORDER_RATIO: f64 = 0.995;

/// The per-order ratio of the last two orders, per channel:
/// `lambda = sum rho |S_M| / sum rho |S_{M-1}|`, clamped to `[0, MAX_ORDER_RATIO]` (0 where the
/// earlier order carries nothing). The orders of the full series are never negative; those of a
/// warm restart's correction may be, and their absolute values keep the ratio from cancelling.
pub fn order_ratio(grid: &DensityGrid, last: &[DVec3], before: &[DVec3]) -> DVec3 {
    let weighted = |s: &[DVec3]| {
        grid.rho
            .iter()
            .zip(s)
            .fold(DVec3::ZERO, |acc, (rho, s)| acc + s.abs() * *rho)
    };
    let (num, den) = (weighted(last), weighted(before));
    let ratio = |a: f64, b: f64| {
        if b > 0.0 {
            (a / b).clamp(0.0, MAX_ORDER_RATIO)
        } else {
            0.0
        }
    };
    DVec3::new(
        ratio(num.x, den.x),
        ratio(num.y, den.y),
        ratio(num.z, den.z),
    )
}

/// Multiple scattering, every order past the first (contract section 4).
#[derive(Clone, Debug, PartialEq)]
pub struct MultipleScattering {
    /// `S_1, ..., S_M` (one mean per voxel each), the orders computed.
    pub orders: Vec<Vec<DVec3>>,
    /// The closure's per-channel ratio `lambda` (zero for `M = 0`).
    pub ratio: DVec3,
    /// `sum_{n=1..M} S_n + S_M lambda / (1 - lambda)` per voxel (the means).
    pub total: Vec<DVec3>,
    /// The same sum of the orders' [`Flux`]es, closed alike; empty for an isotropic medium.
    pub flux: Vec<Flux>,
    /// The sum of the orders' [`Quadrupole`]s (the closure's tail adds none: the light of the
    /// late orders is nearly isotropic); empty for an isotropic medium.
    pub quadrupole: Vec<Quadrupole>,
}

impl MultipleScattering {
    /// The solution's mean and flux, as a warm restart starts from it.
    pub fn moments(&self) -> Moments {
        Moments {
            mean: self.total.clone(),
            flux: self.flux.clone(),
        }
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
/// medium's δ-Eddington transform, with the P1 source of its asymmetry `g'`, from the source
/// `s0` of [`gather_source`] (with its flux unless `g = 0`).
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
fn scatter_through(
    medium: SweptMedium,
    stencil: ScatterStencil,
    s0: &Moments,
    boundary: Boundary,
    iterations: u32,
) -> MultipleScattering {
    let mut series = scatter_series(medium, stencil, s0, boundary, iterations);
    series
        .total
        .iter_mut()
        .for_each(|t| *t = t.max(DVec3::ZERO));
    series
}

/// The orders of the series from `s0` and their closed sum, signed (a warm restart's correction
/// may be negative).
fn scatter_series(
    medium: SweptMedium,
    stencil: ScatterStencil,
    s0: &Moments,
    boundary: Boundary,
    iterations: u32,
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
    let mut quadrupole = vec![[DVec3::ZERO; 5]; s0.flux.len()];
    let (mut total, mut last, mut before) = (zero.clone(), s0.clone(), s0.mean.clone());
    let mut orders: Vec<Vec<DVec3>> = Vec::with_capacity(iterations as usize);
    for k in 0..iterations {
        let entering = if k == 0 { boundary } else { Boundary::NONE };
        let (next, q) = scatter_once(medium, stencil, &last, entering);
        total = total.plus(&next, DVec3::ONE);
        for (t, q) in quadrupole.iter_mut().zip(&q) {
            (0..5).for_each(|i| t[i] += q[i]);
        }
        before = std::mem::replace(&mut last, next).mean;
        orders.push(last.mean.clone());
    }
    let ratio = if iterations == 0 {
        DVec3::ZERO
    } else {
        order_ratio(grid, &last.mean, &before)
    };
    if iterations > 0 {
        total = total.plus(&last, ratio / (DVec3::ONE - ratio));
    }
    MultipleScattering {
        orders,
        ratio,
        total: total.mean,
        flux: total.flux,
        quadrupole,
    }
}

/// One iteration of `stencil`: `K s` (and the quadrupole of the sweep's radiance), with the
/// radiance `sky` entering the grid (the sweep only; the paper's stencil sees the cloud's own
/// medium only, isotropically).
fn scatter_once(
    medium: SweptMedium,
    stencil: ScatterStencil,
    s: &Moments,
    boundary: Boundary,
) -> (Moments, Vec<Quadrupole>) {
    match stencil {
        ScatterStencil::DiscreteOrdinates => sweep(medium, s, boundary),
        ScatterStencil::Paper => (
            Moments::isotropic(paper_stencil(
                medium.grid,
                medium.k_local,
                medium.albedo,
                &s.mean,
            )),
            Vec::new(),
        ),
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
/// solution held ([`MultipleScattering::moments`]). Its quadrupole is that of `K (s0 + previous)`
/// and of the `W_k`.
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
    let (once, q_once) = scatter_once(medium, stencil, &s0.plus(previous, DVec3::ONE), entering);
    let correction = once.plus(previous, DVec3::splat(-1.0));
    let series = scatter_series(medium, stencil, &correction, Boundary::NONE, iterations - 1);
    // Clamped at 0 like the GPU's: the truncated correction may overshoot where the light fell.
    let total = zip_with(&once.mean, &series.total, |k, t| (*k + *t).max(DVec3::ZERO));
    let flux = zip_with(&once.flux, &series.flux, |k, t| {
        std::array::from_fn(|i| k[i] + t[i])
    });
    let quadrupole = zip_with(&q_once, &series.quadrupole, |k, t| {
        std::array::from_fn(|i| k[i] + t[i])
    });
    let mut orders = vec![correction.mean];
    orders.extend(series.orders);
    MultipleScattering {
        orders,
        ratio: series.ratio,
        total,
        flux,
        quadrupole,
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

// ---------------------------------------------------------------------------------------------
// All stages and 5. the illumination at a shading point
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
    /// The scattering grid's density (section 1), `volume_resolution` voxels per side.
    pub grid: DensityGrid,
    /// The fine density grid the lights are shaded through (section 1), `light_resolution()`
    /// voxels per side.
    pub fine: DensityGrid,
    /// Local extinction `K_local = K s` used, 1/local metre.
    pub k_local: f64,
    /// The medium's albedo used.
    pub albedo: f64,
    /// The medium's Henyey–Greenstein `g`.
    pub anisotropy: f64,
    /// Each shaded light's volume with its irradiance (section 2), in input order, with the
    /// shadows of the clouds illuminated with it; lights with zero irradiance or zero direction
    /// are left out.
    pub lights: Vec<(LightVolume, DVec3)>,
    /// The same light volumes before other clouds' shadows: the cloud's own optical depth, what
    /// it casts on others and on the shadow maps.
    pub own_lights: Vec<LightVolume>,
    /// The multiple-scattering source `S_0` per voxel (section 3): its mean, and its flux for
    /// an anisotropic medium.
    pub source: Moments,
    /// Multiple scattering per voxel (section 4).
    pub multiple: MultipleScattering,
    /// How the camera sees the δ-Eddington beam's excess (section 5); `None` for a medium the
    /// transform does not truncate.
    pub beam: Option<BeamPhase>,
}

/// [`illuminate_under_sky`] under a black sky.
pub fn illuminate(
    particles: &[Particle],
    medium: &Medium,
    scale: f64,
    lights_local: &[LocalLight],
    settings: &CloudQualitySettings,
) -> Option<CloudIllumination> {
    illuminate_under_sky(
        particles,
        medium,
        scale,
        lights_local,
        DVec3::ZERO,
        settings,
    )
}

/// Runs every stage of the contract for one cloud, under a uniform sky of radiance `sky` (linear
/// RGB, the units of `E` per steradian; section 4).
///
/// `scale`: the cloud's uniform world scale `s > 0` (so `K_local = medium.extinction * s`);
/// `lights_local`: directions already in local space (see [`LocalLight::from_world`]). Lights with
/// zero irradiance, or a zero / non-finite direction, are skipped. Returns `None` when no particle
/// has `density > 0`. With no lights everything is zero; with zero extinction `T = 1` everywhere.
pub fn illuminate_under_sky(
    particles: &[Particle],
    medium: &Medium,
    scale: f64,
    lights_local: &[LocalLight],
    sky: DVec3,
    settings: &CloudQualitySettings,
) -> Option<CloudIllumination> {
    shade_cloud(particles, medium, scale, lights_local, settings)
        .map(|shaded| shaded.finish((sky, None), settings, None))
}

/// One of several clouds illuminated together ([`illuminate_clouds_under_sky`]).
#[derive(Clone, Copy)]
pub struct PlacedCloud<'a> {
    /// Particles in cloud-local space.
    pub particles: &'a [Particle],
    /// The cloud's medium.
    pub medium: Medium,
    /// Its transform: lights are taken to its local space, and other clouds' points too.
    pub placement: CloudPlacement,
    /// Its quality knobs (clouds may differ, as in a game).
    pub settings: CloudQualitySettings,
}

/// Runs every stage of the contract for clouds that shadow each other, under the world `lights`
/// and a uniform sky `sky`, each cloud at its own settings: each cloud's light volumes take,
/// beside its own optical depth, the optical depth every other cloud casts on it (section 2,
/// [`LightVolume::cast_depth_at`]), before its single and multiple scattering are gathered and
/// scattered. One entry per cloud, `None` for a cloud without density. A cloud alone is
/// [`illuminate_under_sky`] exactly.
pub fn illuminate_clouds_under_sky(
    clouds: &[PlacedCloud],
    lights: &[LightSample],
    sky: DVec3,
) -> Vec<Option<CloudIllumination>> {
    illuminate_clouds_over_ground(clouds, lights, sky, None)
}

/// [`illuminate_clouds_under_sky`] over `ground` (section 4, "The ground"): each cloud's
/// multiple scattering takes the ground's radiance in on the lattice lines that climb into its
/// grid ([`GroundLight`], from its light volumes once the other clouds' shadows are in them),
/// the sky's on the others. `None`: no ground, the sky's from every side.
pub fn illuminate_clouds_over_ground(
    clouds: &[PlacedCloud],
    lights: &[LightSample],
    sky: DVec3,
    ground: Option<&CloudGround>,
) -> Vec<Option<CloudIllumination>> {
    let mut shaded: Vec<Option<ShadedCloud>> = clouds
        .iter()
        .map(|cloud| {
            let rotation = cloud.placement.rotation;
            let local: Vec<LocalLight> = lights
                .iter()
                .map(|l| LocalLight::from_world(l, rotation))
                .collect();
            let scale = cloud.placement.scale;
            shade_cloud(
                cloud.particles,
                &cloud.medium,
                scale,
                &local,
                &cloud.settings,
            )
        })
        .collect();
    let placements: Vec<CloudPlacement> = clouds.iter().map(|c| c.placement).collect();
    cast_shadows(&mut shaded, &placements);
    let foreign = foreign_media(&shaded, &placements);
    shaded
        .into_iter()
        .zip(clouds)
        .zip(&foreign)
        .map(|((s, cloud), foreign)| {
            let boundary = (sky, ground.map(|g| (g, cloud.placement)));
            s.map(|s| s.finish(boundary, &cloud.settings, foreign.as_deref()))
        })
        .collect()
}

/// Adds to every cloud's light volumes the optical depth the other clouds cast on it (contract
/// section 2): at each voxel centre `p` of cloud `a`'s volume of light `l`,
/// `tau += sum_b cast_b,l(p)` over the other clouds `b`, with [`LightVolume::cast_depth_at`] of
/// `b`'s *own* volume of light `l` at `p` taken to `b`'s local space. Optical depths add along a
/// line, so this is the optical depth of all the clouds, each sampled on its own light box. The
/// clouds' light lists must match (the same lights in the same order), as the scene's lights do.
fn cast_shadows(clouds: &mut [Option<ShadedCloud>], placements: &[CloudPlacement]) {
    let own: Vec<Option<Vec<LightVolume>>> = clouds
        .iter()
        .map(|c| c.as_ref().map(|c| c.own.clone()))
        .collect();
    for (a, cloud) in clouds.iter_mut().enumerate() {
        let Some(cloud) = cloud else { continue };
        for (l, (volume, _)) in cloud.lights.iter_mut().enumerate() {
            let casters: Vec<(&LightVolume, &CloudPlacement)> = own
                .iter()
                .zip(placements)
                .enumerate()
                .filter(|&(b, _)| b != a)
                .filter_map(|(_, (volumes, placement))| {
                    Some((volumes.as_ref()?.get(l)?, placement))
                })
                .collect();
            if casters.is_empty() {
                continue;
            }
            let receiver = own[a].as_ref().map(|v| &v[l]).expect("a shaded cloud");
            let n = receiver.n;
            volume
                .optical_depth
                .par_iter_mut()
                .enumerate()
                .for_each(|(idx, tau)| {
                    let (i, j, k) = unravel(idx, n);
                    let world = placements[a].world_point(receiver.voxel_centre(i, j, k));
                    *tau += casters
                        .iter()
                        .map(|(v, placement)| v.cast_depth_at(placement.local_point(world)))
                        .sum::<f64>();
                });
        }
    }
}

/// Per voxel of every cloud's scattering grid, the other clouds' media there (section 4,
/// "Clouds that overlap"): at the voxel's centre, `sum_c c_c K_c rho_c / K` and
/// `sum_c c_c albedo'_c K_c rho_c / K`, `rho_c` trilinear in cloud `c`'s scattering grid (zero
/// outside it), `K` the world extinctions and `c_c`, `albedo'_c` cloud `c`'s δ-Eddington
/// transform (1 and its albedo for an isotropic medium). `None` for a cloud no other cloud's
/// medium reaches.
fn foreign_media(
    clouds: &[Option<ShadedCloud>],
    placements: &[CloudPlacement],
) -> Vec<Option<Vec<[f64; 2]>>> {
    let world_extinction = |c: &ShadedCloud, p: &CloudPlacement| c.inputs.k_local / p.scale;
    clouds
        .iter()
        .zip(placements)
        .enumerate()
        .map(|(a, (cloud, placement))| {
            let cloud = cloud.as_ref()?;
            let extinction = world_extinction(cloud, placement);
            if extinction <= 0.0 {
                return None;
            }
            let others: Vec<(&ShadedCloud, &CloudPlacement)> = clouds
                .iter()
                .zip(placements)
                .enumerate()
                .filter(|&(b, _)| b != a)
                .filter_map(|(_, (c, p))| Some((c.as_ref()?, p)))
                .collect();
            let media: Vec<[f64; 2]> = (0..cloud.grid.len())
                .into_par_iter()
                .map(|i| {
                    let world = placement.world_point(cloud.grid.voxel_centre_linear(i));
                    others.iter().fold([0.0; 2], |[t, s], (c, p)| {
                        let delta = c.delta();
                        let sigma = delta.depth_scale * world_extinction(c, p) / extinction
                            * c.grid.sample(p.local_point(world));
                        [t + sigma, s + delta.albedo * sigma]
                    })
                })
                .collect();
            media.iter().any(|m| m[0] > 0.0).then_some(media)
        })
        .collect()
}

/// A cloud's density grids and light volumes (sections 1 and 2), before the other clouds cast
/// their shadows on it and its scattering is gathered.
struct ShadedCloud {
    fine: DensityGrid,
    grid: DensityGrid,
    inputs: ShadeInputs,
    anisotropy: f64,
    lights: Vec<(LightVolume, DVec3)>,
    /// The light volumes before other clouds' shadows.
    own: Vec<LightVolume>,
}

/// Sections 1 and 2 for one cloud (see [`illuminate_under_sky`] for the arguments).
fn shade_cloud(
    particles: &[Particle],
    medium: &Medium,
    scale: f64,
    lights_local: &[LocalLight],
    settings: &CloudQualitySettings,
) -> Option<ShadedCloud> {
    let fine = voxelize(particles, settings.light_resolution() as usize)?;
    let grid = fine.downsample(settings.supersampling() as usize);
    let inputs = ShadeInputs {
        k_local: medium.extinction as f64 * scale,
        albedo: medium.albedo as f64,
        forward_scattering: settings.forward_scattering as f64,
        resolution: settings.light_resolution() as usize,
    };
    let lights: Vec<(LightVolume, DVec3)> = lights_local
        .iter()
        .filter(|l| l.irradiance != DVec3::ZERO && l.direction.try_normalize().is_some())
        .map(|l| (shade(&fine, &inputs, l.direction), l.irradiance))
        .collect();
    Some(ShadedCloud {
        fine,
        grid,
        inputs,
        anisotropy: medium.anisotropy as f64,
        own: lights.iter().map(|(v, _)| v.clone()).collect(),
        lights,
    })
}

impl ShadedCloud {
    /// The δ-Eddington transform of its medium.
    fn delta(&self) -> DeltaEddington {
        DeltaEddington::new(self.inputs.albedo, self.anisotropy)
    }

    /// Sections 3 and 4: the source gathered from the light volumes, and its multiple scattering
    /// under the sky `sky` and, with a ground, over it (the cloud placed by the placement given),
    /// and with `foreign`, other clouds' media in the scattering grid (section 4).
    fn finish(
        self,
        (sky, ground): (DVec3, Option<(&CloudGround, CloudPlacement)>),
        settings: &CloudQualitySettings,
        foreign: Option<&[[f64; 2]]>,
    ) -> CloudIllumination {
        let ground = ground
            .map(|(g, placement)| GroundLight::new(g, placement, &self.grid, &self.lights, sky));
        let boundary = Boundary {
            sky,
            ground: ground.as_ref(),
        };
        let delta = self.delta();
        let source = gather_source(&self.grid, &self.fine, &self.lights, delta);
        let medium = SweptMedium {
            grid: &self.grid,
            k_local: self.inputs.k_local,
            albedo: self.inputs.albedo,
            delta,
            foreign,
        };
        let stencil = settings.scatter_stencil;
        let iterations = settings.scatter_iterations;
        let multiple = scatter_through(medium, stencil, &source, boundary, iterations);
        CloudIllumination {
            grid: self.grid,
            fine: self.fine,
            k_local: self.inputs.k_local,
            albedo: self.inputs.albedo,
            anisotropy: self.anisotropy,
            lights: self.lights,
            own_lights: self.own,
            source,
            multiple,
            beam: BeamPhase::new(self.anisotropy),
        }
    }
}

/// Cloud `index` of `scene` as [`illuminate_clouds_under_sky`] illuminates it among the scene's
/// other clouds (their shadows included), with the scene's lights and its background as the sky.
/// Scene clouds are translated only, so local and world directions agree.
pub fn illuminate_scene_cloud(
    scene: &crate::scene::Scene,
    index: usize,
    settings: &CloudQualitySettings,
) -> Option<CloudIllumination> {
    illuminate_scene(scene, settings).swap_remove(index)
}

/// Every cloud of `scene`, illuminated together ([`illuminate_clouds_over_ground`]), with the
/// scene's lights, its background as the sky and its ground ([`Scene::cloud_ground`](crate::scene::Scene::cloud_ground)).
pub fn illuminate_scene(
    scene: &crate::scene::Scene,
    settings: &CloudQualitySettings,
) -> Vec<Option<CloudIllumination>> {
    let clouds: Vec<PlacedCloud> = scene
        .clouds
        .iter()
        .map(|c| PlacedCloud {
            particles: &c.particles,
            medium: c.medium,
            placement: CloudPlacement::at(c.translation.as_dvec3()),
            settings: *settings,
        })
        .collect();
    let sky = scene.background.as_dvec3();
    let ground = scene.cloud_ground();
    illuminate_clouds_over_ground(&clouds, &scene.lights, sky, ground.as_ref())
}

impl CloudIllumination {
    /// What a particle scatters towards the camera at local point `p` along the view ray's unit
    /// local direction `ray` (section 5): `albedo (S_1(p, ray) + S_m(p))`, `S_1` from the light
    /// volumes with the phase function towards the camera and `S_m` the multiple scattering,
    /// trilinear and clamped to the edge. Radiance in the units of `E`.
    pub fn scattered_at(&self, p: DVec3, ray: DVec3) -> DVec3 {
        let medium = (self.albedo, self.anisotropy);
        let single = single_scattering_towards(&self.lights, p, medium, ray, self.beam.as_ref());
        (single + self.multiple_towards(p, -ray)) * self.albedo
    }

    /// The multiple scattering at local point `p` scattered towards the unit direction `w`
    /// (section 5): `S_m(p)`, and for an anisotropic medium the Henyey–Greenstein phase function
    /// applied to its first three angular moments,
    /// `max(mean + 3 g F . w + (15/2) g² w^T Q w, 0)`; all trilinear and clamped to the edge.
    pub fn multiple_towards(&self, p: DVec3, w: DVec3) -> DVec3 {
        let m = &self.multiple;
        let mean = self.grid.sample_clamped(&m.total, p);
        if m.flux.is_empty() {
            return mean;
        }
        let g = self.anisotropy;
        let flux = self.grid.sample_clamped_array(&m.flux, p);
        let quadrupole = self.grid.sample_clamped_array(&m.quadrupole, p);
        (mean + flux_along(&flux, w) * (3.0 * g) + quadrupole_along(&quadrupole, w) * (7.5 * g * g))
            .max(DVec3::ZERO)
    }

    /// `S_m` of every voxel of the scattering grid scattered towards a camera at local point
    /// `camera` (section 5, "An anisotropic cloud seen from the camera"):
    /// [`multiple_towards`](Self::multiple_towards) at the voxel's centre, towards the camera
    /// (the mean alone where the camera is at the centre). `None` for an isotropic medium, whose
    /// `S_m` is the same in every direction.
    pub fn multiple_seen_from(&self, camera: DVec3) -> Option<Vec<DVec3>> {
        if self.multiple.flux.is_empty() {
            return None;
        }
        let seen = (0..self.multiple.total.len()).into_par_iter().map(|i| {
            let centre = self.grid.voxel_centre_linear(i);
            self.multiple_towards(centre, (camera - centre).normalize_or_zero())
        });
        Some(seen.collect())
    }

    /// What the billboards of this cloud see from a camera at local point `camera` with
    /// `compositing`: through the view transmittance, an anisotropic cloud's `S_m` comes from
    /// [`multiple_seen_from`](Self::multiple_seen_from), as on the GPU; otherwise the light is
    /// [`scattered_at`](Self::scattered_at).
    pub fn seen_from(&self, camera: DVec3, compositing: Compositing) -> SeenIllumination<'_> {
        let seen = match compositing {
            Compositing::ViewTransmittance => self.multiple_seen_from(camera),
            Compositing::Sorted => None,
        };
        SeenIllumination {
            illumination: self,
            multiple: seen,
        }
    }
}

/// A cloud's illumination as the billboards of one camera see it
/// ([`CloudIllumination::seen_from`]).
pub struct SeenIllumination<'a> {
    illumination: &'a CloudIllumination,
    /// `S_m` per voxel towards the camera, where the billboards read it from a volume.
    multiple: Option<Vec<DVec3>>,
}

impl SeenIllumination<'_> {
    /// [`CloudIllumination::scattered_at`], with `S_m` trilinear in the volume seen from the
    /// camera where there is one.
    pub fn scattered_at(&self, p: DVec3, ray: DVec3) -> DVec3 {
        let ill = self.illumination;
        let Some(multiple) = &self.multiple else {
            return ill.scattered_at(p, ray);
        };
        let medium = (ill.albedo, ill.anisotropy);
        let single = single_scattering_towards(&ill.lights, p, medium, ray, ill.beam.as_ref());
        (single + ill.grid.sample_clamped(multiple, p)) * ill.albedo
    }
}

// ---------------------------------------------------------------------------------------------
// 10. Cloud shadow maps
// ---------------------------------------------------------------------------------------------

/// The cloud shadow map `map` of light `light` (contract section 10): at each texel, the sum over
/// `clouds` (each with its placement) of [`LightVolume::cast_depth_at`] of its own volume of that
/// light at the texel's column point past every cloud. Index `i + size j`.
pub fn cloud_shadow_map(
    clouds: &[(&CloudIllumination, CloudPlacement)],
    light: usize,
    map: &ShadowMapPlacement,
) -> Vec<f64> {
    over_texels(map, |world| {
        clouds
            .iter()
            .filter_map(|(c, p)| Some(c.own_lights.get(light)?.cast_depth_at(p.local_point(world))))
            .sum()
    })
}

/// `value` at each texel's point of `map` (its column's end), index `i + size j`.
fn over_texels(map: &ShadowMapPlacement, value: impl Fn(DVec3) -> f64 + Sync) -> Vec<f64> {
    let n = map.size;
    (0..n * n)
        .into_par_iter()
        .map(|t| value(map.texel_point(t % n, t / n).as_dvec3()))
        .collect()
}

/// The optical depth at world point `x` in the shadow map `map` holding `values`: bilinear
/// between texel centres, zero outside the map and before `w_begin` along the light.
pub fn shadow_map_depth_at(map: &ShadowMapPlacement, values: &[f64], x: DVec3) -> f64 {
    let [u, v, d] = [map.u, map.v, map.d].map(|a| a.as_dvec3());
    if x.dot(d) < map.w_begin as f64 {
        return 0.0;
    }
    let corner = map.corner.as_dvec2();
    let g = (bevy::math::DVec2::new(x.dot(u), x.dot(v)) - corner) / map.texel as f64 - 0.5;
    let n = map.size as i64;
    let texel = |i: i64, j: i64| {
        if (0..n).contains(&i) && (0..n).contains(&j) {
            values[(i + n * j) as usize]
        } else {
            0.0
        }
    };
    let (i, j) = (g.x.floor() as i64, g.y.floor() as i64);
    let f = g - g.floor();
    let bottom = texel(i, j) * (1.0 - f.x) + texel(i + 1, j) * f.x;
    let top = texel(i, j + 1) * (1.0 - f.x) + texel(i + 1, j + 1) * f.x;
    bottom * (1.0 - f.y) + top * f.y
}

/// The sky map `map` ([`ShadowMapPlacement::sky`], contract section 10): at each texel's point
/// on the plane, the fraction of the sky's irradiance on an upward-facing surface that `clouds`
/// (each with its placement) take away, `1 - (1/K) sum_k exp(-tau_k)` over the
/// [`SKY_MAP_DIRECTIONS`] cosine-weighted directions `k`
/// ([`sky_direction`](crate::shadow_maps::sky_direction)), `tau_k` the optical
/// depth of every cloud along it ([`grid_optical_depth`]). Index `i + size j`; read it with
/// [`shadow_map_depth_at`].
pub fn sky_occlusion_map(
    clouds: &[(&CloudIllumination, CloudPlacement)],
    map: &ShadowMapPlacement,
) -> Vec<f64> {
    over_texels(map, |x| sky_occlusion_at(clouds, x, SKY_MAP_DIRECTIONS))
}

/// The fraction of the sky's irradiance on an upward-facing surface at world point `x` that
/// `clouds` take away, over `directions` cosine-weighted directions
/// ([`sky_direction_among`]); the sky map's texels take [`SKY_MAP_DIRECTIONS`].
pub fn sky_occlusion_at(
    clouds: &[(&CloudIllumination, CloudPlacement)],
    x: DVec3,
    directions: u32,
) -> f64 {
    let visible: f64 = (0..directions)
        .map(|k| {
            let up = sky_direction_among(k, directions).as_dvec3();
            let tau: f64 = clouds
                .iter()
                .map(|(c, p)| grid_optical_depth(c, p, x, up))
                .sum();
            (-tau).exp()
        })
        .sum();
    1.0 - visible / directions as f64
}

/// The optical depth of `cloud` (placed by `placement`) along the world ray from `origin` along
/// the unit `direction`: its scattering grid's density marched from where the ray enters the
/// cube around its voxels' centres, widened by half a voxel (where the zero-border density
/// ends), to where it leaves, in `ceil(chord / h - 0.001)` equal steps sampled at their middles.
/// (The sky map takes the scattering grid, not the finer one the lights are shaded through: what
/// a surface sees of the sky averages the clouds over many directions, and the fine grid
/// changed the occlusion by less than the directions' own error, at 3× the steps.)
pub fn grid_optical_depth(
    cloud: &CloudIllumination,
    placement: &CloudPlacement,
    origin: DVec3,
    direction: DVec3,
) -> f64 {
    let grid = &cloud.grid;
    let o = placement.local_point(origin);
    let d = placement.local_direction(direction);
    let lo = grid.origin() - DVec3::splat(0.5 * grid.h);
    let hi = lo + DVec3::splat((grid.n + 1) as f64 * grid.h);
    let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
    for a in 0..3 {
        if d[a].abs() < 1e-12 {
            if o[a] < lo[a] || o[a] > hi[a] {
                return 0.0;
            }
            continue;
        }
        let (near, far) = ((lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]);
        t0 = t0.max(near.min(far));
        t1 = t1.min(near.max(far));
    }
    if t1 <= t0 {
        return 0.0;
    }
    // A chord a rounding error over a whole number of voxels takes that number of steps.
    let steps = ((t1 - t0) / grid.h - 1e-3).ceil().max(1.0);
    let dt = (t1 - t0) / steps;
    let sum: f64 = (0..steps as usize)
        .map(|i| grid.sample(o + d * (t0 + (i as f64 + 0.5) * dt)))
        .sum();
    cloud.k_local * sum * dt
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::math::{DMat3, Vec3};

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

    fn random_cloud(count: usize, seed: u64) -> Vec<Particle> {
        let mut rng = crate::math::SplitMix64::mixed(seed);
        (0..count)
            .map(|_| {
                let mut r = || rng.next_f32();
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

    fn inputs(k_local: f64, albedo: f64, forward: f64, resolution: usize) -> ShadeInputs {
        ShadeInputs {
            k_local,
            albedo,
            forward_scattering: forward,
            resolution,
        }
    }

    #[test]
    fn homogeneous_slab_follows_beer_lambert_along_every_axis() {
        // Uniform rho over the cube; for axis-aligned light the light box coincides with the cube,
        // so a voxel at depth (c + 1/2) h from the lit face has tau = K rho depth exactly (the
        // trapezoid rule is exact for constant sigma), at the grid's resolution and finer.
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
            for m in [n, 2 * n] {
                let vol = shade(&grid, &inputs(k, 0.9, 0.0, m), d);
                assert_eq!(vol.half_extents, DVec3::splat(n as f64 / 2.0));
                for idx in 0..grid.len() {
                    let (i, j, kk) = unravel(idx, n);
                    if m != n && [i, j, kk].iter().any(|&c| c == 0 || c == n - 1) {
                        continue; // finer samples of the outer layer see the thinner border too
                    }
                    let x = grid.voxel_centre_linear(idx);
                    // distance from the face the light enters through
                    let depth = x.dot(d) + grid.side / 2.0;
                    // Finer slices see the zero border thin the outermost half voxel: the
                    // trilinear field's integral there is 0.375 rho h instead of 0.5 rho h.
                    let border = if m == n { 0.0 } else { 0.125 };
                    let expected = k * rho * (depth - border);
                    let tau = vol.optical_depth_at(x);
                    if depth > 1.0 {
                        assert!(
                            (tau - expected).abs() < 1e-12,
                            "{d} m={m}: {tau} vs {expected}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn forward_scattering_reduces_attenuation() {
        let grid = uniform_grid(6, 1.0);
        let (k, albedo, f) = (0.5, 0.8, 0.25);
        let vol = shade(&grid, &inputs(k, albedo, f, 6), DVec3::NEG_Z);
        let x = grid.voxel_centre(0, 0, 0); // deepest for light travelling -Z: depth 5.5
        let expected = (-k * (1.0 - f * albedo) * 5.5).exp();
        assert!((vol.transmittance_at(x) - expected).abs() < 1e-13);
    }

    #[test]
    fn incremental_shade_equals_brute_force() {
        let particles = random_cloud(40, 3);
        let grid = voxelize(&particles, 16).unwrap();
        for (d, m) in [
            (DVec3::new(0.3, -1.0, 0.2), 16),
            (DVec3::NEG_Y, 32),
            (DVec3::new(-1.0, 0.1, -0.7), 24),
        ] {
            let fast = shade(&grid, &inputs(4.0, 0.9, 0.3, m), d);
            let slow = shade_brute_force(&grid, &inputs(4.0, 0.9, 0.3, m), d);
            assert_eq!(fast.basis, slow.basis);
            assert_eq!(fast.n, m);
            let max_diff = fast
                .optical_depth
                .iter()
                .zip(&slow.optical_depth)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(max_diff < 1e-12, "max |diff| = {max_diff}");
            // and the cloud does cast a shadow
            assert!(fast.optical_depth.iter().copied().fold(0.0, f64::max) > 0.7);
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
            let expected = crate::math::particle_optical_depth(k, 2.0, 1.0, 0.0);
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

    /// One axis of the upsampling: each coarse voxel's density weights sum to 2 over the fine
    /// voxels (its mass is kept, at either parity of the fine level), and inside they
    /// interpolate a linear profile exactly.
    #[test]
    fn prolongation_keeps_mass_and_interpolates_linearly() {
        for fine_n in 2usize..40 {
            let coarse_n = fine_n.div_ceil(2);
            let mut given = vec![0.0; coarse_n];
            for i in 0..fine_n {
                for (j, w) in prolongation(i, fine_n, coarse_n) {
                    given[j] += w;
                }
            }
            for (j, total) in given.iter().enumerate() {
                assert!(
                    (total - 2.0).abs() < 1e-15,
                    "{fine_n}: coarse {j} gives {total}"
                );
            }
            // Coarse centre j at 2j + 1/2 in fine coordinates; fine centre i at i.
            for i in 2..fine_n.saturating_sub(2) {
                let value: f64 = prolongation(i, fine_n, coarse_n)
                    .iter()
                    .map(|&(j, w)| w * (3.0 + 0.5 * (2.0 * j as f64 + 0.5)))
                    .sum();
                assert!(
                    (value - (3.0 + 0.5 * i as f64)).abs() < 1e-12,
                    "{fine_n}, {i}"
                );
            }
        }
        assert_eq!(prolongation(0, 8, 4), [(0, 1.0)]);
        assert_eq!(prolongation(5, 8, 4), [(2, 0.75), (3, 0.25)]);
        // An odd level: the last coarse voxel half overhangs; its whole share stays in voxel 8.
        assert_eq!(prolongation(8, 9, 5), [(3, 0.25), (4, 1.75)]);
    }

    /// The levels' upsampling, compensated by the narrower kernel (`level_kernel_radius`): a
    /// particle just too wide for the level below (8.1–8.5 voxels per radius on its level) keeps
    /// its central column optical depth within 0.1 % of the exact chord integral, as a particle
    /// of 8 fine voxels per radius deposited directly does. (Uncompensated, it is 1.8 % low.)
    #[test]
    fn coarse_levels_keep_a_particles_central_column() {
        let p = particle(0.0, 0.0, 0.0, 1.0, 1.0);
        // The mean of the four voxel columns around the particle's axis (each h / √2 from it),
        // relative to the exact chord integral there.
        let centre_column = |n: usize| {
            let grid = voxelize(&[p], n).unwrap();
            let column =
                |i: usize, j: usize| -> f64 { (0..n).map(|k| grid.rho[grid.index(i, j, k)]).sum() };
            let c = n / 2 - 1;
            let sum = column(c, c) + column(c + 1, c) + column(c, c + 1) + column(c + 1, c + 1);
            let exact = crate::math::particle_optical_depth(1.0, 1.0, 1.0, grid.h / 2f64.sqrt());
            sum / 4.0 * grid.h / exact - 1.0
        };
        let direct = centre_column(16);
        for (n, level) in [(34, 1), (66, 2), (130, 3)] {
            let levels = density_level_sizes(n as u32).len();
            assert_eq!(density_level(n as f64 / 2.0, levels), level);
            let error = centre_column(n);
            assert!(
                error.abs() < 1e-3 && direct.abs() < 1e-3,
                "n = {n}, level {level}: {error} against {direct} directly"
            );
        }
    }

    /// The density levels: particles of every size keep their mass exactly on grids of either
    /// parity, and the large ones, deposited on coarse levels and enlarged, stay close to their
    /// direct deposit on the fine grid (the column optical depths within 0.5 % of the largest).
    #[test]
    fn coarse_levels_keep_mass_and_stay_close_to_the_direct_deposit() {
        let mut rng = crate::math::SplitMix64::new(3);
        let particles: Vec<Particle> = (0..40)
            .map(|i| {
                let c = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) - 0.5;
                let radius = [0.01, 0.05, 0.2, 0.6, 1.2][i % 5];
                particle(c.x, c.y, c.z, radius, 1.0 + rng.next_f32())
            })
            .collect();
        let mass: f64 = particles.iter().map(|p| p.mass()).sum();
        for n in [127, 128, 96, 45] {
            let grid = voxelize(&particles, n).unwrap();
            let deepest = particles
                .iter()
                .map(|p| density_level(p.radius as f64 / grid.h, 8))
                .max();
            assert!(
                deepest >= Some(1 + (n >= 96) as usize),
                "n = {n}: {deepest:?}"
            );
            assert!(
                (grid.mass() - mass).abs() < 1e-10 * mass,
                "n = {n}: {} vs {mass}",
                grid.mass()
            );
            // The same particles deposited directly on the fine grid.
            let mut direct = DensityGrid {
                rho: vec![0.0; grid.len()],
                ..grid.clone()
            };
            for p in &particles {
                let (c, r, m) = (p.position.as_dvec3(), p.radius as f64, p.mass());
                if r < direct.h || !deposit_kernel(&mut direct, c, r, m) {
                    deposit_trilinear(&mut direct, c, m);
                }
            }
            let inv_volume = 1.0 / direct.h.powi(3);
            direct.rho.iter_mut().for_each(|v| *v *= inv_volume);
            // Column optical depths (sums along z) through every (i, j), relative to the largest.
            let columns = |g: &DensityGrid| -> Vec<f64> {
                (0..n * n)
                    .map(|ij| (0..n).map(|k| g.rho[ij + n * n * k]).sum::<f64>() * g.h)
                    .collect()
            };
            let (a, b) = (columns(&grid), columns(&direct));
            let largest = b.iter().copied().fold(0.0, f64::max);
            let worst = a
                .iter()
                .zip(&b)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f64::max);
            assert!(
                worst < 0.005 * largest,
                "n = {n}: worst column {worst} of {largest}"
            );
        }
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
    fn paper_iteration_matches_hand_computed_coefficients() {
        let (k, albedo, rho) = (0.7, 0.9, 1.5);
        let grid = uniform_grid(3, rho);
        let mut s0 = vec![DVec3::ZERO; 27];
        s0[grid.index(1, 1, 1)] = DVec3::new(1.0, 2.0, 3.0);
        let p = scatter(&grid, k, albedo, ScatterStencil::Paper, &s0, 1);
        let expected = DVec3::new(1.0, 2.0, 3.0) * (albedo / 26.0) * (1.0 - (-k * rho).exp());
        for idx in (0..27).filter(|&i| i != grid.index(1, 1, 1)) {
            assert!((p.orders[0][idx] - expected).length() < 1e-15);
        }
        // The centre receives nothing (all its neighbours had S_0 = 0).
        assert_eq!(p.orders[0][grid.index(1, 1, 1)], DVec3::ZERO);
    }

    #[test]
    fn segment_weights_are_continuous_at_the_series_switch() {
        for tau in [SERIES_BELOW * (1.0 - 1e-9), SERIES_BELOW] {
            let (c, l) = segment_weights(tau);
            let e = (-tau).exp();
            assert!((c - (1.0 - e)).abs() < 1e-6 * c, "{tau}");
            assert!((l - ((1.0 - e) / tau - e)).abs() < 1e-5 * l, "{tau}");
        }
        assert_eq!(segment_weights(0.0), (0.0, 0.0));
        let (c, l) = segment_weights(1e3);
        assert!((c - 1.0).abs() < 1e-12 && (l - 1e-3).abs() < 1e-12);
    }

    #[test]
    fn sweep_returns_albedo_times_s_inside_a_thick_homogeneous_medium() {
        // The exact operator returns albedo S for uniform S deep inside a homogeneous medium; the
        // sweep loses only what leaks through the grid's edge, exp(-tau) of the line to it.
        let (n, albedo) = (16, 0.9);
        let grid = uniform_grid(n, 1.0);
        let k = 1.0; // one mean free path per voxel
        let s = vec![DVec3::new(1.0, 2.0, 0.5); grid.len()];
        let one = scatter(&grid, k, albedo, ScatterStencil::DiscreteOrdinates, &s, 1);
        let centre = grid.index(n / 2, n / 2, n / 2);
        let ratio = one.orders[0][centre] / s[centre];
        for r in ratio.to_array() {
            assert!((r - albedo).abs() < 2e-3 * albedo, "ratio {r}");
        }
    }

    #[test]
    fn sweep_scales_a_p1_field_by_albedo_and_its_flux_by_g_inside_a_thick_medium() {
        // Deep inside a homogeneous medium a uniform source of mean S and flux F sends
        // albedo' (S + 3 g' F . w) along every direction w; over the 26 lattice directions (whose
        // second moment is exactly I/3) the next order holds albedo' S and albedo' g' F, as the
        // transport operator of the δ-Eddington medium does, and no quadrupole.
        let (n, albedo, g) = (16, 0.9, 0.6);
        let grid = uniform_grid(n, 1.0);
        let k = 1.0 / DeltaEddington::new(albedo, g).depth_scale; // one mean free path per voxel
        let flux = [
            DVec3::new(0.2, 0.1, 0.0),
            DVec3::new(-0.1, 0.0, 0.05),
            DVec3::new(0.0, 0.3, 0.1),
        ];
        let s = Moments {
            mean: vec![DVec3::new(1.0, 2.0, 0.5); grid.len()],
            flux: vec![flux; grid.len()],
        };
        let medium = SweptMedium::alone(&grid, k, albedo, g);
        let delta = medium.delta;
        assert!((delta.anisotropy - g / (1.0 + g)).abs() < 1e-12);
        let (next, quadrupole) = sweep(medium, &s, Boundary::NONE);
        let centre = grid.index(n / 2, n / 2, n / 2);
        let close = |a: DVec3, b: DVec3| (a - b).abs().max_element() < 2e-3 * b.abs().max_element();
        assert!(close(next.mean[centre], s.mean[centre] * delta.albedo));
        for (axis, (swept, f)) in next.flux[centre].iter().zip(flux).enumerate() {
            let expected = f * (delta.albedo * delta.anisotropy);
            assert!(close(*swept, expected), "{axis}: {swept}");
        }
        assert!(
            quadrupole[centre]
                .iter()
                .all(|q| q.abs().max_element() < 2e-3)
        );
    }

    #[test]
    fn an_anisotropic_medium_under_a_uniform_sky_holds_the_sky() {
        // The furnace: at albedo 1, whatever the phase function, a cloud under a uniform sky and
        // no light holds the sky's radiance everywhere, in every direction.
        let particles = random_cloud(30, 5);
        let sky = DVec3::new(0.2, 0.3, 0.5);
        for g in [0.0, 0.8, -0.5] {
            let medium = Medium {
                extinction: 3.0,
                albedo: 1.0,
                anisotropy: g,
            };
            let settings = CloudQualitySettings {
                volume_resolution: 12,
                scatter_iterations: 40,
                ..Default::default()
            };
            let ill = illuminate_under_sky(&particles, &medium, 1.0, &[], sky, &settings).unwrap();
            for (idx, rho) in ill.grid.rho.iter().enumerate() {
                if *rho < 0.5 * ill.grid.max() {
                    continue;
                }
                let x = ill.grid.voxel_centre_linear(idx);
                for w in [
                    DVec3::X,
                    DVec3::NEG_Y,
                    DVec3::new(1.0, 1.0, -1.0).normalize(),
                ] {
                    let seen = ill.multiple_towards(x, w);
                    assert!(
                        ((seen - sky) / sky).abs().max_element() < 0.01,
                        "g {g}: {seen} towards {w}"
                    );
                }
            }
        }
    }

    #[test]
    fn sweep_is_exact_for_a_linear_source_along_a_line() {
        // With S linear in space, the radiance arriving from direction o deep inside a homogeneous
        // medium is albedo (S(v) + dS/ds / sigma) (s measured towards v + o), exactly.
        let (n, sigma, albedo) = (24, 1.5, 0.7);
        let grid = uniform_grid(n, 1.0);
        let gradient = DVec3::new(0.02, -0.01, 0.015); // S per metre
        let s: Vec<DVec3> = (0..grid.len())
            .map(|i| DVec3::splat(2.0 + grid.voxel_centre_linear(i).dot(gradient)))
            .collect();
        for o in [[1, 0, 0], [0, -1, 1], [-1, 1, 1]] {
            let medium = SweptMedium::alone(&grid, sigma, albedo, 0.0);
            let radiance =
                sweep_direction(medium, o, &Moments::isotropic(s.clone()), Boundary::NONE);
            let d = DVec3::new(o[0] as f64, o[1] as f64, o[2] as f64).normalize();
            // the centre: 12 steps (optical depth >= 18) from every edge
            let v = grid.index(n / 2, n / 2, n / 2);
            let expected = albedo * (s[v].x + gradient.dot(d) / sigma);
            assert!(
                (radiance[v].x - expected).abs() < 1e-6 * expected,
                "{o:?}: {} vs {expected}",
                radiance[v].x
            );
        }
    }

    #[test]
    fn sweep_is_exact_for_a_quadratic_source_along_a_line() {
        // With S quadratic in space, S = S_0 + g . x + x^T A x, the radiance arriving from
        // direction o (unit d towards v + o) deep inside a homogeneous medium is
        // albedo (S(v) + g . d / sigma + 2 d^T A d / sigma^2): the parabola the sweep takes
        // between voxel centres is the field itself.
        let (n, sigma, albedo) = (24, 1.5, 0.7);
        let grid = uniform_grid(n, 1.0);
        let gradient = DVec3::new(0.02, -0.01, 0.015);
        let curvature = DMat3::from_cols_array(&[
            0.004, 0.001, -0.002, 0.001, -0.003, 0.0005, -0.002, 0.0005, 0.002,
        ]);
        let centre = grid.voxel_centre(n / 2, n / 2, n / 2);
        let field = |x: DVec3| {
            let r = x - centre;
            2.0 + r.dot(gradient) + r.dot(curvature * r)
        };
        let s: Vec<DVec3> = (0..grid.len())
            .map(|i| DVec3::splat(field(grid.voxel_centre_linear(i))))
            .collect();
        let v = grid.index(n / 2, n / 2, n / 2);
        for o in [[1, 0, 0], [0, -1, 1], [-1, 1, 1]] {
            let medium = SweptMedium::alone(&grid, sigma, albedo, 0.0);
            let radiance =
                sweep_direction(medium, o, &Moments::isotropic(s.clone()), Boundary::NONE);
            let d = DVec3::new(o[0] as f64, o[1] as f64, o[2] as f64).normalize();
            let expected = albedo
                * (s[v].x + gradient.dot(d) / sigma + 2.0 * d.dot(curvature * d) / sigma.powi(2));
            assert!(
                (radiance[v].x - expected).abs() < 1e-6 * expected,
                "{o:?}: {} vs {expected}",
                radiance[v].x
            );
        }
    }

    #[test]
    fn one_sweep_diffuses_like_the_transport_operator() {
        // The transport operator of a thick homogeneous medium maps a quadratic S to
        // albedo (S + lap S / (3 sigma^2)). Interpolating S linearly between voxel centres
        // would add about (|o| h)^2 / 12 of curvature per direction: 17 % more diffusion at a
        // voxel optical depth of 1 (36 % here), which carried light through thick clouds into
        // their shadow.
        let (n, sigma, albedo) = (24, 1.5, 1.0);
        let grid = uniform_grid(n, 1.0);
        let centre = grid.voxel_centre(n / 2, n / 2, n / 2);
        let s: Vec<DVec3> = (0..grid.len())
            .map(|i| {
                let r = grid.voxel_centre_linear(i) - centre;
                DVec3::splat(1.0 + 0.01 * r.length_squared())
            })
            .collect();
        let medium = SweptMedium::alone(&grid, sigma, albedo, 0.0);
        let (next, _) = sweep(medium, &Moments::isotropic(s.clone()), Boundary::NONE);
        let v = grid.index(n / 2, n / 2, n / 2);
        let laplacian = 0.06;
        let expected = albedo * (s[v].x + laplacian / (3.0 * sigma * sigma));
        assert!(
            (next.mean[v].x - expected).abs() < 1e-6,
            "{} vs {expected}",
            next.mean[v].x
        );
    }

    #[test]
    fn curvature_weight_is_continuous_at_the_series_switch() {
        let below = curvature_weight(0.5 * (1.0 - 1e-12));
        let above = curvature_weight(0.5);
        assert!((below - above).abs() < 1e-9 * above, "{below} vs {above}");
        assert_eq!(curvature_weight(0.0), 0.0);
        // int_0^inf exp(-t) u (1 - u) dt -> 1 / tau for large tau
        let tau = 1e3;
        assert!((curvature_weight(tau) * tau - 1.0).abs() < 1e-2);
    }

    #[test]
    fn series_closure_recovers_the_orders_left_over() {
        // A thick, bright cloud: 8 iterations closed with lambda agree with 400 iterations
        // (whose tail is negligible) within 3 %; without the closure they would be short.
        let particles = random_cloud(40, 21);
        let grid = voxelize(&particles, 12).unwrap();
        let k = 4.0 / (grid.max() * grid.h); // ~4 mean free paths per voxel at the densest
        let vol = shade(&grid, &inputs(k, 0.99, 0.0, 12), DVec3::new(0.2, -1.0, 0.1));
        let s0 = gather(&grid, &grid, &[(vol, DVec3::ONE)]);
        let total = |m: Vec<DVec3>| -> f64 { m.iter().zip(&grid.rho).map(|(s, r)| s.x * r).sum() };
        let short = scatter(&grid, k, 0.99, ScatterStencil::DiscreteOrdinates, &s0, 8);
        let long = scatter(&grid, k, 0.99, ScatterStencil::DiscreteOrdinates, &s0, 400);
        let (closed, converged) = (total(short.total.clone()), total(long.total));
        let plain: f64 = short.orders.iter().map(|o| total(o.clone())).sum();
        assert!(short.ratio.x > 0.5 && short.ratio.x <= MAX_ORDER_RATIO);
        assert!(
            (closed / converged - 1.0).abs() < 0.03,
            "{closed} vs {converged}"
        );
        assert!(
            plain < 0.95 * converged,
            "the closure matters here: {plain} vs {converged}"
        );
    }

    #[test]
    fn a_warm_restart_corrects_towards_the_new_solution() {
        // The sun moves by 10 degrees over a thick, bright cloud. Restarted from the old
        // solution, 4 iterations land far closer to the converged new solution than 4 from zero,
        // or than the old solution; from zero, the warm restart is the plain series; from the
        // converged solution, it stays.
        let particles = random_cloud(40, 21);
        let grid = voxelize(&particles, 12).unwrap();
        let k = 4.0 / (grid.max() * grid.h);
        let source = |direction: DVec3| {
            let vol = shade(&grid, &inputs(k, 0.99, 0.0, 12), direction);
            gather(&grid, &grid, &[(vol, DVec3::ONE)])
        };
        let (old, new) = (
            source(DVec3::new(0.2, -1.0, 0.1)),
            source(DVec3::new(0.38, -0.95, 0.1)),
        );
        let stencil = ScatterStencil::DiscreteOrdinates;
        let converged = |s0: &[DVec3]| scatter(&grid, k, 0.99, stencil, s0, 400).total;
        let (before, after) = (converged(&old), converged(&new));
        let x = |v: &[DVec3]| v.iter().map(|s| s.x).collect::<Vec<_>>();
        let error =
            |m: &[DVec3]| crate::reference::metrics::max_relative_difference(&x(m), &x(&after));
        let warm = scatter_warm(&grid, k, 0.99, stencil, &new, &before, DVec3::ZERO, 4);
        let cold = scatter(&grid, k, 0.99, stencil, &new, 4);
        assert!(
            error(&warm.total) < 0.2 * error(&cold.total),
            "warm {} vs cold {}",
            error(&warm.total),
            error(&cold.total)
        );
        // (Measured: warm 0.032, cold 0.35, the old solution 0.16 of the largest value. With a
        // linear source between voxel centres, whose extra diffusion made the series converge
        // faster, warm was 0.026.)
        assert!(
            error(&warm.total) < 0.25 * error(&before),
            "warm {}, old solution {}",
            error(&warm.total),
            error(&before)
        );
        assert!(
            error(&before) > 0.05,
            "the sun's move matters: {}",
            error(&before)
        );

        let zero = vec![DVec3::ZERO; grid.len()];
        let from_zero = scatter_warm(&grid, k, 0.99, stencil, &new, &zero, DVec3::ZERO, 4);
        assert!(error(&from_zero.total) > 0.0);
        for (a, b) in from_zero.total.iter().zip(&cold.total) {
            assert!((*a - *b).abs().max_element() <= 1e-12 * b.max_element().max(1e-300));
        }
        let stays = scatter_warm(&grid, k, 0.99, stencil, &new, &after, DVec3::ZERO, 2);
        assert!(error(&stays.total) < 1e-3, "{}", error(&stays.total));
    }

    #[test]
    fn an_anisotropic_warm_restart_is_the_series_from_zero_and_stays_at_the_solution() {
        let particles = random_cloud(40, 21);
        let grid = voxelize(&particles, 12).unwrap();
        let k = 4.0 / (grid.max() * grid.h);
        let (albedo, g) = (0.95, 0.7);
        let delta = DeltaEddington::new(albedo, g);
        let vol = shade(
            &grid,
            &inputs(k, albedo, 0.0, 12),
            DVec3::new(0.2, -1.0, 0.1),
        );
        let s0 = gather_source(&grid, &grid, &[(vol, DVec3::ONE)], delta);
        assert_eq!(s0.flux.len(), grid.len());
        let stencil = ScatterStencil::DiscreteOrdinates;
        let sky = DVec3::new(0.1, 0.1, 0.2);
        let converged = scatter_medium(&grid, k, (albedo, g), stencil, &s0, sky, 300);
        let cold = scatter_medium(&grid, k, (albedo, g), stencil, &s0, sky, 4);
        let zero = s0.plus(&s0, DVec3::splat(-1.0));
        let from_zero = scatter_warm_medium(&grid, k, (albedo, g), stencil, &s0, &zero, sky, 4);
        let close = |a: &[DVec3], b: &[DVec3], tolerance: f64| {
            let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs().max_element()));
            a.iter()
                .zip(b)
                .all(|(a, b)| (*a - *b).abs().max_element() <= tolerance * scale)
        };
        let fluxes = |m: &MultipleScattering, axis: usize| {
            m.flux.iter().map(|f| f[axis]).collect::<Vec<_>>()
        };
        assert!(close(&from_zero.total, &cold.total, 1e-12));
        assert!((0..3).all(|a| close(&fluxes(&from_zero, a), &fluxes(&cold, a), 1e-12)));
        let stays = scatter_warm_medium(
            &grid,
            k,
            (albedo, g),
            stencil,
            &s0,
            &converged.moments(),
            sky,
            2,
        );
        assert!(close(&stays.total, &converged.total, 1e-3));
        assert!((0..3).all(|a| close(&fluxes(&stays, a), &fluxes(&converged, a), 1e-3)));
        assert!(
            !close(&cold.total, &converged.total, 1e-2),
            "the test can tell them apart"
        );
    }

    #[test]
    fn scatter_with_albedo_one_stays_below_energy_bound() {
        let particles = random_cloud(30, 11);
        let fine = voxelize(&particles, 24).unwrap();
        let grid = fine.downsample(2);
        for k in [3.0 / (grid.max() * grid.h), 500.0] {
            let vol = shade(&fine, &inputs(k, 1.0, 0.0, 24), DVec3::new(0.2, -1.0, 0.1));
            let s0 = gather(&grid, &fine, &[(vol, DVec3::new(1.0, 0.8, 0.5))]);
            let max_s0 = max_component(&s0);
            for stencil in [ScatterStencil::DiscreteOrdinates, ScatterStencil::Paper] {
                for iterations in [1, 8, 1000] {
                    let bound = energy_bound(&grid, k, 1.0, iterations, max_s0);
                    assert!(bound.is_finite());
                    let m = scatter(&grid, k, 1.0, stencil, &s0, iterations);
                    assert!(
                        m.total
                            .iter()
                            .all(|v| v.is_finite() && v.min_element() >= 0.0)
                    );
                    let max_m = max_component(&m.total);
                    assert!(
                        max_m <= bound,
                        "{stencil:?} x{iterations}: {max_m} > {bound}"
                    );
                    assert!(
                        max_m > 0.01 * max_s0,
                        "{stencil:?}: multiple scattering adds light"
                    );
                }
            }
        }
        // No iterations: no multiple scattering and a zero bound.
        let opaque = uniform_grid(4, 1e6);
        assert_eq!(energy_bound(&opaque, 1e3, 1.0, 0, 2.0), 0.0);
    }

    #[test]
    fn downsampling_keeps_mass_and_averages_children() {
        let particles = random_cloud(25, 4);
        let fine = voxelize(&particles, 16).unwrap();
        let coarse = fine.downsample(4);
        assert_eq!((coarse.n, coarse.h), (4, fine.h * 4.0));
        assert!((coarse.mass() - fine.mass()).abs() < 1e-12 * fine.mass());
        let children: f64 = (0..4)
            .flat_map(|k| (0..4).flat_map(move |j| (0..4).map(move |i| (i, j, k))))
            .map(|(i, j, k)| fine.rho[fine.index(4 + i, 8 + j, 12 + k)])
            .sum();
        assert!((coarse.rho[coarse.index(1, 2, 3)] - children / 64.0).abs() < 1e-12);
        assert_eq!(fine.downsample(1), fine);
    }

    #[test]
    fn gather_weights_the_children_by_their_density() {
        let particles = random_cloud(20, 17);
        let fine = voxelize(&particles, 16).unwrap();
        let vol = shade(
            &fine,
            &inputs(3.0, 0.9, 0.0, 16),
            DVec3::new(0.3, -1.0, 0.2),
        );
        let lights = [(vol, DVec3::new(1.0, 2.0, 3.0))];
        // Without supersampling the source is S_1 at the voxel centre.
        let same = gather(&fine, &fine, &lights);
        for idx in [0, 100, 3000] {
            let x = fine.voxel_centre_linear(idx);
            assert!((same[idx] - single_scattering_at(&lights, x)).length() < 1e-15);
        }
        // With f = 2, each child's S_1 weighted by its density.
        let grid = fine.downsample(2);
        let source = gather(&grid, &fine, &lights);
        let (mut checked, mut differs) = (0, false);
        for (idx, source) in source.iter().enumerate() {
            let (i, j, k) = unravel(idx, grid.n);
            let (mut weighted, mut mass) = (DVec3::ZERO, 0.0);
            for c in 0..8 {
                let (a, b, cc) = unravel(c, 2);
                let (fi, fj, fk) = (2 * i + a, 2 * j + b, 2 * k + cc);
                let rho = fine.rho[fine.index(fi, fj, fk)];
                weighted += single_scattering_at(&lights, fine.voxel_centre(fi, fj, fk)) * rho;
                mass += rho;
            }
            if mass > 0.0 {
                let expected = weighted / mass;
                assert!((*source - expected).length() < 1e-12 * expected.length().max(1e-300));
                let centre = single_scattering_at(&lights, grid.voxel_centre_linear(idx));
                differs |= (*source - centre).length() > 1e-3 * centre.length();
                checked += 1;
            }
        }
        assert!(checked > 50 && differs, "{checked} voxels with density");
    }

    #[test]
    fn zero_extinction_gives_unattenuated_light_everywhere() {
        let particles = random_cloud(20, 5);
        let medium = Medium {
            extinction: 0.0,
            albedo: 0.8,
            ..Default::default()
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
            light_supersampling: 2,
            ..Default::default()
        };
        let ill = illuminate(&particles, &medium, 2.0, &lights, &settings).unwrap();
        assert_eq!(
            ill.lights.len(),
            2,
            "zero irradiance and zero direction lights are skipped"
        );
        for (vol, _) in &ill.lights {
            assert_eq!(vol.n, 16);
            assert!(vol.optical_depth.iter().all(|&t| t == 0.0));
        }
        let expected = DVec3::new(3.0, 3.0, 4.5) / (4.0 * PI);
        for s in &ill.source.mean {
            assert!((*s - expected).length() < 1e-15);
        }
        // Nothing scatters twice in a medium that does not interact.
        assert!(ill.multiple.total.iter().all(|m| *m == DVec3::ZERO));
        for idx in [0, 77, 511] {
            let x = ill.grid.voxel_centre_linear(idx);
            assert!((ill.scattered_at(x, DVec3::Z) - expected * ill.albedo).length() < 1e-15);
        }
    }

    /// Through a grid of uniform density the march is exact: the zero-border density ramps to 0
    /// half a voxel beyond the outer centres, so a chord along an axis holds `K rho n h`; and
    /// the sky map sees the cloud most under it and not at all far beside it.
    #[test]
    fn the_sky_map_marches_the_fine_density() {
        let settings = CloudQualitySettings {
            volume_resolution: 8,
            light_supersampling: 1,
            ..Default::default()
        };
        let medium = Medium::default();
        let particles = random_cloud(40, 3);
        let mut ill = illuminate(&particles, &medium, 1.0, &[], &settings).unwrap();
        ill.grid.rho.iter_mut().for_each(|r| *r = 0.75);
        let grid = ill.grid.clone();
        let placement = CloudPlacement {
            translation: DVec3::new(1.0, 10.0, -2.0),
            rotation: DQuat::from_rotation_y(0.3),
            scale: 1.0,
        };
        let below = placement.world_point(grid.centre) - DVec3::Y * 8.0;
        let tau = grid_optical_depth(&ill, &placement, below, DVec3::Y);
        let exact = ill.k_local * 0.75 * grid.n as f64 * grid.h;
        assert!((tau - exact).abs() < 1e-9 * exact, "{tau} against {exact}");
        assert_eq!(
            grid_optical_depth(&ill, &placement, below, DVec3::NEG_Y),
            0.0
        );

        let world = placement.world_point(grid.centre).as_vec3();
        let radius = (0.5 * 3f64.sqrt() * grid.side) as f32;
        let map = ShadowMapPlacement::sky(&[(world, radius)], 2.0, 24, 0).unwrap();
        let occlusion = sky_occlusion_map(&[(&ill, placement)], &map);
        let at = |x: DVec3| shadow_map_depth_at(&map, &occlusion, x);
        let under = at(DVec3::new(world.x as f64, 2.0, world.z as f64));
        let beside = at(DVec3::new(world.x as f64 + 16.0, 2.0, world.z as f64));
        assert!(occlusion.iter().all(|o| (0.0..1.0).contains(o)));
        assert!(under > 0.05 && beside < 0.5 * under, "{under} {beside}");
        assert_eq!(at(DVec3::new(1e3, 2.0, 0.0)), 0.0, "nothing beyond the map");
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
        assert!(ill.multiple.total.iter().all(|a| *a == DVec3::ZERO));
        assert_eq!(ill.scattered_at(DVec3::ZERO, DVec3::Z), DVec3::ZERO);
    }

    #[test]
    fn transmittance_at_centre_of_particle_matches_half_chord() {
        // tau at the centre of one particle lit from an oblique direction ~ K eta r 8/15.
        let p = particle(0.0, 0.0, 0.0, 1.0, 1.0);
        let grid = voxelize(&[p], 64).unwrap();
        let k = 2.0;
        let vol = shade(&grid, &inputs(k, 1.0, 0.0, 64), DVec3::new(0.4, -1.0, 0.3));
        let tau = vol.optical_depth_at(DVec3::ZERO);
        let expected = k * 8.0 / 15.0;
        assert!(
            (tau - expected).abs() < 0.01 * expected,
            "tau {tau} vs {expected}"
        );
    }

    #[test]
    fn scattered_light_is_albedo_times_single_plus_multiple() {
        let particles = random_cloud(10, 9);
        let medium = Medium {
            extinction: 5.0,
            albedo: 0.7,
            ..Default::default()
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
        // At a voxel centre the multiple part is that voxel's value.
        let idx = ill.grid.index(3, 4, 5);
        let x = ill.grid.voxel_centre(3, 4, 5);
        let expected =
            (single_scattering_at(&ill.lights, x) + ill.multiple.total[idx]) * ill.albedo;
        assert!((ill.scattered_at(x, DVec3::X) - expected).length() < 1e-12 * expected.length());
        assert!(
            ill.multiple
                .total
                .iter()
                .all(|a| a.is_finite() && a.min_element() >= 0.0)
        );
    }

    /// A Henyey–Greenstein medium: single scattering takes the phase function towards the
    /// camera (forward: the camera looks into the light) and sees the optical depths through the
    /// δ-Eddington depth scale `1 - albedo g²`; the multiple scattering is seen through the phase
    /// function's first three moments. `g = 0` is the isotropic medium exactly.
    #[test]
    fn anisotropic_medium_sees_single_and_multiple_scattering_with_its_phase_function() {
        let particles = random_cloud(12, 4);
        let medium = Medium {
            extinction: 6.0,
            albedo: 0.9,
            anisotropy: 0.7,
        };
        let settings = CloudQualitySettings {
            volume_resolution: 8,
            scatter_iterations: 5,
            ..Default::default()
        };
        let light = LocalLight {
            direction: DVec3::new(0.3, -1.0, 0.2).normalize(),
            irradiance: DVec3::new(1.0, 0.9, 0.8),
        };
        let ill = illuminate(&particles, &medium, 1.0, &[light], &settings).unwrap();
        let x = ill.grid.voxel_centre(4, 3, 4);
        let scale = DeltaEddington::new(ill.albedo, ill.anisotropy).depth_scale;
        assert!((scale - (1.0 - 0.9 * 0.49)).abs() < 1e-6);
        let (vol, e) = &ill.lights[0];
        let tau = vol.optical_depth_at(x);
        let table = ill.beam.as_ref().expect("g > 0 truncates the peak");
        // The beam that never scattered, and its excess spread by the peak scatterings.
        let beam = |cos| {
            let excess = (-tau * scale).exp() - (-tau).exp();
            *e * ((-tau).exp() + excess * table.ratio(cos, tau * (1.0 - scale)))
        };
        let m = &ill.multiple;
        let (mean, flux, quadrupole) = (
            ill.grid.sample_clamped(&m.total, x),
            ill.grid.sample_clamped_array(&m.flux, x),
            ill.grid.sample_clamped_array(&m.quadrupole, x),
        );
        for (ray, cos) in [(-light.direction, 1.0), (light.direction, -1.0)] {
            let (w, g) = (-ray, ill.anisotropy);
            let seen = (mean
                + flux_along(&flux, w) * (3.0 * g)
                + quadrupole_along(&quadrupole, w) * (7.5 * g * g))
                .max(DVec3::ZERO);
            assert_eq!(ill.multiple_towards(x, w), seen);
            let expected = (beam(cos) * henyey_greenstein(ill.anisotropy, cos) + seen) * ill.albedo;
            let got = ill.scattered_at(x, ray);
            assert!(
                (got - expected).length() < 1e-12 * expected.length(),
                "cos {cos}: {got} against {expected}"
            );
        }
        // The multiply scattered light flows on with the light: more of it is seen looking into
        // the light than from where it comes.
        assert!(
            ill.multiple_towards(x, light.direction).x
                > ill.multiple_towards(x, -light.direction).x
        );
        assert!(
            ill.scattered_at(x, -light.direction).x > 10.0 * ill.scattered_at(x, light.direction).x
        );
        let isotropic = Medium {
            anisotropy: 0.0,
            ..medium
        };
        let iso = illuminate(&particles, &isotropic, 1.0, &[light], &settings).unwrap();
        assert!(iso.source.flux.is_empty() && iso.multiple.flux.is_empty());
        assert!(iso.multiple.quadrupole.is_empty() && iso.beam.is_none());
        let plain = scatter(
            &iso.grid,
            iso.k_local,
            iso.albedo,
            settings.scatter_stencil,
            &iso.source.mean,
            5,
        );
        assert_eq!(iso.multiple, plain);
        for ray in [DVec3::X, -light.direction] {
            let expected = (single_scattering_at(&iso.lights, x)
                + iso.grid.sample_clamped(&iso.multiple.total, x))
                * iso.albedo;
            assert!((iso.scattered_at(x, ray) - expected).length() < 1e-15 * expected.length());
        }
        assert_eq!(
            DeltaEddington::new(0.9, 0.0),
            DeltaEddington {
                depth_scale: 1.0,
                albedo: 0.9,
                anisotropy: 0.0
            }
        );
    }
}
