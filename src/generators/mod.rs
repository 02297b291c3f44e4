//! Particle generators for common shapes. Deterministic for a given seed.
//!
//! Every generator returns [`Particles`] in cloud-local metres with density 1 unless stated
//! otherwise; the same arguments and seed always give the same particles, on any thread count.
//!
//! | generator | shape |
//! |---|---|
//! | [`sphere`], [`cuboid`] | a ball, a box |
//! | [`cumulus`] | a flat-bottomed heap of puffs |
//! | [`cloudscape`] | a sky of cumulus on a jittered grid |
//! | [`from_sdf`] | the inside of any signed-distance function, e.g. [`bunny_sdf`] |
//! | [`from_mesh_volume`] | the inside of a closed triangle [`Mesh`] |

use bevy::{
    math::{Quat, Vec2, Vec3},
    mesh::{Mesh, MeshTrianglesError},
};
#[cfg(feature = "parallel")]
use rayon::prelude::*;

pub use crate::math::SplitMix64;
use crate::{Medium, Particles, particle::Particle};

/// `count` particles of radius `particle_radius` filling a ball of radius `radius` (metres),
/// density 1.
pub fn sphere(radius: f32, particle_radius: f32, count: usize, seed: u64) -> Particles {
    let mut rng = SplitMix64::new(seed);
    let inner = (radius - particle_radius).max(0.0);
    Particles::new(
        (0..count)
            .map(|_| Particle {
                position: rng.in_unit_ball() * inner,
                radius: particle_radius,
                density: 1.0,
            })
            .collect(),
    )
}

/// `count` particles filling an axis-aligned box of full `extents` (metres), density 1.
pub fn cuboid(extents: Vec3, particle_radius: f32, count: usize, seed: u64) -> Particles {
    let mut rng = SplitMix64::new(seed);
    let half = (extents * 0.5 - particle_radius).max(Vec3::ZERO);
    Particles::new(
        (0..count)
            .map(|_| {
                let u = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0 - 1.0;
                Particle {
                    position: u * half,
                    radius: particle_radius,
                    density: 1.0,
                }
            })
            .collect(),
    )
}

/// A cumulus: a flat-bottomed heap of overlapping puffs, about `size` metres across, made of
/// `count` particles. Puffs are larger and denser at the core and thin out towards the edges.
pub fn cumulus(size: f32, count: usize, seed: u64) -> Particles {
    cumulus_with_puffs(size, count, seed, |size, core| size * (0.07 + 0.06 * core))
}

/// One cloud of a [`cloudscape`].
#[derive(Clone, Debug)]
pub struct PlacedCloud {
    /// World position of the cloud's local origin, metres.
    pub translation: Vec3,
    /// Its medium: extinction `20 / size` per metre, so that every cloud has the same optical
    /// thickness whatever its size.
    pub medium: Medium,
    /// Its particles, in cloud-local metres.
    pub particles: Particles,
}

/// A sky of `clouds` cumulus of `particles / clouds` particles each (at least 1), 25–60 m across,
/// their bases at 70–110 m, on a jittered grid 80 m apart centred on the origin, each turned
/// about the vertical by a random angle (baked into its particles). The `cloudscape` example's
/// and the benchmark's sky.
pub fn cloudscape(clouds: u32, particles: u32, seed: u64) -> Vec<PlacedCloud> {
    let side = (clouds as f32).sqrt().ceil() as u32;
    let per_cloud = (particles / clouds.max(1)).max(1) as usize;
    let mut rng = SplitMix64::new(seed);
    (0..clouds)
        .map(|i| {
            let size = 25.0 + 35.0 * rng.next_f32();
            let cell = Vec2::new((i % side) as f32, (i / side) as f32) - (side as f32 - 1.0) / 2.0;
            let jitter = Vec2::new(rng.next_f32(), rng.next_f32()) - 0.5;
            let at = (cell + 0.6 * jitter) * 80.0;
            let base = 70.0 + 40.0 * rng.next_f32();
            let turn = Quat::from_rotation_y(rng.next_f32() * std::f32::consts::TAU);
            let mut cloud = cumulus(size, per_cloud, 1000 + i as u64);
            for p in &mut cloud.particles {
                p.position = turn * p.position;
            }
            PlacedCloud {
                translation: Vec3::new(at.x, base, at.y),
                medium: Medium {
                    extinction: 20.0 / size,
                    albedo: 0.99,
                    ..Default::default()
                },
                particles: cloud,
            }
        })
        .collect()
}

