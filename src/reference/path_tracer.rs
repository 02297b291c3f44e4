//! CPU ground-truth volumetric path tracer for exactly the model of docs/physics.md.
//!
//! What it computes, per camera ray `x_t = o + t w`:
//!
//! ```text
//! L = ∫ T(0,t) σ_s(x_t) S(x_t) dt + T(0,∞) L_background
//! S = (1/4π) ( Σ_l E_l T_l(x) + ∫ L(x, w') dw' )
//! ```
//!
//! with the exact particle kernel, Henyey–Greenstein scattering (isotropic by default), all
//! scattering orders, opaque unlit objects
//! ending rays (camera, scattered and shadow rays alike) and the constant background radiance seen by
//! every ray that escapes.
//!
//! How it estimates it (each step unbiased):
//!
//! - **Free flights** by delta tracking against a piecewise-constant majorant: a uniform grid over
//!   the clouds stores, per cell, an upper bound of `σ_t` and the list of particles overlapping the
//!   cell; rays walk the grid with a 3D DDA. A real collision at `x` happens with density
//!   `T(0,t) σ_t(x_t)`, so weighting by `σ_s/σ_t` turns it into an estimate of the first integral.
//! - **Next-event estimation** at every real collision: each directional light adds
//!   `(σ_s/σ_t) · E_l T_l(x) p(x, cos θ_l)`, `p` the phase function of the media at `x` (where
//!   clouds of different anisotropies overlap, the mixture of theirs weighted by their `σ_s`) and
//!   `θ_l` the angle between the light's travel direction and the way back along the path.
//!   `T_l` is computed *exactly*: the optical depth of one particle
//!   along a straight segment is a polynomial integral, so summing it over the particles of the cells
//!   the shadow ray crosses gives `T_l` without noise ([`Media::optical_depth`]). Shadow rays hitting
//!   an opaque object carry nothing (objects are unlit and block the light, which comes from infinity).
//!   [`transmittance`] (ratio tracking) is the stochastic alternative, kept for media without a
//!   closed form and for tests.
//! - **Multiple scattering**: the `∫ p L dw'` term is estimated by continuing the path in a
//!   direction sampled from the phase function itself (so the weight is 1): uniformly for the
//!   isotropic medium, by inverting the Henyey–Greenstein distribution otherwise, the component
//!   of a mixture chosen in proportion to its `σ_s`. Russian roulette with survival
//!   probability `σ_s/σ_t` replaces the albedo weight, so every path has weight 1 and ends by
//!   absorption, by escaping (adding `L_background`) or by hitting an object (adding its `color`).
//!   Directional lights are delta distributions: an escaping ray never "sees" them, so there is no
//!   double counting with next-event estimation.
//!
//! Transport is grey (the albedo is a scalar per cloud), so paths carry a scalar weight and colour
//! only enters through `E_l`, `L_background` and the objects' `color` and `reflectance`.
//!
//! Lit objects (a `reflectance`) reflect, as Lambertian surfaces, the irradiance of the lights
//! (shadow rays, blocked by objects and attenuated by the clouds with the exact transmittance)
//! and of the sky (one cosine-distributed direction per path, blocked or attenuated alike);
//! light the clouds scatter onto them is not part of the model (docs/physics.md).
//!
//! Camera rays start at the eye (`t = 0`, as in docs/physics.md), not at Bevy's near plane.

use std::ops::ControlFlow;
use std::sync::{
    Arc,
    atomic::{AtomicUsize, Ordering},
};

use bevy::math::DVec3;
use rayon::prelude::*;

use crate::fog::Fog;
use crate::math::{INV_4PI, SplitMix64, henyey_greenstein, kernel_u2, light_basis};
use crate::reference::camera::PinholeCamera;
use crate::reference::geometry::{box_interval, nearest_object, object_normal};
use crate::reference::metrics::relative_rmse;
use crate::scene::{ResolvedCloud, Scene, SceneObject};

/// Safety cap on real scattering events per path. It is the only source of bias: paths are cut
/// after this many events. With Russian roulette on the albedo a path of albedo `ω < 1` has
/// `ω/(1-ω)` events on average (99 for `ω = 0.99`); at `ω = 1` paths end by escaping, after about
/// `τ²` events in a medium of optical radius `τ`, so the cap only matters for `τ ≳ 300`.
pub const MAX_SCATTER_EVENTS: u32 = 100_000;

/// Called as rows of the image are finished, with `(rows done, rows in all)`, from any thread.
#[derive(Clone)]
pub struct Progress(pub Arc<dyn Fn(usize, usize) + Send + Sync>);

impl Progress {
    /// A callback from a closure.
    pub fn new(report: impl Fn(usize, usize) + Send + Sync + 'static) -> Self {
        Self(Arc::new(report))
    }
}

impl std::fmt::Debug for Progress {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Progress(..)")
    }
}

/// Settings of [`render`].
#[derive(Clone, Debug)]
pub struct PathTracerSettings {
    /// Paths per pixel, each through a uniformly jittered point of the pixel (0 is taken as 1).
    pub samples_per_pixel: u32,
    /// Seed of all random numbers; the image is a deterministic function of the scene and this
    /// seed, whatever the number of threads.
    pub seed: u64,
    /// Told how many rows are finished, as they finish.
    pub progress: Option<Progress>,
}

impl Default for PathTracerSettings {
    fn default() -> Self {
        Self {
            samples_per_pixel: 256,
            seed: 0,
            progress: None,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Media
// ---------------------------------------------------------------------------------------------

/// Extinction and scattering coefficients at a point, 1/m.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Coefficients {
    /// `σ_t`, summed over all clouds.
    pub extinction: f64,
    /// `σ_s = Σ_clouds ω_c σ_t,c`.
    pub scattering: f64,
}

/// A stretch `[t0, t1)` of a ray (metres along a unit direction) over which `σ_t <= majorant`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    /// Start of the stretch, metres along the ray.
    pub t0: f64,
    /// End of the stretch (exclusive), metres along the ray.
    pub t1: f64,
    /// Upper bound of `σ_t` over the stretch, 1/m, `> 0`.
    pub majorant: f64,
    /// Opaque handle the media uses to evaluate coefficients inside the stretch (a grid cell).
    pub cell: u32,
}

/// A participating medium as the tracker sees it. Implemented by [`ParticleMedia`]; tests add
/// analytic media through the same interface.
pub trait Media: Sync {
    /// Visits, in increasing `t`, disjoint segments within `[0, t_max]` of the ray
    /// `origin + t dir` (`dir` unit) that cover every point where `σ_t` may be non-zero.
    /// Stops early when `visit` breaks, and then returns `Break`.
    fn visit_segments(
        &self,
        origin: DVec3,
        dir: DVec3,
        t_max: f64,
        visit: impl FnMut(Segment) -> ControlFlow<()>,
    ) -> ControlFlow<()>;

    /// Coefficients at `x`, a point of `segment` (given so the media can look up its cell).
    fn coefficients(&self, x: DVec3, segment: &Segment) -> Coefficients;

    /// Exact optical depth `∫_0^t_max σ_t(origin + t dir) dt` (dimensionless); `t_max` may be `∞`.
    fn optical_depth(&self, origin: DVec3, dir: DVec3, t_max: f64) -> f64;

    /// The phase function (per steradian) at `x`, where `σ_s > 0`, at the cosine between the
    /// light's travel direction and the scattered direction. Isotropic unless overridden.
    fn phase(&self, _x: DVec3, _cos_theta: f64) -> f64 {
        INV_4PI
    }

    /// A direction scattered at `x` from the travel direction `dir` (unit), with the phase
    /// function at `x` as its pdf. Uniform unless overridden.
    fn scatter_direction(&self, _x: DVec3, _dir: DVec3, rng: &mut SplitMix64) -> DVec3 {
        rng.unit_sphere()
    }
}

/// One particle as the tracer stores it: world centre and precomputed constants.
#[derive(Clone, Copy, Debug)]
struct TracedParticle {
    /// World centre, metres.
    centre: DVec3,
    /// Radius, metres.
    radius: f64,
    /// `1 / r²`, 1/m².
    inv_r2: f64,
    /// `σ_t` at the centre: `K η`, 1/m.
    extinction_peak: f64,
    /// `σ_s` at the centre: `ω K η`, 1/m.
    scattering_peak: f64,
    /// Henyey–Greenstein `g` of its cloud's medium.
    anisotropy: f64,
}

impl TracedParticle {
    /// `(σ_t, σ_s)` contribution at `x`.
    #[inline]
    fn coefficients(&self, x: DVec3) -> (f64, f64) {
        let k = kernel_u2((x - self.centre).length_squared() * self.inv_r2);
        (self.extinction_peak * k, self.scattering_peak * k)
    }

