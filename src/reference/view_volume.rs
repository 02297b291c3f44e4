//! CPU reference of a cloud's view transmittance volume (`docs/illumination.md` §5, "View
//! transmittance"): the optical depth from the camera to every point of the cloud, marched through
//! the fine density grid along the view rays of a frustum-aligned grid.
//!
//! Nodes sit on `n` rays per axis spanning the cloud's tangent rectangle (`u = x / depth`,
//! `v = y / depth` in view space) and on `d` view depths spanning its depth range. Along each ray
//! `tau_k = tau_{k-1} + K (rho_{k-1} + rho_k) / 2 * dz sqrt(1 + u² + v²)`, with `tau_0 = 0` at
//! the cloud's nearest depth (or the near plane), so the volume holds world optical depth.

use bevy::math::DVec3;

use crate::reference::{
    camera::PinholeCamera, composite::CloudPlacement, illumination::DensityGrid,
};

/// One cloud's optical depth towards one camera.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewVolume {
    /// Eye, world metres.
    pub eye: DVec3,
    /// The camera's unit basis: right, up, forward (world).
    pub basis: [DVec3; 3],
    /// Tangent rectangle `[u0, u1, v0, v1]` of the nodes' rays.
    pub rect: [f64; 4],
    /// View depths `[z0, z1]` of the first and last slice, world metres.
    pub depth: [f64; 2],
    /// Rays per side `n >= 2`.
    pub n: usize,
    /// Slices `d >= 2`.
    pub d: usize,
    /// World optical depth at node `(i, j, k)`, index `i + n (j + n k)`.
    pub optical_depth: Vec<f64>,
    /// The front map: at column `(i, j)`, index `i + n j`, the optical depth along its ray of the
    /// clouds wholly in front of this one ([`Self::sum_front`]); empty when none is.
    pub front: Vec<f64>,
}

/// The cube of `fine` in world space, its 8 corners.
fn world_corners(fine: &DensityGrid, placement: &CloudPlacement) -> [DVec3; 8] {
    let half = fine.side * 0.5;
    std::array::from_fn(|c| {
        let sign = |bit: usize| if c & bit == 0 { -half } else { half };
        placement.world_point(fine.centre + DVec3::new(sign(1), sign(2), sign(4)))
    })
}