/// [`cumulus`] with the puffs' radius (metres) given by `radius(size, core)`, `core` in `[0, 1]`
/// growing towards the centre of the puff's lobe.
pub fn cumulus_with_puffs(
    size: f32,
    count: usize,
    seed: u64,
    radius: impl Fn(f32, f32) -> f32,
) -> Particles {
    let mut rng = SplitMix64::new(seed);
    // A few large lobes give the cauliflower silhouette; particles cluster around them.
    let lobes: Vec<(Vec3, f32)> = (0..7)
        .map(|i| {
            let a = i as f32 / 7.0 * std::f32::consts::TAU + rng.next_f32();
            let r = if i == 0 {
                0.0
            } else {
                0.28 + 0.12 * rng.next_f32()
            };
            let centre = Vec3::new(a.cos() * r, 0.1 + 0.25 * rng.next_f32(), a.sin() * r * 0.7);
            (centre * size, size * (0.22 + 0.12 * rng.next_f32()))
        })
        .collect();
    let particles = (0..count)
        .map(|i| {
            let (centre, lobe_radius) = lobes[i % lobes.len()];
            let mut p = centre + rng.in_unit_ball() * lobe_radius;
            p.y = p.y.max(-0.05 * size); // flat base, as condensation starts at one altitude
            let core = 1.0 - ((p - centre).length() / lobe_radius).min(1.0);
            Particle {
                position: p,
                radius: radius(size, core),
                density: 0.5 + 0.5 * core,
            }
        })
        .collect();
    Particles::new(particles)
}

/// Particles generated per independently seeded chunk by the rejection samplers: the result does
/// not depend on whether (feature `parallel`) or how many threads rayon uses.
const CHUNK: usize = 4096;

/// Candidates tried per requested particle before a rejection sampler gives up (a shape filling
/// less than about 0.1 % of its box).
const TRIES_PER_PARTICLE: usize = 1000;

/// `count` uniformly distributed particles whose centres satisfy `inside`, drawn from the box
/// `[lo, hi]`. Fewer only when the shape is (nearly) empty.
fn rejection_sample(
    inside: impl Fn(Vec3) -> bool + Sync,
    bounds_min: Vec3,
    bounds_max: Vec3,
    particle_radius: f32,
    count: usize,
    seed: u64,
) -> Particles {
    assert!(
        bounds_min.is_finite() && bounds_max.is_finite(),
        "generator bounds must be finite (got {bounds_min} .. {bounds_max})"
    );
    let (lo, hi) = (bounds_min.min(bounds_max), bounds_min.max(bounds_max));
    let chunks = count.div_ceil(CHUNK);
    #[cfg(feature = "parallel")]
    let chunks = (0..chunks).into_par_iter();
    #[cfg(not(feature = "parallel"))]
    let chunks = 0..chunks;
    let particles: Vec<Vec<Particle>> = chunks
        .map(|chunk| {
            let n = CHUNK.min(count - chunk * CHUNK);
            let mut rng =
                SplitMix64::new(seed ^ (chunk as u64 + 1).wrapping_mul(0xD1B5_4A32_D192_ED03));
            let mut out = Vec::with_capacity(n);
            let mut tries = 0;
            while out.len() < n && tries < n * TRIES_PER_PARTICLE {
                tries += 1;
                let u = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
                let p = lo + (hi - lo) * u;
                if inside(p) {
                    out.push(Particle {
                        position: p,
                        radius: particle_radius,
                        density: 1.0,
                    });
                }
            }
            out
        })
        .collect();
    Particles::new(particles.into_iter().flatten().collect())
}