    /// Optical depth of this particle along `origin + t dir` (`dir` unit) for `t ∈ [t0, t1]`.
    ///
    /// With `s = t - t_c` measured from the closest approach and `a = 1 - b²/r²`, the kernel is
    /// `(a - s²/r²)²`, whose antiderivative in `u = s/r` is `r (a² u - 2a u³/3 + u⁵/5)`; over the
    /// whole chord this gives docs/physics.md's `K η r 16/15 a^(5/2)`. Measuring from the closest approach
    /// keeps the polynomial well conditioned.
    fn optical_depth(&self, origin: DVec3, dir: DVec3, t0: f64, t1: f64) -> f64 {
        let v = self.centre - origin;
        let t_c = v.dot(dir);
        // |v × dir|² is the squared distance of the line from the centre, without cancellation.
        let a = 1.0 - v.cross(dir).length_squared() * self.inv_r2;
        if a <= 0.0 {
            return 0.0;
        }
        let half = self.radius * a.sqrt();
        let lo = t0.max(t_c - half);
        let hi = t1.min(t_c + half);
        if hi <= lo {
            return 0.0;
        }
        let g = |u: f64| {
            let u2 = u * u;
            u * (a * a - u2 * (2.0 / 3.0 * a - 0.2 * u2))
        };
        let inv_r = self.inv_r2.sqrt();
        self.extinction_peak * self.radius * (g((hi - t_c) * inv_r) - g((lo - t_c) * inv_r))
    }
}

/// The clouds of a scene in world space with a uniform majorant grid.
///
/// Each cell stores the particles whose support overlaps it and the majorant
/// `Σ_i K_i η_i k(d_i / r_i)`, `d_i` the distance from particle `i`'s centre to the closest point of
/// the cell: since each kernel is largest where it is closest to its centre, this bounds `σ_t` over
/// the cell (tighter than `Σ K η`, which it never exceeds).
#[derive(Clone, Debug)]
pub struct ParticleMedia {
    particles: Vec<TracedParticle>,
    /// Lower corner of the grid, metres.
    lo: DVec3,
    /// Upper corner of the grid, metres.
    hi: DVec3,
    /// Edge of a (cubic) cell, metres.
    cell_size: f64,
    dims: [usize; 3],
    /// Per-cell majorant of `σ_t`, 1/m.
    majorant: Vec<f64>,
    /// Particles of cell `c`: `cell_particles[cell_start[c]..cell_start[c + 1]]`.
    cell_start: Vec<u32>,
    cell_particles: Vec<u32>,
    /// The anisotropy every particle shares, when they do (the common case: then the phase
    /// function needs no lookup).
    uniform_anisotropy: Option<f64>,
}

/// Largest number of grid cells; the cell size grows to respect it.
const MAX_GRID_CELLS: usize = 1 << 22;
/// Largest number of particle–cell list entries (4 bytes each); the cell size grows to respect it.
const MAX_LIST_ENTRIES: usize = 1 << 25;
/// Cell edge as a fraction of the median particle radius. Smaller cells give tighter majorants
/// (fewer null collisions) and shorter lists, but each particle is then visited in more cells by the
/// exact shadow-ray optical depth; 0.5 was fastest on 100–2000-particle clouds (0.3–1.5 tried).
const CELL_PER_RADIUS: f64 = 0.5;

impl ParticleMedia {
    /// The media of a scene's clouds.
    pub fn from_scene(scene: &Scene) -> Self {
        Self::new(&scene.clouds)
    }

    /// World-space media of `clouds` (world = local + translation). Particles that cannot
    /// attenuate (`K η = 0`) are dropped.
    pub fn new(clouds: &[ResolvedCloud]) -> Self {
        let particles: Vec<TracedParticle> = clouds
            .iter()
            .flat_map(|cloud| {
                let k = cloud.medium.extinction as f64;
                let omega = cloud.medium.albedo as f64;
                let anisotropy = cloud.medium.anisotropy as f64;
                let offset = cloud.translation.as_dvec3();
                cloud.particles.iter().map(move |p| {
                    let r = p.radius as f64;
                    let peak = k * p.density as f64;
                    TracedParticle {
                        centre: p.position.as_dvec3() + offset,
                        radius: r,
                        inv_r2: 1.0 / (r * r),
                        extinction_peak: peak,
                        scattering_peak: omega * peak,
                        anisotropy,
                    }
                })
            })
            .filter(|p| p.extinction_peak > 0.0)
            .collect();
        Self::build(particles)
    }

    /// Number of particles that can attenuate.
    pub fn particle_count(&self) -> usize {
        self.particles.len()
    }

    /// Cells per axis of the majorant grid.
    pub fn grid_dims(&self) -> [usize; 3] {
        self.dims
    }

    fn build(particles: Vec<TracedParticle>) -> Self {
        if particles.is_empty() {
            return Self {
                particles,
                lo: DVec3::ZERO,
                hi: DVec3::ZERO,
                cell_size: 1.0,
                dims: [0; 3],
                majorant: Vec::new(),
                cell_start: vec![0],
                cell_particles: Vec::new(),
                uniform_anisotropy: Some(0.0),
            };
        }
        let first = particles[0].anisotropy;
        let uniform_anisotropy = particles
            .iter()
            .all(|p| p.anisotropy == first)
            .then_some(first);
        let (lo, hi) = particles
            .iter()
            .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(lo, hi), p| {
                (lo.min(p.centre - p.radius), hi.max(p.centre + p.radius))
            });
        let (cell_size, dims) = grid_shape(&particles, lo, hi);
        let hi = lo + cell_size * DVec3::new(dims[0] as f64, dims[1] as f64, dims[2] as f64);
        let mut media = Self {
            particles,
            lo,
            hi,
            cell_size,
            dims,
            majorant: vec![0.0; dims[0] * dims[1] * dims[2]],
            cell_start: Vec::new(),
            cell_particles: Vec::new(),
            uniform_anisotropy,
        };
        media.fill_cells();
        media
    }

    /// Two passes over the particle–cell overlaps: count, then fill (compressed rows).
    fn fill_cells(&mut self) {
        let n = self.majorant.len();
        let mut counts = vec![0u32; n + 1];
        for p in &self.particles {
            self.for_each_overlap(p, |cell, _| counts[cell + 1] += 1);
        }
        for c in 0..n {
            counts[c + 1] += counts[c];
        }
        let mut cursor = counts.clone();
        let mut lists = vec![0u32; counts[n] as usize];
        let mut majorant = vec![0.0; n];
        for (i, p) in self.particles.iter().enumerate() {
            self.for_each_overlap(p, |cell, k_max| {
                lists[cursor[cell] as usize] = i as u32;
                cursor[cell] += 1;
                majorant[cell] += p.extinction_peak * k_max;
            });
        }
        self.cell_start = counts;
        self.cell_particles = lists;
        self.majorant = majorant;
    }

    /// Calls `f(cell, k_max)` for every cell the particle's support overlaps, `k_max` the largest
    /// kernel value over the cell.
    fn for_each_overlap(&self, p: &TracedParticle, mut f: impl FnMut(usize, f64)) {
        let first = self.cell_of(p.centre - p.radius);
        let last = self.cell_of(p.centre + p.radius);
        for z in first[2]..=last[2] {
            for y in first[1]..=last[1] {
                for x in first[0]..=last[0] {
                    let cell_lo =
                        self.lo + self.cell_size * DVec3::new(x as f64, y as f64, z as f64);
                    let nearest = p.centre.clamp(cell_lo, cell_lo + self.cell_size);
                    let k_max = kernel_u2((p.centre - nearest).length_squared() * p.inv_r2);
                    if k_max > 0.0 {
                        f(self.linear([x, y, z]), k_max);
                    }
                }
            }
        }
    }

    /// Grid coordinates of the cell containing `x`, clamped to the grid.
    fn cell_of(&self, x: DVec3) -> [usize; 3] {
        let rel = (x - self.lo) / self.cell_size;
        let clamp = |v: f64, n: usize| (v.floor().max(0.0) as usize).min(n - 1);
        [
            clamp(rel.x, self.dims[0]),
            clamp(rel.y, self.dims[1]),
            clamp(rel.z, self.dims[2]),
        ]
    }

    #[inline]
    fn linear(&self, [x, y, z]: [usize; 3]) -> usize {
        x + self.dims[0] * (y + self.dims[1] * z)
    }

    /// Particles overlapping a cell.
    #[inline]
    fn cell_list(&self, cell: usize) -> &[u32] {
        &self.cell_particles[self.cell_start[cell] as usize..self.cell_start[cell + 1] as usize]
    }

    /// Coefficients at any world point (looks the cell up from the position).
    pub fn coefficients_at(&self, x: DVec3) -> Coefficients {
        if self.particles.is_empty() || !(x.cmpge(self.lo).all() && x.cmple(self.hi).all()) {
            return Coefficients::default();
        }
        self.cell_coefficients(self.linear(self.cell_of(x)), x)
    }

    /// The majorant of the cell containing `x` (0 outside the grid), 1/m.
    pub fn majorant_at(&self, x: DVec3) -> f64 {
        if self.particles.is_empty() || !(x.cmpge(self.lo).all() && x.cmple(self.hi).all()) {
            return 0.0;
        }
        self.majorant[self.linear(self.cell_of(x))]
    }

    /// The particles of the cell holding `x` (none outside the grid).
    fn particles_near(&self, x: DVec3) -> impl Iterator<Item = &TracedParticle> {
        let inside = !self.particles.is_empty() && x.cmpge(self.lo).all() && x.cmple(self.hi).all();
        let list = if inside {
            self.cell_list(self.linear(self.cell_of(x)))
        } else {
            &[]
        };
        list.iter().map(|&i| &self.particles[i as usize])
    }

    fn cell_coefficients(&self, cell: usize, x: DVec3) -> Coefficients {
        let mut c = Coefficients::default();
        for &i in self.cell_list(cell) {
            let (t, s) = self.particles[i as usize].coefficients(x);
            c.extinction += t;
            c.scattering += s;
        }
        c
    }
}

/// Cell size and cells per axis for particles spanning `[lo, hi]`: `CELL_PER_RADIUS` times the
/// median radius, grown until the grid and its particle lists fit the memory budgets.
fn grid_shape(particles: &[TracedParticle], lo: DVec3, hi: DVec3) -> (f64, [usize; 3]) {
    let mut radii: Vec<f64> = particles.iter().map(|p| p.radius).collect();
    let mid = radii.len() / 2;
    let median = *radii.select_nth_unstable_by(mid, f64::total_cmp).1;
    let extent = (hi - lo).max(DVec3::splat(1e-9));
    let cells = |h: f64| (extent / h).ceil().max(DVec3::ONE);
    // Upper bound of the list entries: a particle overlaps at most (2r/h + 2)³ cells.
    let entries = |h: f64| {
        particles
            .iter()
            .map(|p| (2.0 * p.radius / h + 2.0).powi(3))
            .sum::<f64>()
    };
    let mut h = median * CELL_PER_RADIUS;
    while cells(h).element_product() > MAX_GRID_CELLS as f64 || entries(h) > MAX_LIST_ENTRIES as f64
    {
        h *= 1.25;
    }
    let n = cells(h);
    (h, [n.x as usize, n.y as usize, n.z as usize])
}

