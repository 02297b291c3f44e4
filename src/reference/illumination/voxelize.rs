//! Section 1: the particles' density voxelized on the fine grid, wide particles through coarser
//! density levels.

use std::ops::{Add, Mul};

use bevy::math::DVec3;

use super::interpolation::{
    Entries, axis_clamped, axis_zero_border, overlaps, trilinear, trilinear_of, unravel,
};
use crate::math::{density_level, density_level_sizes, kernel_u2, level_kernel_radius};
use crate::particle::Particle;

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

    /// [`DensityGrid::sample_clamped`] of per-voxel arrays (a [`Flux`](super::Flux), a [`Quadrupole`](super::Quadrupole)), entry
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
        self.averaged_onto(self.n / f)
    }

    /// The same cube at `n <= self.n` voxels per side, each the mean of this grid over its
    /// cube: every voxel of this grid weighed by its overlap with it (mass-exact; contract
    /// section 1). With `self.n = f n`, the mean of its `f³` children.
    pub fn averaged_onto(&self, n: usize) -> DensityGrid {
        assert!((1..=self.n).contains(&n), "{n} must be in 1..={}", self.n);
        let volume = (self.n as f64 / n as f64).powi(3);
        let rho = (0..n * n * n)
            .map(|idx| {
                overlaps(unravel(idx, n), n, self.n)
                    .map(|((i, j, k), w)| w * self.rho[self.index(i, j, k)])
                    .sum::<f64>()
                    / volume
            })
            .collect();
        DensityGrid {
            n,
            centre: self.centre,
            side: self.side,
            h: self.side / n as f64,
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
/// which its radius spans at most 32 voxels, [`density_level`]): large particles (`r >= h`) spread it
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reference::illumination::test_support::*;
    use bevy::math::Vec3;

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
    /// particle just too wide for the level below (16.1–16.5 voxels per radius on its level)
    /// keeps its central column optical depth within 0.1 % of the exact chord integral, as a
    /// particle of 8 fine voxels per radius deposited directly does.
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
        for (n, level) in [(66, 1), (130, 2), (258, 3)] {
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
            assert!(deepest >= Some((n >= 96) as usize), "n = {n}: {deepest:?}");
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
        // Onto a side that does not divide it: still mass-exact, each voxel the fine grid's
        // mean over its cube.
        let odd = fine.averaged_onto(5);
        assert!((odd.h - fine.side / 5.0).abs() < 1e-15);
        assert!((odd.mass() - fine.mass()).abs() < 1e-12 * fine.mass());
        let share = 16.0 / 5.0 - 3.0;
        let first: f64 = (0..4)
            .flat_map(|k| (0..4).flat_map(move |j| (0..4).map(move |i| (i, j, k))))
            .map(|(i, j, k)| {
                let w = |a: usize| if a == 3 { share } else { 1.0 };
                w(i) * w(j) * w(k) * fine.rho[fine.index(i, j, k)]
            })
            .sum();
        let cube = (16.0f64 / 5.0).powi(3);
        assert!((odd.rho[0] - first / cube).abs() < 1e-12 * first.max(1e-300));
    }
}