/// `count` particles of radius `particle_radius` (metres) and density 1 whose centres are
/// uniformly distributed over the inside (`sdf(p) < 0`) of a signed-distance function, within the
/// box `bounds_min..bounds_max` (metres; the box must contain the shape, or the shape is clipped).
///
/// Rejection sampling, in parallel with the `parallel` feature: the cost is about `count` × box volume / shape volume
/// evaluations of `sdf`. Only the sign of `sdf` matters, so a bound (such as the usual ellipsoid
/// approximation) works as well as an exact distance. Returns fewer than `count` particles only
/// when the shape fills less than about 0.1 % of the box (an empty shape gives none).
/// Deterministic for a given `seed`.
///
/// ```
/// use bevy::math::Vec3;
/// use bevy_particle_clouds::generators;
/// // A torus of major radius 1 m and minor radius 0.3 m.
/// let torus = |p: Vec3| (Vec3::new(p.x, 0.0, p.z).length() - 1.0).hypot(p.y) - 0.3;
/// let particles = generators::from_sdf(torus, Vec3::splat(-1.3), Vec3::splat(1.3), 0.08, 500, 1);
/// assert_eq!(particles.particles.len(), 500);
/// ```
pub fn from_sdf(
    sdf: impl Fn(Vec3) -> f32 + Sync,
    bounds_min: Vec3,
    bounds_max: Vec3,
    particle_radius: f32,
    count: usize,
    seed: u64,
) -> Particles {
    rejection_sample(
        |p| sdf(p) < 0.0,
        bounds_min,
        bounds_max,
        particle_radius,
        count,
        seed,
    )
}

/// `count` particles of radius `particle_radius` (metres) and density 1 whose centres are
/// uniformly distributed inside a closed triangle mesh (positions in metres; `TriangleList` or
/// `TriangleStrip`, indexed, `Float32x3` positions — every Bevy primitive mesh qualifies).
///
/// A point is inside when rays from it cross the surface an odd number of times (the majority
/// of three rays in different directions, so a ray grazing an edge does not misclassify it).
/// Each candidate tests every triangle: meant for meshes of up to a few thousand triangles.
/// Returns fewer than `count` particles only when the mesh encloses (almost) no volume.
/// Deterministic for a given `seed`.
///
/// # Errors
/// The mesh's error when it has no usable triangles (see [`Mesh::triangles`]).
pub fn from_mesh_volume(
    mesh: &Mesh,
    particle_radius: f32,
    count: usize,
    seed: u64,
) -> Result<Particles, MeshTrianglesError> {
    let triangles: Vec<[Vec3; 3]> = mesh.triangles()?.map(|t| t.vertices).collect();
    let Some((lo, hi)) = triangles
        .iter()
        .flatten()
        .map(|&v| (v, v))
        .reduce(|(lo, hi), (a, b)| (lo.min(a), hi.max(b)))
    else {
        return Ok(Particles::default());
    };
    // Generic directions: no axis-aligned face or edge of a primitive mesh lies along them.
    let rays = [
        Vec3::new(0.8727, 0.3571, 0.3331).normalize(),
        Vec3::new(-0.2913, 0.9123, -0.2879).normalize(),
        Vec3::new(0.1931, -0.4127, 0.8903).normalize(),
    ];
    let inside = |p: Vec3| {
        let odd = rays
            .iter()
            .filter(|&&d| {
                triangles
                    .iter()
                    .filter(|t| ray_hits_triangle(p, d, t))
                    .count()
                    % 2
                    == 1
            })
            .count();
        odd >= 2
    };
    Ok(rejection_sample(
        inside,
        lo,
        hi,
        particle_radius,
        count,
        seed,
    ))
}

/// Whether the ray `origin + t · dir`, `t > 0`, crosses the triangle (either side; Möller–Trumbore).
fn ray_hits_triangle(origin: Vec3, dir: Vec3, [a, b, c]: &[Vec3; 3]) -> bool {
    let (e1, e2) = (*b - *a, *c - *a);
    let p = dir.cross(e2);
    let det = e1.dot(p);
    if det.abs() < 1e-12 {
        return false;
    }
    let inv = 1.0 / det;
    let s = origin - *a;
    let u = s.dot(p) * inv;
    if !(0.0..=1.0).contains(&u) {
        return false;
    }
    let q = s.cross(e1);
    let v = dir.dot(q) * inv;
    if v < 0.0 || u + v > 1.0 {
        return false;
    }
    e2.dot(q) * inv > 0.0
}