impl Media for ParticleMedia {
    /// 3D DDA (Amanatides & Woo) through the grid, skipping empty cells.
    fn visit_segments(
        &self,
        origin: DVec3,
        dir: DVec3,
        t_max: f64,
        mut visit: impl FnMut(Segment) -> ControlFlow<()>,
    ) -> ControlFlow<()> {
        if self.particles.is_empty() {
            return ControlFlow::Continue(());
        }
        let Some((t_enter, t_exit)) = box_interval(self.lo, self.hi, origin, dir) else {
            return ControlFlow::Continue(());
        };
        let t_end = t_exit.min(t_max);
        if t_end.is_nan() || t_end <= t_enter {
            return ControlFlow::Continue(());
        }
        let mut idx = self.cell_of(origin + dir * t_enter);
        let step = dir.to_array().map(|d| (d > 0.0) as i64 - (d < 0.0) as i64);
        // Distance to the next cell boundary on one axis, recomputed exactly from the integer
        // cell index (no accumulated round-off).
        let next_boundary = |axis: usize, i: usize| -> f64 {
            match step[axis] {
                0 => f64::INFINITY,
                s => {
                    let face = i as f64 + (s > 0) as u8 as f64;
                    (self.lo[axis] + face * self.cell_size - origin[axis]) / dir[axis]
                }
            }
        };
        let mut t_next = [0, 1, 2].map(|a| next_boundary(a, idx[a]));
        let mut t = t_enter;
        loop {
            let axis = if t_next[0] <= t_next[1] && t_next[0] <= t_next[2] {
                0
            } else if t_next[1] <= t_next[2] {
                1
            } else {
                2
            };
            let seg_end = t_next[axis].min(t_end);
            if seg_end > t {
                let cell = self.linear(idx);
                let majorant = self.majorant[cell];
                if majorant > 0.0 {
                    visit(Segment {
                        t0: t,
                        t1: seg_end,
                        majorant,
                        cell: cell as u32,
                    })?;
                }
                t = seg_end;
            }
            if t_next[axis] >= t_end {
                return ControlFlow::Continue(());
            }
            let i = idx[axis] as i64 + step[axis];
            if i < 0 || i >= self.dims[axis] as i64 {
                return ControlFlow::Continue(());
            }
            idx[axis] = i as usize;
            t_next[axis] = next_boundary(axis, idx[axis]);
        }
    }

    fn coefficients(&self, x: DVec3, segment: &Segment) -> Coefficients {
        self.cell_coefficients(segment.cell as usize, x)
    }

    /// The `σ_s`-weighted mixture of the particles' phase functions at `x`.
    fn phase(&self, x: DVec3, cos_theta: f64) -> f64 {
        if let Some(g) = self.uniform_anisotropy {
            return henyey_greenstein(g, cos_theta);
        }
        let (mut weighted, mut scattering) = (0.0, 0.0);
        for p in self.particles_near(x) {
            let s = p.coefficients(x).1;
            weighted += s * henyey_greenstein(p.anisotropy, cos_theta);
            scattering += s;
        }
        if scattering > 0.0 {
            weighted / scattering
        } else {
            INV_4PI
        }
    }

    /// Picks the scattering particle in proportion to its `σ_s` at `x`, then samples its
    /// phase function: exactly the mixture's pdf.
    fn scatter_direction(&self, x: DVec3, dir: DVec3, rng: &mut SplitMix64) -> DVec3 {
        if let Some(g) = self.uniform_anisotropy {
            return rng.henyey_greenstein(g, dir);
        }
        let total: f64 = self.particles_near(x).map(|p| p.coefficients(x).1).sum();
        let mut pick = rng.next_f64() * total;
        let mut g = 0.0;
        for p in self.particles_near(x) {
            let s = p.coefficients(x).1;
            if s > 0.0 {
                g = p.anisotropy;
                pick -= s;
                if pick < 0.0 {
                    break;
                }
            }
        }
        rng.henyey_greenstein(g, dir)
    }

    /// Exact: every particle contributes the polynomial integral of its kernel over the part of
    /// its chord inside each cell the ray crosses. A particle whose support meets the ray inside a
    /// cell overlaps that cell, so it is in the cell's list, and the cells' stretches partition the
    /// ray: each piece of each chord is counted exactly once.
    fn optical_depth(&self, origin: DVec3, dir: DVec3, t_max: f64) -> f64 {
        let mut tau = 0.0;
        let _ = self.visit_segments(origin, dir, t_max, |seg| {
            for &i in self.cell_list(seg.cell as usize) {
                tau += self.particles[i as usize].optical_depth(origin, dir, seg.t0, seg.t1);
            }
            ControlFlow::Continue(())
        });
        tau
    }
}

// ---------------------------------------------------------------------------------------------
// Estimators
// ---------------------------------------------------------------------------------------------

/// Delta tracking: samples a real collision along `origin + t dir` (`dir` unit) in `[0, t_max]`
/// with density `T(0,t) σ_t(t)`. Returns the distance (metres) and the coefficients there, or
/// `None` (probability `T(0, t_max)`) when the ray leaves `[0, t_max]` unscattered.
pub fn sample_free_flight<M: Media>(
    media: &M,
    origin: DVec3,
    dir: DVec3,
    t_max: f64,
    rng: &mut SplitMix64,
) -> Option<(f64, Coefficients)> {
    let mut hit = None;
    let _ = media.visit_segments(origin, dir, t_max, |seg| {
        // Exponential steps are memoryless, so restarting at each segment boundary with the new
        // majorant is exact.
        let mut t = seg.t0;
        loop {
            t += rng.exponential() / seg.majorant;
            if t >= seg.t1 {
                return ControlFlow::Continue(());
            }
            let c = media.coefficients(origin + dir * t, &seg);
            // Real collision with probability σ_t / majorant, null collision otherwise.
            if rng.next_f64() * seg.majorant < c.extinction {
                hit = Some((t, c));
                return ControlFlow::Break(());
            }
        }
    });
    hit
}

/// Below this transmittance weight, ratio tracking plays Russian roulette (survive with 1/2,
/// weight doubled): unbiased, and it stops wasting work on rays that carry almost nothing.
const RATIO_TRACKING_ROULETTE: f64 = 0.1;

/// Ratio tracking: an unbiased estimate of the transmittance `exp(-∫_0^t_max σ_t dt)` of the
/// medium alone (objects are not considered) along `origin + t dir`, `dir` unit, `t_max` in metres
/// (may be `∞`). Dimensionless, in `[0, 1]` up to the roulette's weight doubling.
pub fn transmittance<M: Media>(
    media: &M,
    origin: DVec3,
    dir: DVec3,
    t_max: f64,
    rng: &mut SplitMix64,
) -> f64 {
    let mut weight = 1.0;
    let _ = media.visit_segments(origin, dir, t_max, |seg| {
        let mut t = seg.t0;
        loop {
            t += rng.exponential() / seg.majorant;
            if t >= seg.t1 {
                return ControlFlow::Continue(());
            }
            let c = media.coefficients(origin + dir * t, &seg);
            // Each tentative collision multiplies by the null-collision probability.
            weight *= (1.0 - c.extinction / seg.majorant).max(0.0);
            if weight < RATIO_TRACKING_ROULETTE {
                if weight == 0.0 || rng.next_f64() < 0.5 {
                    weight = 0.0;
                    return ControlFlow::Break(());
                }
                weight *= 2.0;
            }
        }
    });
    weight
}

/// A directional light prepared for shadow rays.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DirectionalLight {
    /// Unit direction from the medium towards the light (minus the travel direction).
    pub to_light: DVec3,
    /// Linear RGB irradiance perpendicular to the light's direction.
    pub irradiance: DVec3,
}

/// Everything but the media that a path sees: lights, background and opaque objects.
#[derive(Clone, Debug, PartialEq)]
pub struct Lighting {
    /// Linear RGB radiance of every ray that escapes.
    pub background: DVec3,
    /// The directional lights.
    pub lights: Vec<DirectionalLight>,
    /// Opaque objects: emitting their colour, and reflecting light where they have a reflectance.
    pub objects: Vec<SceneObject>,
    /// Distance fog along the camera's rays (docs/physics.md, "Fog"), if any.
    pub fog: Option<Fog>,
}

/// How far a ray leaving an object's surface starts off it, metres: clear of the surface it
/// leaves for any scene of sane size.
const SURFACE_OFFSET: f64 = 1e-7;

impl Lighting {
    /// The lighting of a scene; lights with a zero direction (refused by validation) are skipped.
    pub fn from_scene(scene: &Scene) -> Self {
        let lights = scene
            .lights
            .iter()
            .filter(|l| l.direction.length_squared() > 0.0)
            .map(|l| DirectionalLight {
                to_light: -l.direction.as_dvec3().normalize(),
                irradiance: l.irradiance.as_dvec3(),
            })
            .collect();
        Self {
            background: scene.background.as_dvec3(),
            lights,
            objects: scene.objects.clone(),
            fog: scene.fog,
        }
    }

    /// The fog's colour along the camera ray `dir` (its glow about each light).
    fn fog_colour(&self, fog: &Fog, dir: DVec3) -> DVec3 {
        fog.colour_towards(dir, self.lights.iter().map(|l| (l.to_light, l.irradiance)))
    }

    /// `Σ_l E_l T_l(x)`: unscattered irradiance at `x` from all lights, with exact transmittance.
    /// An object anywhere on the shadow ray blocks the light entirely.
    pub fn direct_irradiance<M: Media>(&self, media: &M, x: DVec3) -> DVec3 {
        self.single_scattering(media, x, |_| 1.0)
    }

