//! Section 3: single scattering, and the scattering source the multiple-scattering grid starts
//! from, with its angular moments for an anisotropic medium.

use std::f64::consts::PI;

use bevy::math::DVec3;
use rayon::prelude::*;

use super::interpolation::{overlaps, unravel};
use super::shade::LightVolume;
use super::voxelize::DensityGrid;
use crate::beam_phase::BeamPhase;
use crate::math::henyey_greenstein;
use crate::particle::DeltaM;

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
/// the camera), `d_l` the light's travel direction, `c` the δ-M depth scale
/// ([`DeltaM::depth_scale`]) and `r` the `beam` table's spread of the excess at
/// `m = (1 - c) tau_l` (1 without a table). [`single_scattering_at`] for `g = 0`.
pub fn single_scattering_towards(
    lights: &[(LightVolume, DVec3)],
    p: DVec3,
    (albedo, g): (f64, f64),
    ray: DVec3,
    beam: Option<&BeamPhase>,
) -> DVec3 {
    let scale = DeltaM::new(albedo, g).depth_scale;
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
pub(super) fn quadrupole_along(q: &Quadrupole, w: DVec3) -> DVec3 {
    let zz = -(q[0] + q[1]);
    q[0] * (w.x * w.x)
        + q[1] * (w.y * w.y)
        + zz * (w.z * w.z)
        + (q[2] * (w.x * w.y) + q[3] * (w.x * w.z) + q[4] * (w.y * w.z)) * 2.0
}

/// `F . w` for unit `w`.
pub(super) fn flux_along(f: &Flux, w: DVec3) -> DVec3 {
    f[0] * w.x + f[1] * w.y + f[2] * w.z
}

/// A source or an order of the multiple scattering over the scattering grid (contract
/// section 4): per voxel the mean radiance `(1/4π) ∫ L dω` (`S` of an isotropic medium) and, for
/// an anisotropic medium, the [`Flux`] and the [`Quadrupole`]; both are empty for an isotropic
/// one.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Moments {
    /// Mean radiance per voxel.
    pub mean: Vec<DVec3>,
    /// First angular moment per voxel; empty for an isotropic medium.
    pub flux: Vec<Flux>,
    /// Second angular moment (without its trace) per voxel; empty for an isotropic medium.
    pub quadrupole: Vec<Quadrupole>,
}

impl Moments {
    /// An isotropic source or order.
    pub fn isotropic(mean: Vec<DVec3>) -> Self {
        Self {
            mean,
            flux: Vec::new(),
            quadrupole: Vec::new(),
        }
    }

    /// `self + k other`, voxel by voxel.
    pub(super) fn plus(&self, other: &Moments, k: DVec3) -> Moments {
        Moments {
            mean: zip_with(&self.mean, &other.mean, |a, b| *a + *b * k),
            flux: zip_with(&self.flux, &other.flux, |a, b| {
                std::array::from_fn(|i| a[i] + b[i] * k)
            }),
            quadrupole: zip_with(&self.quadrupole, &other.quadrupole, |a, b| {
                std::array::from_fn(|i| a[i] + b[i] * k)
            }),
        }
    }
}

pub(super) fn zip_with<T, U>(a: &[T], b: &[T], f: impl Fn(&T, &T) -> U) -> Vec<U> {
    a.iter().zip(b).map(|(a, b)| f(a, b)).collect()
}

/// The multiple-scattering source `S_0` of every voxel of `grid` (contract section 3): the
/// mean of [`single_scattering_at`] over the centres of the voxels of `fine` that overlap it
/// (its `f³` children when `fine.n = f grid.n`), weighted by their density and their overlap
/// with it, or by their overlap alone where all of them are empty. Lights with zero irradiance
/// may be left out.
pub fn gather(
    grid: &DensityGrid,
    fine: &DensityGrid,
    lights: &[(LightVolume, DVec3)],
) -> Vec<DVec3> {
    gather_source(grid, fine, lights, DeltaM::new(1.0, 0.0)).mean
}

/// [`gather`] for a medium of δ-M transform `delta` (contract section 3): the lights'
/// beams seen through `delta.depth_scale` of their optical depth, `E_l exp(-c tau_l) / 4π`, and,
/// for an anisotropic medium, their flux `E_l exp(-c tau_l) d_l / 4π` and quadrupole
/// `E_l exp(-c tau_l) (d_l d_l^T - I/3) / 4π` (the moments of a collimated beam), density-weighted
/// alike.
pub fn gather_source(
    grid: &DensityGrid,
    fine: &DensityGrid,
    lights: &[(LightVolume, DVec3)],
    delta: DeltaM,
) -> Moments {
    let beams = |p: DVec3| {
        lights.iter().fold(BeamMoments::default(), |sum, (vol, e)| {
            let t = *e * (-vol.optical_depth_at(p) * delta.depth_scale).exp() / (4.0 * PI);
            sum.plus(&BeamMoments::collimated(t, vol.basis[2]), 1.0)
        })
    };
    let voxels: Vec<BeamMoments> = (0..grid.len())
        .into_par_iter()
        .map(|idx| {
            let (mut weighted, mut mass, mut plain) =
                (BeamMoments::default(), 0.0, BeamMoments::default());
            for ((fi, fj, fk), w) in overlaps(unravel(idx, grid.n), grid.n, fine.n) {
                let beams = beams(fine.voxel_centre(fi, fj, fk));
                let rho = w * fine.rho[fine.index(fi, fj, fk)];
                weighted = weighted.plus(&beams, rho);
                plain = plain.plus(&beams, w);
                mass += rho;
            }
            if mass > 0.0 {
                weighted.scaled(1.0 / mass)
            } else {
                plain.scaled(1.0 / (fine.n as f64 / grid.n as f64).powi(3))
            }
        })
        .collect();
    let mean = voxels.iter().map(|b| b.mean).collect();
    if delta.anisotropy == 0.0 {
        return Moments::isotropic(mean);
    }
    Moments {
        mean,
        flux: voxels.iter().map(|b| b.flux).collect(),
        quadrupole: voxels.iter().map(|b| b.quadrupole).collect(),
    }
}

/// The mean, flux and quadrupole of one point's beams.
#[derive(Clone, Copy, Default)]
struct BeamMoments {
    mean: DVec3,
    flux: Flux,
    quadrupole: Quadrupole,
}

impl BeamMoments {
    /// A collimated beam of mean radiance `t` travelling along the unit direction `d`.
    fn collimated(t: DVec3, d: DVec3) -> Self {
        Self {
            mean: t,
            flux: [t * d.x, t * d.y, t * d.z],
            quadrupole: quadrupole_basis(d).map(|q| t * q),
        }
    }

    /// `self + k other`.
    fn plus(&self, other: &Self, k: f64) -> Self {
        Self {
            mean: self.mean + other.mean * k,
            flux: std::array::from_fn(|i| self.flux[i] + other.flux[i] * k),
            quadrupole: std::array::from_fn(|i| self.quadrupole[i] + other.quadrupole[i] * k),
        }
    }

    fn scaled(&self, k: f64) -> Self {
        Self::default().plus(self, k)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reference::illumination::test_support::*;
    use crate::reference::illumination::{shade, voxelize};

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
}