/// Signed-distance bound of an axis-aligned ellipsoid of semi-axes `radii` centred at `centre`
/// (negative inside; exact sign, approximate magnitude).
pub fn sdf_ellipsoid(p: Vec3, centre: Vec3, radii: Vec3) -> f32 {
    let q = p - centre;
    let k0 = (q / radii).length();
    let k1 = (q / (radii * radii)).length();
    if k1 == 0.0 {
        -radii.min_element()
    } else {
        k0 * (k0 - 1.0) / k1
    }
}

/// Signed distance of a capsule: the segment `a`–`b` thickened by `radius`.
pub fn sdf_capsule(p: Vec3, a: Vec3, b: Vec3, radius: f32) -> f32 {
    let (pa, ba) = (p - a, b - a);
    let h = (pa.dot(ba) / ba.length_squared()).clamp(0.0, 1.0);
    (pa - ba * h).length() - radius
}

/// Smooth union of two signed distances, blending over about `k` metres (`k = 0`: plain `min`).
pub fn sdf_smooth_union(d1: f32, d2: f32, k: f32) -> f32 {
    if k <= 0.0 {
        return d1.min(d2);
    }
    let h = (0.5 + 0.5 * (d2 - d1) / k).clamp(0.0, 1.0);
    d2 + (d1 - d2) * h - k * h * (1.0 - h)
}

/// The box (metres) that contains [`bunny_sdf`]'s shape: `(min, max)`.
pub const BUNNY_BOUNDS: (Vec3, Vec3) = (Vec3::new(-1.05, -0.05, -0.6), Vec3::new(1.05, 2.05, 0.6));

/// A stylised sitting bunny, about 1.9 m long (x: tail at −x, nose at +x), 2 m tall (y up, feet
/// on `y = 0`) and 1 m wide (z), as a signed distance (metres; negative inside): a smooth union
/// of ellipsoids (body, haunches, chest, head, cheeks, feet, paws), a ball (tail) and capsules
/// (ears). Fill it with [`from_sdf`] over [`BUNNY_BOUNDS`]: the `snow_bunny` example.
pub fn bunny_sdf(p: Vec3) -> f32 {
    // Symmetric in z: model one side.
    let q = Vec3::new(p.x, p.y, p.z.abs());
    let body = sdf_ellipsoid(q, Vec3::new(-0.15, 0.55, 0.0), Vec3::new(0.68, 0.52, 0.46));
    let haunch = sdf_ellipsoid(q, Vec3::new(-0.25, 0.38, 0.22), Vec3::new(0.45, 0.36, 0.26));
    let chest = sdf_ellipsoid(q, Vec3::new(0.32, 0.62, 0.0), Vec3::new(0.34, 0.42, 0.34));
    let head = sdf_ellipsoid(q, Vec3::new(0.58, 1.12, 0.0), Vec3::new(0.34, 0.29, 0.28));
    let cheek = sdf_ellipsoid(q, Vec3::new(0.7, 1.04, 0.1), Vec3::new(0.22, 0.17, 0.16));
    let ear = sdf_capsule(
        q,
        Vec3::new(0.5, 1.3, 0.1),
        Vec3::new(0.3, 1.92, 0.2),
        0.085,
    );
    let tail = (q - Vec3::new(-0.82, 0.5, 0.0)).length() - 0.17;
    let foot = sdf_ellipsoid(q, Vec3::new(-0.05, 0.09, 0.3), Vec3::new(0.42, 0.09, 0.14));
    let paw = sdf_ellipsoid(q, Vec3::new(0.56, 0.08, 0.14), Vec3::new(0.2, 0.08, 0.09));
    let k = 0.06;
    [haunch, chest, head, cheek, ear, tail, foot, paw]
        .into_iter()
        .fold(body, |d, part| sdf_smooth_union(d, part, k))
}

#[cfg(test)]
mod tests;