    /// `Σ_l p(cos θ_l) E_l T_l(x)`: the unscattered light of every light scattered at `x`
    /// towards `-dir` (`dir` the unit direction the path arrived along), per unit `σ_s`.
    pub fn in_scattered<M: Media>(&self, media: &M, x: DVec3, dir: DVec3) -> DVec3 {
        // The light travels along -to_light and leaves along -dir: cos θ = to_light · dir.
        self.single_scattering(media, x, |to_light| media.phase(x, to_light.dot(dir)))
    }

    /// The radiance object `index` shows at its surface point `x` (docs/physics.md, "Lit
    /// objects"): its colour, plus `R / π` times the irradiance reaching it from the lights
    /// (blocked by objects, attenuated by every cloud: exact transmittance) and from the sky
    /// (one direction, cosine-distributed about the normal: `π L_background T` where nothing
    /// blocks it), an unbiased estimate.
    pub fn object_radiance<M: Media>(
        &self,
        media: &M,
        index: usize,
        x: DVec3,
        rng: &mut SplitMix64,
    ) -> DVec3 {
        let object = &self.objects[index];
        let emitted = object.color.as_dvec3();
        let reflectance = object.reflectance.as_dvec3();
        if reflectance == DVec3::ZERO {
            return emitted;
        }
        let n = object_normal(object, x);
        let origin = x + n * SURFACE_OFFSET;
        let arriving = |to: DVec3| {
            let blocked = nearest_object(&self.objects, origin, to).is_some();
            if blocked {
                0.0
            } else {
                (-media.optical_depth(origin, to, f64::INFINITY)).exp()
            }
        };
        let mut irradiance = DVec3::ZERO;
        for light in &self.lights {
            let cos = n.dot(light.to_light);
            if cos > 0.0 {
                irradiance += light.irradiance * (cos * arriving(light.to_light));
            }
        }
        if self.background != DVec3::ZERO {
            irradiance +=
                self.background * (std::f64::consts::PI * arriving(cosine_direction(n, rng)));
        }
        emitted + reflectance * irradiance * std::f64::consts::FRAC_1_PI
    }

    fn single_scattering<M: Media>(
        &self,
        media: &M,
        x: DVec3,
        phase: impl Fn(DVec3) -> f64,
    ) -> DVec3 {
        let mut e = DVec3::ZERO;
        for light in &self.lights {
            if nearest_object(&self.objects, x, light.to_light).is_some() {
                continue;
            }
            let tau = media.optical_depth(x, light.to_light, f64::INFINITY);
            e += light.irradiance * ((-tau).exp() * phase(light.to_light));
        }
        e
    }
}

/// A unit direction about the unit normal `n`, with the density `cos θ / π`.
fn cosine_direction(n: DVec3, rng: &mut SplitMix64) -> DVec3 {
    cosine_direction_of(n, [rng.next_f64(), rng.next_f64()])
}

/// The direction [`cosine_direction`] makes of the uniform numbers `u` in `[0, 1)²`.
fn cosine_direction_of(n: DVec3, [u1, u2]: [f64; 2]) -> DVec3 {
    let (r, phi) = (u1.sqrt(), 2.0 * std::f64::consts::PI * u2);
    let [u, v, w] = light_basis(n);
    u * (r * phi.cos()) + v * (r * phi.sin()) + w * (1.0 - u1).max(0.0).sqrt()
}

/// One-sample estimate of the radiance (linear RGB) arriving at `origin` from direction `-dir`
/// (`dir` unit), i.e. docs/physics.md's `L` for the ray `origin + t dir`.
///
/// `max_scatter_events` cuts paths after that many real scattering events (1 gives single
/// scattering exactly; [`MAX_SCATTER_EVENTS`] for the full solution).
pub fn radiance<M: Media>(
    media: &M,
    lighting: &Lighting,
    origin: DVec3,
    dir: DVec3,
    max_scatter_events: u32,
    rng: &mut SplitMix64,
) -> DVec3 {
    let mut total = [DVec3::ZERO];
    radiance_by_order(
        media,
        lighting,
        origin,
        dir,
        max_scatter_events,
        rng,
        &mut total,
    );
    total[0]
}

/// [`radiance`] split by scattering order: `orders[k]` receives the light that reached the camera
/// after exactly `k` scattering events (0: the background or an object seen unscattered), the last
/// entry every order from its own on. The entries sum to [`radiance`]'s estimate.
pub fn radiance_by_order<M: Media>(
    media: &M,
    lighting: &Lighting,
    origin: DVec3,
    dir: DVec3,
    max_scatter_events: u32,
    rng: &mut SplitMix64,
    orders: &mut [DVec3],
) {
    let last = orders.len() - 1;
    let (mut o, mut d) = (origin, dir);
    let mut events = 0;
    // What the fog lets through from the camera ray's end (its first collision or its object).
    let mut fogged = DVec3::ONE;
    loop {
        let object = nearest_object(&lighting.objects, o, d);
        let t_max = object.map_or(f64::INFINITY, |(t, _)| t);
        let collision = sample_free_flight(media, o, d, t_max, rng);
        if events == 0
            && let Some(fog) = &lighting.fog
        {
            // The fog fogs what ends the camera ray, at its distance (the sky is not fogged, as
            // in Bevy). With t the first collision, E[A(t) F] = ∫ T_cloud dA F, the fog of a
            // medium that permeates the cloud (docs/physics.md, "Fog").
            let end = collision.map(|(t, _)| t).or(object.map(|(t, _)| t));
            if let Some(t) = end {
                let at = fog.at(t);
                fogged = at.transmitted;
                orders[0] += at.inscattered * lighting.fog_colour(fog, d);
            }
        }
        let Some((t, c)) = collision else {
            // Unscattered to the end of the ray: the object's radiance or the background.
            orders[(events as usize).min(last)] += fogged
                * match object {
                    Some((t, i)) => lighting.object_radiance(media, i, o + d * t, rng),
                    None => lighting.background,
                };
            return;
        };
        let x = o + d * t;
        // σ_s/σ_t: a real collision was accepted with probability σ_t/majorant > 0, so σ_t > 0.
        let albedo = c.scattering / c.extinction;
        events += 1;
        orders[(events as usize).min(last)] += fogged * lighting.in_scattered(media, x, d) * albedo;
        // Russian roulette on the albedo: survivors keep weight 1.
        if events >= max_scatter_events || rng.next_f64() >= albedo {
            return;
        }
        d = media.scatter_direction(x, d, rng);
        o = x;
    }
}

// ---------------------------------------------------------------------------------------------
// Images
// ---------------------------------------------------------------------------------------------

/// Renders a scene: linear RGB radiance per pixel (alpha 1), row-major, row 0 at the top.
pub fn render(scene: &Scene, settings: &PathTracerSettings) -> Vec<[f32; 4]> {
    let media = ParticleMedia::from_scene(scene);
    let lighting = Lighting::from_scene(scene);
    let camera = PinholeCamera::from_scene(&scene.camera);
    render_media(&media, &lighting, &camera, settings)
}

/// [`render`] split by scattering order: image `k` holds the light scattered exactly `k` times
/// (image 0 the background and objects seen directly), the last image every order from its own
/// on; `orders >= 1` images, which sum to [`render`]'s image.
pub fn render_orders(
    scene: &Scene,
    settings: &PathTracerSettings,
    orders: usize,
) -> Vec<Vec<[f32; 4]>> {
    let media = ParticleMedia::from_scene(scene);
    let lighting = Lighting::from_scene(scene);
    let camera = PinholeCamera::from_scene(&scene.camera);
    render_media_orders(&media, &lighting, &camera, settings, orders)
}

/// [`render`] for any media: rows in parallel, each sample with its own generator seeded from
/// `(seed, pixel, sample)`, so the image does not depend on the number of threads.
pub fn render_media<M: Media>(
    media: &M,
    lighting: &Lighting,
    camera: &PinholeCamera,
    settings: &PathTracerSettings,
) -> Vec<[f32; 4]> {
    render_media_orders(media, lighting, camera, settings, 1)
        .pop()
        .expect("one image")
}

/// [`render_orders`] for any media.
pub fn render_media_orders<M: Media>(
    media: &M,
    lighting: &Lighting,
    camera: &PinholeCamera,
    settings: &PathTracerSettings,
    orders: usize,
) -> Vec<Vec<[f32; 4]>> {
    let orders = orders.max(1);
    let (width, height) = (camera.width as usize, camera.height as usize);
    let mut pixels = vec![vec![DVec3::ZERO; orders]; width * height];
    if width > 0 && height > 0 {
        let rows_done = AtomicUsize::new(0);
        pixels
            .par_chunks_mut(width)
            .enumerate()
            .for_each(|(py, row)| {
                for (px, out) in row.iter_mut().enumerate() {
                    let pixel = (py * width + px) as u64;
                    pixel_radiance(media, lighting, camera, settings, pixel, px, py, out);
                }
                let done = rows_done.fetch_add(1, Ordering::Relaxed) + 1;
                if let Some(Progress(report)) = &settings.progress {
                    report(done, height);
                }
            });
    }
    (0..orders)
        .map(|k| {
            pixels
                .iter()
                .map(|p| [p[k].x as f32, p[k].y as f32, p[k].z as f32, 1.0])
                .collect()
        })
        .collect()
}

/// Mean radiance of `samples_per_pixel` paths through jittered points of pixel `(px, py)`, split
/// into `orders.len()` scattering orders.
#[allow(clippy::too_many_arguments)]
fn pixel_radiance<M: Media>(
    media: &M,
    lighting: &Lighting,
    camera: &PinholeCamera,
    settings: &PathTracerSettings,
    pixel: u64,
    px: usize,
    py: usize,
    orders: &mut [DVec3],
) {
    let spp = settings.samples_per_pixel.max(1);
    for s in 0..spp {
        let mut rng = SplitMix64::for_sample(settings.seed, pixel, s as u64);
        let x = px as f64 + rng.next_f64();
        let y = py as f64 + rng.next_f64();
        let dir = camera.ray_direction(x, y);
        radiance_by_order(
            media,
            lighting,
            camera.position,
            dir,
            MAX_SCATTER_EVENTS,
            &mut rng,
            orders,
        );
    }
    orders.iter_mut().for_each(|o| *o /= spp as f64);
}

