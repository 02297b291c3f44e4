//! Section 2: each light's optical depth on its light-aligned volume, marched slice by slice.

use bevy::math::DVec3;
use rayon::prelude::*;

use super::interpolation::{axis_clamped, trilinear, unravel};
use super::voxelize::DensityGrid;
use crate::math::light_basis;

/// One light's optical depth sampled on its light-aligned box (contract section 2).
#[derive(Clone, Debug, PartialEq)]
pub struct LightVolume {
    /// Voxels per axis, `m`: the fine grid's ([`CloudQualitySettings::light_resolution`](crate::settings::CloudQualitySettings::light_resolution)).
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reference::illumination::test_support::*;
    use crate::reference::illumination::voxelize;

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
}