/// Where a cloud's view volume lies: tangent rectangle and depth range, or `None` when the cloud's
/// cube is wholly behind the near plane or outside the view's tangent rectangle.
pub fn view_bounds(
    eye: DVec3,
    basis: [DVec3; 3],
    near: f64,
    frustum: [f64; 4],
    corners: &[DVec3; 8],
) -> Option<([f64; 4], [f64; 2])> {
    let view = corners.map(|c| {
        let d = c - eye;
        DVec3::new(d.dot(basis[0]), d.dot(basis[1]), d.dot(basis[2]))
    });
    let nearest = view.iter().map(|p| p.z).fold(f64::INFINITY, f64::min);
    let farthest = view.iter().map(|p| p.z).fold(f64::NEG_INFINITY, f64::max);
    let z0 = nearest.max(near);
    if farthest <= z0 {
        return None;
    }
    let mut rect = frustum;
    if nearest > near {
        // The cube is wholly ahead: its corners bound its rays (each face is convex).
        let (mut u0, mut u1, mut v0, mut v1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for p in &view {
            let (u, v) = (p.x / p.z, p.y / p.z);
            (u0, u1, v0, v1) = (u0.min(u), u1.max(u), v0.min(v), v1.max(v));
        }
        rect = [
            u0.max(frustum[0]),
            u1.min(frustum[1]),
            v0.max(frustum[2]),
            v1.min(frustum[3]),
        ];
    }
    (rect[0] < rect[1] && rect[2] < rect[3]).then_some((rect, [z0, farthest]))
}

/// Node `i` of `count` spread evenly over `[a, b]`.
fn node(i: usize, count: usize, a: f64, b: f64) -> f64 {
    a + (b - a) * i as f64 / (count - 1) as f64
}

impl ViewVolume {
    /// Marches `n` x `n` rays of `d` slices through `fine` (cloud-local, zero outside), `n = d =`
    /// the fine grid's resolution, for a cloud at `placement` with world extinction `extinction`
    /// (1/m at density 1). `None` when the cloud is not in front of the camera.
    pub fn march(
        camera: &PinholeCamera,
        fine: &DensityGrid,
        placement: &CloudPlacement,
        extinction: f64,
    ) -> Option<Self> {
        let basis = [camera.right, camera.up, camera.forward];
        let aspect = camera.width as f64 / camera.height as f64;
        let (tu, tv) = (camera.tan_half_fov * aspect, camera.tan_half_fov);
        let (rect, depth) = view_bounds(
            camera.position,
            basis,
            camera.near,
            [-tu, tu, -tv, tv],
            &world_corners(fine, placement),
        )?;
        let (n, d) = (fine.n.max(2), fine.n.max(2));
        let dz = (depth[1] - depth[0]) / (d - 1) as f64;
        let mut optical_depth = vec![0.0; n * n * d];
        for j in 0..n {
            for i in 0..n {
                let (u, v) = (node(i, n, rect[0], rect[1]), node(j, n, rect[2], rect[3]));
                let step = extinction * dz * (1.0 + u * u + v * v).sqrt() * 0.5;
                let density = |z: f64| {
                    let world = camera.position + (basis[0] * u + basis[1] * v + basis[2]) * z;
                    fine.sample(placement.local_point(world))
                };
                let (mut tau, mut before) = (0.0, density(depth[0]));
                for k in 1..d {
                    let here = density(node(k, d, depth[0], depth[1]));
                    tau += (before + here) * step;
                    optical_depth[i + n * (j + n * k)] = tau;
                    before = here;
                }
            }
        }
        Some(Self {
            eye: camera.position,
            basis,
            rect,
            depth,
            n,
            d,
            optical_depth,
            front: Vec::new(),
        })
    }

    /// Whether this cloud lies wholly in front of `behind`: its last slice before the other's
    /// first, so all of its optical depth along a ray is in front of every point of `behind`.
    pub fn wholly_in_front_of(&self, behind: &ViewVolume) -> bool {
        self.depth[1] <= behind.depth[0]
    }

    /// View-space tangents `(u, v)` and depth of world point `x`.
    fn tangents(&self, x: DVec3) -> (f64, f64, f64) {
        let p = x - self.eye;
        let z = p.dot(self.basis[2]);
        (p.dot(self.basis[0]) / z, p.dot(self.basis[1]) / z, z)
    }

    /// The four columns about the ray of tangents `(u, v)`, clamped to the rectangle of rays:
    /// `(i, j, weight)`.
    fn columns(&self, u: f64, v: f64) -> [(usize, usize, f64); 4] {
        let r = &self.rect;
        let at = |t: f64| {
            let g = (t * (self.n - 1) as f64).clamp(0.0, (self.n - 1) as f64);
            let i = (g.floor() as usize).min(self.n - 2);
            (i, g - i as f64)
        };
        let ((i, fu), (j, fv)) = (
            at((u - r[0]) / (r[1] - r[0])),
            at((v - r[2]) / (r[3] - r[2])),
        );
        [
            (i, j, (1.0 - fu) * (1.0 - fv)),
            (i + 1, j, fu * (1.0 - fv)),
            (i, j + 1, (1.0 - fu) * fv),
            (i + 1, j + 1, fu * fv),
        ]
    }

    /// Optical depth along the whole ray of tangents `(u, v)`: bilinear in the last slice, 0 off
    /// the rectangle of rays.
    pub fn along(&self, u: f64, v: f64) -> f64 {
        let r = &self.rect;
        if u < r[0] || u > r[1] || v < r[2] || v > r[3] {
            return 0.0;
        }
        let last = self.n * self.n * (self.d - 1);
        self.columns(u, v)
            .iter()
            .map(|&(i, j, w)| w * self.optical_depth[last + i + self.n * j])
            .sum()
    }

    /// Fills the front map from the clouds wholly in front of this one: at each column, the sum
    /// of their optical depth along its ray. The GPU sums it once per view (`sum_front`), so each
    /// pixel reads it instead of looking each of them up.
    pub fn sum_front<'v>(&mut self, fronts: impl Iterator<Item = &'v ViewVolume>) {
        let fronts: Vec<&ViewVolume> = fronts.collect();
        if fronts.is_empty() {
            self.front.clear();
            return;
        }
        let n = self.n;
        self.front = (0..n * n)
            .map(|c| {
                let u = node(c % n, n, self.rect[0], self.rect[1]);
                let v = node(c / n, n, self.rect[2], self.rect[3]);
                fronts.iter().map(|f| f.along(u, v)).sum()
            })
            .collect();
    }

    /// The front map at world point `x`'s ray: bilinear, clamped to the rectangle of rays.
    pub fn front_at(&self, x: DVec3) -> f64 {
        if self.front.is_empty() {
            return 0.0;
        }
        let (u, v, _) = self.tangents(x);
        self.columns(u, v)
            .iter()
            .map(|&(i, j, w)| w * self.front[i + self.n * j])
            .sum()
    }

    /// Optical depth from the camera to world point `x`: trilinear between nodes, clamped to the
    /// volume (0 before its first slice, the full depth behind its last), and 0 off its rectangle
    /// of rays, whose edges only graze the cloud's cube (the view volume of another cloud is
    /// looked up there).
    pub fn optical_depth_at(&self, x: DVec3) -> f64 {
        let (u, v, z) = self.tangents(x);
        let r = &self.rect;
        if z <= self.depth[0] || u < r[0] || u > r[1] || v < r[2] || v > r[3] {
            return 0.0;
        }
        let coords = [
            ((u - r[0]) / (r[1] - r[0]), self.n),
            ((v - r[2]) / (r[3] - r[2]), self.n),
            (
                (z - self.depth[0]) / (self.depth[1] - self.depth[0]),
                self.d,
            ),
        ]
        .map(|(t, count)| {
            let g = (t * (count - 1) as f64).clamp(0.0, (count - 1) as f64);
            let i = (g.floor() as usize).min(count - 2);
            (i, g - i as f64)
        });
        let mut tau = 0.0;
        for corner in 0..8 {
            let pick = |axis: usize| {
                let (i, f) = coords[axis];
                if corner >> axis & 1 == 0 {
                    (i, 1.0 - f)
                } else {
                    (i + 1, f)
                }
            };
            let ((i, wi), (j, wj), (k, wk)) = (pick(0), pick(1), pick(2));
            tau += wi * wj * wk * self.optical_depth[i + self.n * (j + self.n * k)];
        }
        tau
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::particle_optical_depth;
    use crate::particle::Particle;
    use crate::reference::illumination::voxelize;
    use bevy::math::{DQuat, Vec3};

    #[test]
    fn optical_depth_through_a_particle_matches_its_chord_integral() {
        // One particle 5 m ahead, scaled by 2 into the world (R = 1.2), on a 128³ grid.
        let particle = Particle {
            position: Vec3::ZERO,
            radius: 0.6,
            density: 1.5,
        };
        let fine = voxelize(&[particle], 128).unwrap();
        let placement = CloudPlacement {
            translation: DVec3::new(0.0, 0.0, -5.0),
            rotation: DQuat::from_rotation_y(0.3),
            scale: 2.0,
        };
        let camera = PinholeCamera::looking_at(DVec3::ZERO, DVec3::NEG_Z, DVec3::Y, 40.0, 64, 48);
        let volume = ViewVolume::march(&camera, &fine, &placement, 0.8).unwrap();
        for b in [0.0, 0.3, 0.7] {
            let behind = DVec3::new(b, 0.0, -7.0);
            let w = behind.normalize();
            // Impact parameter of the ray from the eye through `behind` to the centre.
            let impact = (DVec3::new(0.0, 0.0, -5.0) - w * (w.z * -5.0)).length();
            let exact = particle_optical_depth(0.8, 1.5, 1.2, impact);
            let got = volume.optical_depth_at(behind);
            assert!(
                (got - exact).abs() < 0.03 * particle_optical_depth(0.8, 1.5, 1.2, 0.0),
                "b {b}: {got} vs {exact}"
            );
            // In front of the particle nothing has been crossed yet.
            assert!(volume.optical_depth_at(w * 3.5) < 1e-9);
        }
    }

    #[test]
    fn a_cloud_behind_the_camera_has_no_volume() {
        let particle = Particle {
            position: Vec3::ZERO,
            radius: 0.5,
            density: 1.0,
        };
        let fine = voxelize(&[particle], 16).unwrap();
        let camera = PinholeCamera::looking_at(DVec3::ZERO, DVec3::NEG_Z, DVec3::Y, 40.0, 64, 48);
        let behind = CloudPlacement::at(DVec3::new(0.0, 0.0, 3.0));
        assert!(ViewVolume::march(&camera, &fine, &behind, 1.0).is_none());
        // A cloud holding the camera starts at the near plane and covers the whole view.
        let around = CloudPlacement::at(DVec3::ZERO);
        let volume = ViewVolume::march(&camera, &fine, &around, 1.0).unwrap();
        assert_eq!(volume.depth[0], camera.near);
        assert!(volume.rect[1] > 0.0 && volume.rect[0] < 0.0);
    }
}