/// Noise level of a path-traced image (docs/physics.md): the relative RMSE between two independent
/// renders (different seeds, same sample count) divided by `√2`, which estimates the relative RMSE
/// of one render against the noise-free image. Dimensionless.
pub fn noise_level(a: &[[f32; 4]], b: &[[f32; 4]]) -> f64 {
    relative_rmse(a, b) / std::f64::consts::SQRT_2
}

#[cfg(test)]
mod tests {
    //! Analytic checks of the estimators and of the whole tracer. Monte Carlo comparisons use
    //! tolerances of 4–5 standard errors (estimated from the samples themselves), so a correct
    //! tracer fails them with negligible probability, and the seeds are fixed anyway.

    use super::*;
    use crate::math::particle_optical_depth;
    use crate::particle::{LightSample, Medium, Particle};
    use crate::scene::{ObjectShape, SceneCamera};
    use crate::settings::CloudQualitySettings;
    use bevy::math::Vec3;

    fn cloud(
        translation: Vec3,
        extinction: f32,
        albedo: f32,
        particles: Vec<Particle>,
    ) -> ResolvedCloud {
        ResolvedCloud {
            translation,
            medium: Medium {
                extinction,
                albedo,
                ..Default::default()
            },
            particles,
        }
    }

    fn particle(x: f32, y: f32, z: f32, radius: f32, density: f32) -> Particle {
        Particle {
            position: Vec3::new(x, y, z),
            radius,
            density,
        }
    }

    /// `n` particles in `[-1, 1]³`, radii 0.2–0.5, densities 0.2–1.5.
    fn random_particles(n: usize, seed: u64) -> Vec<Particle> {
        let mut rng = SplitMix64::mixed(seed);
        let mut u = |a: f64, b: f64| (a + (b - a) * rng.next_f64()) as f32;
        (0..n)
            .map(|_| particle(u(-1., 1.), u(-1., 1.), u(-1., 1.), u(0.2, 0.5), u(0.2, 1.5)))
            .collect()
    }

    fn scene(
        clouds: Vec<ResolvedCloud>,
        lights: Vec<LightSample>,
        background: Vec3,
        objects: Vec<SceneObject>,
        (width, height): (u32, u32),
    ) -> Scene {
        Scene {
            camera: SceneCamera {
                position: Vec3::new(0.0, 0.3, 5.0),
                look_at: Vec3::ZERO,
                up: Vec3::Y,
                vertical_fov_degrees: 40.0,
                width,
                height,
            },
            background,
            lights,
            clouds,
            objects,
            fog: None,
            shadow_map_resolution: crate::scene::DEFAULT_SHADOW_MAP_RESOLUTION,
            settings: CloudQualitySettings::default(),
        }
    }

    /// Brute-force coefficients: every particle of every cloud, no grid.
    fn brute_force(clouds: &[ResolvedCloud], x: DVec3) -> Coefficients {
        let mut c = Coefficients::default();
        for cl in clouds {
            for p in &cl.particles {
                let centre = p.position.as_dvec3() + cl.translation.as_dvec3();
                let r = p.radius as f64;
                let k = kernel_u2((x - centre).length_squared() / (r * r));
                let t = cl.medium.extinction as f64 * p.density as f64 * k;
                c.extinction += t;
                c.scattering += cl.medium.albedo as f64 * t;
            }
        }
        c
    }

    /// Composite Simpson rule with `n` (even) intervals.
    fn simpson(a: f64, b: f64, n: usize, f: impl Fn(f64) -> f64) -> f64 {
        let h = (b - a) / n as f64;
        let mut s = f(a) + f(b);
        for i in 1..n {
            s += f(a + i as f64 * h) * if i % 2 == 1 { 4.0 } else { 2.0 };
        }
        s * h / 3.0
    }

    /// Mean and standard error of the mean of samples of a vector quantity.
    fn mean_and_error(samples: &[DVec3]) -> (DVec3, DVec3) {
        let n = samples.len() as f64;
        let mean = samples.iter().copied().sum::<DVec3>() / n;
        let var = samples
            .iter()
            .map(|s| (*s - mean) * (*s - mean))
            .sum::<DVec3>()
            / (n - 1.0);
        (mean, (var / n).map(f64::sqrt))
    }

    /// Asserts `|mean - expected| <= sigmas * error + abs` per channel.
    fn assert_close(
        what: &str,
        (mean, error): (DVec3, DVec3),
        expected: DVec3,
        sigmas: f64,
        abs: f64,
    ) {
        let diff = (mean - expected).abs();
        let tol = error * sigmas + DVec3::splat(abs);
        println!("{what}: estimate {mean} ± {error}, expected {expected}");
        assert!(
            diff.cmple(tol).all(),
            "{what}: estimate {mean} ± {error}, expected {expected} (|diff| {diff} > tol {tol})"
        );
    }

    /// A test-only analytic medium: an axis-aligned box of constant coefficients whose majorant
    /// is `majorant_factor` times `σ_t`, so ratio and delta tracking see null collisions.
    struct HomogeneousBox {
        lo: DVec3,
        hi: DVec3,
        extinction: f64,
        albedo: f64,
        majorant_factor: f64,
    }

    impl Media for HomogeneousBox {
        fn visit_segments(
            &self,
            origin: DVec3,
            dir: DVec3,
            t_max: f64,
            mut visit: impl FnMut(Segment) -> ControlFlow<()>,
        ) -> ControlFlow<()> {
            match box_interval(self.lo, self.hi, origin, dir) {
                Some((t0, t1)) if t1.min(t_max) > t0 => visit(Segment {
                    t0,
                    t1: t1.min(t_max),
                    majorant: self.extinction * self.majorant_factor,
                    cell: 0,
                }),
                _ => ControlFlow::Continue(()),
            }
        }

        fn coefficients(&self, _: DVec3, _: &Segment) -> Coefficients {
            Coefficients {
                extinction: self.extinction,
                scattering: self.albedo * self.extinction,
            }
        }

        fn optical_depth(&self, origin: DVec3, dir: DVec3, t_max: f64) -> f64 {
            box_interval(self.lo, self.hi, origin, dir).map_or(0.0, |(t0, t1)| {
                self.extinction * (t1.min(t_max) - t0).max(0.0)
            })
        }
    }

    /// The grid gives exactly the brute-force coefficients (two overlapping, translated clouds
    /// with different albedos) and its majorant bounds `σ_t` everywhere.
    #[test]
    fn grid_coefficients_match_brute_force_and_stay_below_majorant() {
        let clouds = vec![
            cloud(Vec3::new(0.3, 0.0, 0.0), 4.0, 0.9, random_particles(50, 1)),
            cloud(Vec3::new(-0.2, 0.4, 0.1), 7.0, 0.3, random_particles(30, 2)),
        ];
        let media = ParticleMedia::new(&clouds);
        assert_eq!(media.particle_count(), 80);
        let mut rng = SplitMix64::mixed(3);
        for _ in 0..5000 {
            let x = DVec3::new(rng.next_f64(), rng.next_f64(), rng.next_f64()) * 3.4 - 1.7;
            let grid = media.coefficients_at(x);
            let brute = brute_force(&clouds, x);
            assert!(
                (grid.extinction - brute.extinction).abs() <= 1e-12 * (1.0 + brute.extinction),
                "at {x}: grid {grid:?}, brute force {brute:?}"
            );
            assert!((grid.scattering - brute.scattering).abs() <= 1e-12 * (1.0 + brute.scattering));
            assert!(
                brute.extinction <= media.majorant_at(x) * (1.0 + 1e-12),
                "majorant below σ_t at {x}"
            );
        }
    }

    /// The exact (polynomial) optical depth through the grid equals Simpson quadrature of the
    /// brute-force field, for rays starting inside and outside, with finite and infinite ends.
    #[test]
    fn exact_optical_depth_matches_quadrature() {
        let clouds = vec![
            cloud(Vec3::ZERO, 3.0, 0.8, random_particles(60, 4)),
            cloud(Vec3::new(0.5, -0.3, 0.2), 5.0, 0.5, random_particles(20, 5)),
        ];
        let media = ParticleMedia::new(&clouds);
        let mut rng = SplitMix64::mixed(6);
        for i in 0..40 {
            let origin = if i % 2 == 0 {
                DVec3::new(rng.next_f64(), rng.next_f64(), rng.next_f64()) * 2.0 - 1.0
            } else {
                rng.unit_sphere() * 4.0
            };
            let dir = if i % 2 == 0 {
                rng.unit_sphere()
            } else {
                (-origin + rng.unit_sphere()).normalize()
            };
            let t_max = if i % 4 < 2 {
                f64::INFINITY
            } else {
                1.0 + 3.0 * rng.next_f64()
            };
            let exact = media.optical_depth(origin, dir, t_max);
            let quad = simpson(0.0, t_max.min(8.0), 40_000, |t| {
                brute_force(&clouds, origin + dir * t).extinction
            });
            assert!(
                (exact - quad).abs() <= 1e-6 * (1.0 + quad),
                "ray {i}: exact {exact}, quadrature {quad}"
            );
        }
    }

    /// One particle, lines at several distances `b`: the exact optical depth equals
    /// `particle_optical_depth`, and ratio tracking and delta tracking reproduce `exp(-τ_i(b))`.
    #[test]
    fn single_particle_transmittance_matches_closed_form() {
        // Values as the f32 scene stores them, so the closed form sees the same numbers.
        let (k, eta, r) = (2.5, 1.3f32 as f64, 0.7f32 as f64);
        let centre = DVec3::new(0.3, -0.2, 0.1).as_vec3().as_dvec3();
        let clouds = vec![cloud(
            centre.as_vec3(),
            k as f32,
            0.5,
            vec![particle(0.0, 0.0, 0.0, r as f32, eta as f32)],
        )];
        let media = ParticleMedia::new(&clouds);
        let dir = DVec3::new(1.0, 2.0, -0.5).normalize();
        let side = dir.any_orthonormal_vector();
        let n = 20_000;
        for (j, b) in [0.0, 0.1, 0.35, 0.6, 0.69, 0.75].into_iter().enumerate() {
            let origin = centre + side * b - dir * 3.0;
            let expected_tau = particle_optical_depth(k, eta, r, b);
            let tau = media.optical_depth(origin, dir, f64::INFINITY);
            assert!(
                (tau - expected_tau).abs() <= 1e-12 * (1.0 + expected_tau),
                "b {b}: τ {tau} vs {expected_tau}"
            );
            let t = (-expected_tau).exp();
            let mut rng = SplitMix64::mixed(10 + j as u64);
            let ratio: Vec<DVec3> = (0..n)
                .map(|_| DVec3::splat(transmittance(&media, origin, dir, f64::INFINITY, &mut rng)))
                .collect();
            assert_close(
                "ratio tracking",
                mean_and_error(&ratio),
                DVec3::splat(t),
                4.0,
                1e-9,
            );
            let escaped = (0..n)
                .filter(|_| {
                    sample_free_flight(&media, origin, dir, f64::INFINITY, &mut rng).is_none()
                })
                .count();
            let binomial = (t * (1.0 - t) / n as f64).sqrt();
            let p = escaped as f64 / n as f64;
            assert!(
                (p - t).abs() <= 4.5 * binomial + 1e-9,
                "b {b}: delta tracking escapes {p}, expected {t}"
            );
        }
    }

    /// Distance fog on the camera ray: an object at distance D shows `V(D) L + A(D) F` exactly,
    /// the sky is not fogged, and an absorbing slab from t0 to t1 in front of the sky shows the
    /// fog between the camera and every depth of it: `F [1 - e^{-σL} - σ/(σ+k) e^{-k t0}
    /// (1 - e^{-(σ+k)L})] + e^{-σL} B` for exponential fog of density k (docs/physics.md, "Fog").
    #[test]
    fn distance_fog_fogs_the_camera_ray_up_to_its_first_collision() {
        use crate::fog::{Falloff, Fog};
        use crate::scene::ObjectShape;
        let k = 0.3;
        let fog = Fog {
            color: Vec3::new(0.6, 0.7, 0.8),
            alpha: 1.0,
            falloff: Falloff::Exponential { density: k as f32 },
            directional_light_color: Vec3::ZERO,
            directional_light_exponent: 8.0,
        };
        let f = fog.color.as_dvec3();
        let background = DVec3::new(0.1, 0.2, 0.4);
        let mut lighting = Lighting {
            background,
            lights: vec![],
            objects: vec![],
            fog: Some(fog),
        };
        let origin = DVec3::ZERO;
        let mut rng = SplitMix64::mixed(31);
        let empty = HomogeneousBox {
            lo: DVec3::splat(100.0),
            hi: DVec3::splat(101.0),
            extinction: 1.0,
            albedo: 0.0,
            majorant_factor: 1.0,
        };
        // The sky: unfogged.
        let sky = radiance(&empty, &lighting, origin, DVec3::Z, 8, &mut rng);
        assert_eq!(sky, background);
        // An unlit object 4 m away (its front face at z = 4).
        let colour = Vec3::new(1.0, 0.5, 0.25);
        lighting.objects = vec![SceneObject {
            shape: ObjectShape::Cuboid(Vec3::new(10.0, 10.0, 2.0)),
            translation: Vec3::new(0.0, 0.0, 5.0),
            color: colour,
            reflectance: Vec3::ZERO,
        }];
        let seen = radiance(&empty, &lighting, origin, DVec3::Z, 8, &mut rng);
        let v = (-k * 4.0f64).exp();
        let expected = colour.as_dvec3() * v + f * (1.0 - v);
        assert!((seen - expected).length() < 1e-6, "{seen} vs {expected}");
        // An absorber from 2 to 3.5 m, the sky behind.
        lighting.objects.clear();
        let (sigma, t0, length) = (1.2, 2.0, 1.5);
        let slab = HomogeneousBox {
            lo: DVec3::new(-50.0, -50.0, t0),
            hi: DVec3::new(50.0, 50.0, t0 + length),
            extinction: sigma,
            albedo: 0.0,
            majorant_factor: 2.0,
        };
        let samples: Vec<DVec3> = (0..40_000)
            .map(|_| radiance(&slab, &lighting, origin, DVec3::Z, 8, &mut rng))
            .collect();
        let t = (-sigma * length).exp();
        let fogged =
            1.0 - t - sigma / (sigma + k) * (-k * t0).exp() * (1.0 - (-(sigma + k) * length).exp());
        assert_close(
            "fogged absorber",
            mean_and_error(&samples),
            f * fogged + background * t,
            4.5,
            1e-9,
        );
    }

    /// Beer–Lambert through a homogeneous slab (analytic test medium with a loose majorant):
    /// ratio tracking, the escape probability of delta tracking and the mean collision distance.
    #[test]
    fn homogeneous_slab_follows_beer_lambert() {
        let sigma = 1.7;
        let slab = HomogeneousBox {
            lo: DVec3::new(-50.0, -50.0, 0.0),
            hi: DVec3::new(50.0, 50.0, 1.0),
            extinction: sigma,
            albedo: 0.5,
            majorant_factor: 2.5,
        };
        let mut rng = SplitMix64::mixed(20);
        let n = 40_000;
        // Transmittances 0.18, 0.15 and 0.004 (deep into ratio tracking's roulette).
        for dir in [
            DVec3::Z,
            DVec3::new(0.5, 0.2, 1.0).normalize(),
            DVec3::new(3.0, 0.0, 1.0).normalize(),
        ] {
            let origin = DVec3::new(0.0, 0.0, -1.0);
            let length = 1.0 / dir.z;
            let t = (-sigma * length).exp();
            let ratio: Vec<DVec3> = (0..n)
                .map(|_| DVec3::splat(transmittance(&slab, origin, dir, f64::INFINITY, &mut rng)))
                .collect();
            assert_close(
                "slab ratio tracking",
                mean_and_error(&ratio),
                DVec3::splat(t),
                4.0,
                1e-9,
            );
            // Delta tracking: P(escape) = T, and E[(t - t_entry) · 1{collision}] = (1 - T(1 + σL)) / σ.
            let flights: Vec<Option<f64>> = (0..n)
                .map(|_| {
                    sample_free_flight(&slab, origin, dir, f64::INFINITY, &mut rng).map(|(t, _)| t)
                })
                .collect();
            let escapes: Vec<DVec3> = flights
                .iter()
                .map(|f| DVec3::splat(f.is_none() as u8 as f64))
                .collect();
            assert_close(
                "slab escape",
                mean_and_error(&escapes),
                DVec3::splat(t),
                4.5,
                1e-9,
            );
            let depth: Vec<DVec3> = flights
                .iter()
                .map(|f| DVec3::splat(f.map_or(0.0, |t| t - 1.0 / dir.z)))
                .collect();
            let expected = (1.0 - t * (1.0 + sigma * length)) / sigma;
            assert_close(
                "slab collision depth",
                mean_and_error(&depth),
                DVec3::splat(expected),
                4.5,
                1e-9,
            );
        }
    }

    /// Single scattering (paths cut after one event) of one large particle, against nested
    /// Simpson quadrature of `B T(0,∞) + ∫ T(0,t) σ_s E p(cos θ) T_light dt` with the exact
    /// kernel, isotropic and Henyey–Greenstein forward and backward.
    #[test]
    fn single_scattering_matches_quadrature() {
        for g in [0.0, 0.7, -0.4] {
            single_scattering_matches_quadrature_for(g);
        }
    }

    fn single_scattering_matches_quadrature_for(g: f64) {
        let (k, eta, r, omega) = (1.2f32 as f64, 1.0, 1.0, 0.8f32 as f64);
        let centre = DVec3::new(0.1, 0.0, -0.2).as_vec3().as_dvec3();
        let mut clouds = vec![cloud(
            centre.as_vec3(),
            k as f32,
            omega as f32,
            vec![particle(0.0, 0.0, 0.0, r as f32, eta as f32)],
        )];
        clouds[0].medium.anisotropy = g as f32;
        let media = ParticleMedia::new(&clouds);
        let light = LightSample {
            direction: Vec3::new(-0.3, -1.0, -0.2),
            irradiance: Vec3::new(1.0, 0.5, 0.25),
        };
        let background = Vec3::new(0.1, 0.2, 0.3);
        let s = scene(clouds.clone(), vec![light], background, vec![], (1, 1));
        let lighting = Lighting::from_scene(&s);
        let to_light = lighting.lights[0].to_light;
        let sigma_t = |x: DVec3| k * eta * kernel_u2((x - centre).length_squared() / (r * r));
        // Optical depth along a ray up to distance `len` (the particle is left after 2r).
        let tau = |o: DVec3, d: DVec3, len: f64| simpson(0.0, len, 400, |t| sigma_t(o + d * t));
        let eye = DVec3::new(0.0, 0.0, 5.0);
        for (j, target) in [
            DVec3::new(0.1, 0.0, -0.2),
            DVec3::new(0.4, 0.3, -0.2),
            DVec3::new(-0.6, 0.5, -0.2),
        ]
        .into_iter()
        .enumerate()
        {
            let dir = (target - eye).normalize();
            // Chord of the ray through the particle.
            let t_c = (centre - eye).dot(dir);
            let b2 = (centre - eye).cross(dir).length_squared();
            let half = (r * r - b2).sqrt();
            let (ta, tb) = (t_c - half, t_c + half);
            let scattered = simpson(ta, tb, 2000, |t| {
                let x = eye + dir * t;
                let t_cam = (-tau(eye + dir * ta, dir, t - ta)).exp();
                let t_light = (-tau(x, to_light, 2.0 * r)).exp();
                t_cam * omega * sigma_t(x) * henyey_greenstein(g, to_light.dot(dir)) * t_light
            });
            let t_total = (-particle_optical_depth(k, eta, r, b2.sqrt())).exp();
            let expected =
                background.as_dvec3() * t_total + lighting.lights[0].irradiance * scattered;
            let mut rng = SplitMix64::mixed(30 + j as u64);
            let samples: Vec<DVec3> = (0..40_000)
                .map(|_| radiance(&media, &lighting, eye, dir, 1, &mut rng))
                .collect();
            assert_close(
                &format!("single scattering, g {g}"),
                mean_and_error(&samples),
                expected,
                4.5,
                1e-6,
            );
        }
    }

    /// Albedo 0: no light is scattered, whatever the lights; the camera sees `B exp(-τ)` with τ
    /// the sum of the particles' closed-form optical depths.
    #[test]
    fn absorbing_cloud_shows_attenuated_background() {
        let particles = random_particles(30, 40);
        let (k, translation) = (2.0, Vec3::new(0.0, 0.2, 0.0));
        let clouds = vec![cloud(translation, k as f32, 0.0, particles.clone())];
        let light = LightSample {
            direction: Vec3::new(0.0, -1.0, 0.3),
            irradiance: Vec3::splat(5.0),
        };
        let background = Vec3::new(1.0, 0.5, 0.25);
        let s = scene(clouds, vec![light], background, vec![], (1, 1));
        let media = ParticleMedia::from_scene(&s);
        let lighting = Lighting::from_scene(&s);
        let eye = DVec3::new(0.0, 0.3, 6.0);
        let mut rng = SplitMix64::mixed(41);
        let n = 20_000;
        for j in 0..5 {
            let target = DVec3::new(rng.next_f64() - 0.5, rng.next_f64() - 0.5, 0.0);
            let dir = (target - eye).normalize();
            let tau: f64 = particles
                .iter()
                .map(|p| {
                    let v = p.position.as_dvec3() + translation.as_dvec3() - eye;
                    let b = v.cross(dir).length();
                    particle_optical_depth(k, p.density as f64, p.radius as f64, b)
                })
                .sum();
            let t = (-tau).exp();
            let samples: Vec<DVec3> = (0..n)
                .map(|_| radiance(&media, &lighting, eye, dir, MAX_SCATTER_EVENTS, &mut rng))
                .collect();
            // Each sample is B or 0: binomial error.
            let error = background.as_dvec3() * (t * (1.0 - t) / n as f64).sqrt();
            let mean = mean_and_error(&samples).0;
            assert_close(
                &format!("absorbing ray {j}"),
                (mean, error),
                background.as_dvec3() * t,
                4.5,
                1e-9,
            );
        }
    }

    /// Furnace: albedo 1, no lights, uniform background `B`: scattering only redistributes the
    /// background, so the cloud is invisible and every pixel is exactly `B` (each path ends by
    /// escaping with weight 1). With albedo < 1 the cloud must darken the image.
    #[test]
    fn furnace_albedo_one_is_invisible() {
        let background = Vec3::new(0.2, 0.5, 1.0);
        let clouds = vec![
            cloud(Vec3::ZERO, 20.0, 1.0, random_particles(60, 50)),
            cloud(Vec3::new(0.4, 0.2, 0.0), 8.0, 1.0, random_particles(20, 51)),
        ];
        let s = scene(clouds, vec![], background, vec![], (16, 12));
        let settings = PathTracerSettings {
            samples_per_pixel: 4,
            seed: 1,
            progress: None,
        };
        let image = render(&s, &settings);
        for px in &image {
            for c in 0..3 {
                assert!(
                    (px[c] - background[c]).abs() <= 1e-6 * background[c],
                    "pixel {px:?}"
                );
            }
            assert_eq!(px[3], 1.0);
        }
        let mut grey = s.clone();
        grey.clouds.iter_mut().for_each(|c| c.medium.albedo = 0.7);
        let image = render(&grey, &settings);
        let centre = image[6 * 16 + 8];
        assert!(
            centre[2] < 0.9 * background.z,
            "albedo 0.7 cloud not darker: {centre:?}"
        );
    }

    /// A uniform environment `B` equals directional lights from all directions: `N` lights in a
    /// uniformly random rotation of a spherical Fibonacci set, `E = 4π B / N` each, estimate the
    /// environment's unscattered irradiance without bias. Along a ray, the lights version (black
    /// background) must then give the environment version minus the directly transmitted
    /// `B T(0,∞)`. This checks next-event estimation (the phase function, exact `T_l`) against
    /// the multiple-scattering continuation (directions sampled from the phase function) and
    /// escapes, at all orders (albedo 0.9, τ up to ~2): isotropic, and a mixture of a forward and
    /// a backward Henyey–Greenstein cloud in the same place.
    #[test]
    fn environment_equals_many_lights() {
        let ball = |g: f32, density: f32| {
            let mut c = cloud(
                Vec3::ZERO,
                2.0,
                0.9,
                vec![particle(0.0, 0.0, 0.0, 1.0, density)],
            );
            c.medium.anisotropy = g;
            c
        };
        assert_environment_equals_many_lights(vec![ball(0.0, 1.0)], 60);
        assert_environment_equals_many_lights(vec![ball(0.7, 0.5), ball(-0.4, 0.5)], 70);
    }

    fn assert_environment_equals_many_lights(clouds: Vec<ResolvedCloud>, seed: u64) {
        let background = DVec3::new(1.0, 0.6, 0.3);
        let env = scene(clouds, vec![], background.as_vec3(), vec![], (1, 1));
        let media = ParticleMedia::from_scene(&env);
        let env_lighting = Lighting::from_scene(&env);
        let n_lights = 8;
        let golden = std::f64::consts::PI * (3.0 - 5.0f64.sqrt());
        let fibonacci: Vec<DVec3> = (0..n_lights)
            .map(|i| {
                let z = 1.0 - (2.0 * i as f64 + 1.0) / n_lights as f64;
                let s = (1.0 - z * z).sqrt();
                DVec3::new(
                    s * (golden * i as f64).cos(),
                    s * (golden * i as f64).sin(),
                    z,
                )
            })
            .collect();
        // Uniformly random rotation (Shoemake's unit quaternion).
        let random_lights = |rng: &mut SplitMix64| {
            let (u1, u2, u3) = (rng.next_f64(), rng.next_f64(), rng.next_f64());
            let tau = std::f64::consts::TAU;
            let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
            let q = bevy::math::DQuat::from_xyzw(
                a * (tau * u2).sin(),
                a * (tau * u2).cos(),
                b * (tau * u3).sin(),
                b * (tau * u3).cos(),
            );
            let lights = fibonacci
                .iter()
                .map(|d| DirectionalLight {
                    to_light: q * *d,
                    irradiance: background * (4.0 * std::f64::consts::PI / n_lights as f64),
                })
                .collect();
            Lighting {
                background: DVec3::ZERO,
                lights,
                objects: vec![],
                fog: None,
            }
        };
        let eye = DVec3::new(0.0, 0.0, 4.0);
        let n = 100_000;
        for (j, b) in [0.0, 0.5, 0.85].into_iter().enumerate() {
            let dir = (DVec3::new(b, 0.0, 0.0) - eye).normalize();
            let t_direct = (-media.optical_depth(eye, dir, f64::INFINITY)).exp();
            let mut rng = SplitMix64::mixed(seed + j as u64);
            let env_samples: Vec<DVec3> = (0..n)
                .map(|_| {
                    radiance(
                        &media,
                        &env_lighting,
                        eye,
                        dir,
                        MAX_SCATTER_EVENTS,
                        &mut rng,
                    ) - background * t_direct
                })
                .collect();
            let lit_samples: Vec<DVec3> = (0..n)
                .map(|_| {
                    let lighting = random_lights(&mut rng);
                    radiance(&media, &lighting, eye, dir, MAX_SCATTER_EVENTS, &mut rng)
                })
                .collect();
            let (env_mean, env_err) = mean_and_error(&env_samples);
            let (lit_mean, lit_err) = mean_and_error(&lit_samples);
            let err = (env_err * env_err + lit_err * lit_err).map(f64::sqrt);
            assert_close(
                "lights vs environment",
                (lit_mean, err),
                env_mean,
                4.5,
                1e-9,
            );
        }
    }

    /// Objects end camera rays with their own radiance, hide the background (attenuated by the
    /// medium in front) and block shadow rays completely.
    #[test]
    fn objects_block_camera_and_shadow_rays() {
        let particles = vec![particle(0.0, 0.0, 0.0, 1.0, 1.0)];
        let light = LightSample {
            direction: Vec3::new(0.0, -1.0, 0.0),
            irradiance: Vec3::ONE,
        };
        let eye = DVec3::new(0.0, 0.0, 5.0);
        let dir = -DVec3::Z;
        // A big sphere above the cloud shadows it completely; background and object are black.
        let shade = SceneObject {
            shape: ObjectShape::Sphere(3.0),
            translation: Vec3::new(0.0, 10.0, 0.0),
            color: Vec3::ZERO,
            reflectance: Vec3::ZERO,
        };
        let clouds = vec![cloud(Vec3::ZERO, 3.0, 0.9, particles.clone())];
        let shaded = scene(clouds.clone(), vec![light], Vec3::ZERO, vec![shade], (1, 1));
        let open = scene(clouds, vec![light], Vec3::ZERO, vec![], (1, 1));
        let media = ParticleMedia::from_scene(&open);
        let mut rng = SplitMix64::mixed(70);
        let lighting = Lighting::from_scene(&shaded);
        let total: DVec3 = (0..2000)
            .map(|_| radiance(&media, &lighting, eye, dir, MAX_SCATTER_EVENTS, &mut rng))
            .sum();
        assert_eq!(total, DVec3::ZERO, "shadowed cloud received light");
        let lighting = Lighting::from_scene(&open);
        let total: DVec3 = (0..2000)
            .map(|_| radiance(&media, &lighting, eye, dir, MAX_SCATTER_EVENTS, &mut rng))
            .sum();
        assert!(total.x > 0.0, "lit cloud is black");
        // An object behind an absorbing cloud: its colour times the transmittance; beside the
        // cloud: exactly its colour.
        let color = Vec3::new(0.2, 0.4, 0.8);
        let wall = SceneObject {
            shape: ObjectShape::Cuboid(Vec3::new(10.0, 10.0, 0.2)),
            translation: Vec3::new(0.0, 0.0, -3.0),
            color,
            reflectance: Vec3::ZERO,
        };
        let absorbing = vec![cloud(Vec3::ZERO, 1.5, 0.0, particles)];
        let s = scene(absorbing, vec![light], Vec3::ONE, vec![wall], (1, 1));
        let (media, lighting) = (ParticleMedia::from_scene(&s), Lighting::from_scene(&s));
        let beside = radiance(
            &media,
            &lighting,
            eye,
            (DVec3::new(2.0, 0.0, -3.0) - eye).normalize(),
            MAX_SCATTER_EVENTS,
            &mut rng,
        );
        assert_eq!(beside, color.as_dvec3());
        let n = 20_000;
        let t = (-particle_optical_depth(1.5, 1.0, 1.0, 0.0)).exp();
        let samples: Vec<DVec3> = (0..n)
            .map(|_| radiance(&media, &lighting, eye, dir, MAX_SCATTER_EVENTS, &mut rng))
            .collect();
        let error = color.as_dvec3() * (t * (1.0 - t) / n as f64).sqrt();
        assert_close(
            "object behind cloud",
            (mean_and_error(&samples).0, error),
            color.as_dvec3() * t,
            4.5,
            1e-9,
        );
    }

    fn test_scene(size: (u32, u32)) -> Scene {
        let clouds = vec![cloud(Vec3::ZERO, 6.0, 0.95, random_particles(100, 80))];
        let light = LightSample {
            direction: Vec3::new(-0.5, -0.8, -0.35),
            irradiance: Vec3::new(1.0, 0.97, 0.9),
        };
        scene(
            clouds,
            vec![light],
            Vec3::new(0.05, 0.07, 0.1),
            vec![],
            size,
        )
    }

    /// Same seed → bit-identical image, whatever the thread count; another seed → another image.
    #[test]
    fn deterministic_for_seed_and_thread_count() {
        let s = test_scene((12, 9));
        let settings = PathTracerSettings {
            samples_per_pixel: 4,
            seed: 7,
            progress: None,
        };
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let one = pool(1).install(|| render(&s, &settings));
        let three = pool(3).install(|| render(&s, &settings));
        assert_eq!(one, three);
        assert_eq!(one, render(&s, &settings));
        let other = render(
            &s,
            &PathTracerSettings {
                seed: 8,
                ..settings
            },
        );
        assert_ne!(one, other);
        assert!(
            one.iter()
                .all(|p| p.iter().all(|c| c.is_finite() && *c >= 0.0))
        );
    }

    /// The noise level of two independent renders is finite, positive and falls like `1/√spp`.
    #[test]
    fn noise_level_is_finite_and_falls_with_samples() {
        let s = test_scene((32, 24));
        let mut levels = Vec::new();
        for spp in [16, 64] {
            let start = std::time::Instant::now();
            let a = render(
                &s,
                &PathTracerSettings {
                    samples_per_pixel: spp,
                    seed: 1,
                    progress: None,
                },
            );
            let elapsed = start.elapsed();
            let b = render(
                &s,
                &PathTracerSettings {
                    samples_per_pixel: spp,
                    seed: 2,
                    progress: None,
                },
            );
            let noise = noise_level(&a, &b);
            println!(
                "32x24, 100 particles, {spp} spp: noise level {noise:.4}, {elapsed:.2?} per render"
            );
            assert!(noise.is_finite() && noise > 0.0);
            levels.push(noise);
        }
        let ratio = levels[1] / levels[0];
        assert!(
            (0.35..0.7).contains(&ratio),
            "noise ratio 64/16 spp = {ratio}, expected ≈ 0.5"
        );
    }

    /// The top face of a ground box (reflectance (0.2, 0.5, 0.8), colour (0.01, 0.02, 0.03)) at
    /// the point (0.3, 0, 0.1), under `lights`, clouds and a background: its radiance, the mean
    /// of `samples` paths.
    fn ground_radiance(
        clouds: Vec<ResolvedCloud>,
        lights: Vec<LightSample>,
        background: Vec3,
        samples: usize,
    ) -> DVec3 {
        let ground = SceneObject {
            shape: ObjectShape::Cuboid(Vec3::new(40.0, 1.0, 40.0)),
            translation: Vec3::new(0.0, -0.5, 0.0),
            color: Vec3::new(0.01, 0.02, 0.03),
            reflectance: Vec3::new(0.2, 0.5, 0.8),
        };
        let s = scene(clouds, lights, background, vec![ground], (1, 1));
        let (media, lighting) = (ParticleMedia::from_scene(&s), Lighting::from_scene(&s));
        let mut rng = SplitMix64::mixed(81);
        // Obliquely, clear of the particles the tests put above the point.
        let (eye, target) = (DVec3::new(4.3, 0.5, 0.1), DVec3::new(0.3, 0.0, 0.1));
        let dir = (target - eye).normalize();
        let sum: DVec3 = (0..samples)
            .map(|_| radiance(&media, &lighting, eye, dir, MAX_SCATTER_EVENTS, &mut rng))
            .sum();
        sum / samples as f64
    }

    #[test]
    fn a_lit_object_reflects_its_lights_and_the_sky_as_a_lambertian_surface() {
        let color = DVec3::new(0.01, 0.02, 0.03);
        let r = DVec3::new(0.2, 0.5, 0.8);
        // A light 60° from the normal, and one below the surface (it lights nothing); no clouds
        // and nothing above the ground, so the sky's estimate has no variance.
        let lights = vec![
            LightSample {
                direction: Vec3::new(3f32.sqrt(), -1.0, 0.0),
                irradiance: Vec3::new(2.0, 1.0, 4.0),
            },
            LightSample {
                direction: Vec3::Y,
                irradiance: Vec3::splat(9.0),
            },
        ];
        let sky = Vec3::new(0.1, 0.2, 0.3);
        let got = ground_radiance(vec![], lights, sky, 64);
        let e = DVec3::new(2.0, 1.0, 4.0) * 0.5 + sky.as_dvec3() * std::f64::consts::PI;
        let expected = color + r * e / std::f64::consts::PI;
        // Exact but for the scene's f32 inputs.
        assert!(
            (got - expected).abs().max_element() < 1e-7,
            "{got} vs {expected}"
        );
    }

    #[test]
    fn a_cloud_between_a_lit_object_and_its_light_shadows_it_by_its_transmittance() {
        // One particle straight above the point seen, the light straight down: the shadow ray
        // runs through the particle's centre, tau = K eta r 16/15.
        let (k, eta, radius) = (1.5f32, 0.8f32, 0.5f32);
        let above = cloud(
            Vec3::new(0.3, 1.0, 0.1),
            k,
            0.0,
            vec![particle(0.0, 0.0, 0.0, radius, eta)],
        );
        let light = LightSample {
            direction: Vec3::NEG_Y,
            irradiance: Vec3::ONE,
        };
        // The camera ray passes the particle too (it sees the ground through it): look at the
        // ground point from beside it instead, through clear air.
        let ground = SceneObject {
            shape: ObjectShape::Cuboid(Vec3::new(40.0, 1.0, 40.0)),
            translation: Vec3::new(0.0, -0.5, 0.0),
            color: Vec3::ZERO,
            reflectance: Vec3::ONE,
        };
        let s = scene(vec![above], vec![light], Vec3::ZERO, vec![ground], (1, 1));
        let (media, lighting) = (ParticleMedia::from_scene(&s), Lighting::from_scene(&s));
        let target = DVec3::new(0.3, 0.0, 0.1);
        let eye = DVec3::new(3.3, 1.0, 0.1);
        let dir = (target - eye).normalize();
        let mut rng = SplitMix64::mixed(82);
        let got = radiance(&media, &lighting, eye, dir, MAX_SCATTER_EVENTS, &mut rng);
        let tau = (k * eta * radius) as f64 * 16.0 / 15.0;
        let expected = (-tau).exp() / std::f64::consts::PI;
        assert!((got.x - expected).abs() < 1e-7, "{} vs {expected}", got.x);
        // Under a sky alone, a thick particle above darkens the ground by the cosine-weighted
        // mean transmittance of the sky's directions: against a midpoint quadrature of that mean.
        let thick = || {
            vec![cloud(
                Vec3::new(0.3, 1.0, 0.1),
                4.0,
                0.0,
                vec![particle(0.0, 0.0, 0.0, 0.9, 1.0)],
            )]
        };
        let samples = 20_000;
        let got = ground_radiance(thick(), vec![], Vec3::ONE, samples);
        let s = scene(thick(), vec![], Vec3::ONE, vec![], (1, 1));
        let media = ParticleMedia::from_scene(&s);
        let n = 200;
        let visible: f64 = (0..n * n)
            .map(|i| {
                let u = [(i % n) as f64, (i / n) as f64].map(|c| (c + 0.5) / n as f64);
                let d = cosine_direction_of(DVec3::Y, u);
                (-media.optical_depth(target, d, f64::INFINITY)).exp()
            })
            .sum::<f64>()
            / (n * n) as f64;
        // Radiance = colour + R * (mean transmittance); its standard error is at most R / 2 /
        // sqrt(samples) (T lies in [0, 1]).
        let expected = 0.01 + 0.2 * visible;
        let error = 4.0 * 0.2 * 0.5 / (samples as f64).sqrt();
        assert!(
            visible < 0.7,
            "the particle hides much of the sky: {visible}"
        );
        assert!(
            (got.x - expected).abs() < error,
            "{} vs {expected} ± {error}",
            got.x
        );
    }
}
