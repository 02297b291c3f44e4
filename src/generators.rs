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
mod tests {
    use bevy::prelude::{Cuboid, MeshBuilder, Meshable, Sphere, Torus};

    use super::*;

    fn positions(p: &Particles) -> Vec<Vec3> {
        p.particles.iter().map(|p| p.position).collect()
    }

    #[test]
    fn sphere_fills_the_ball() {
        let p = sphere(2.0, 0.25, 1000, 3);
        assert_eq!(p.particles.len(), 1000);
        for q in &p.particles {
            assert!(
                q.position.length() + q.radius <= 2.0 + 1e-5,
                "{q:?} leaves the ball"
            );
            assert_eq!((q.radius, q.density), (0.25, 1.0));
        }
        // Uniform in volume: about (1/2)³ of the centres lie within half the inner radius.
        let inner = p
            .particles
            .iter()
            .filter(|q| q.position.length() < 0.875)
            .count();
        assert!(
            (80..=175).contains(&inner),
            "{inner} of 1000 in the inner half radius"
        );
        assert_eq!(p, sphere(2.0, 0.25, 1000, 3));
        assert_ne!(p, sphere(2.0, 0.25, 1000, 4));
    }

    #[test]
    fn cuboid_fills_the_box() {
        let extents = Vec3::new(4.0, 1.0, 2.0);
        let p = cuboid(extents, 0.1, 800, 9);
        assert_eq!(p.particles.len(), 800);
        for q in &p.particles {
            assert!(
                (q.position.abs() + q.radius)
                    .cmple(extents * 0.5 + 1e-5)
                    .all(),
                "{q:?} leaves the box"
            );
        }
        let (lo, hi) = p.bounds().unwrap();
        // 800 uniform samples reach within 2 % of each face.
        assert!(
            lo.cmplt(-extents * 0.49).all() && hi.cmpgt(extents * 0.49).all(),
            "{lo} {hi}"
        );
        assert_eq!(p, cuboid(extents, 0.1, 800, 9));
        assert_ne!(p, cuboid(extents, 0.1, 800, 10));
    }

    #[test]
    fn cumulus_is_a_flat_bottomed_heap() {
        let p = cumulus(2.5, 3000, 7);
        assert_eq!(p.particles.len(), 3000);
        for q in &p.particles {
            assert!(q.position.y >= -0.05 * 2.5 - 1e-6, "{q:?} below the base");
            assert!(q.position.length() < 2.5, "{q:?} far outside the heap");
            assert!((0.07 * 2.5 - 1e-5..=0.13 * 2.5 + 1e-5).contains(&q.radius));
            assert!((0.5..=1.0).contains(&q.density));
        }
        assert_eq!(p, cumulus(2.5, 3000, 7));
        assert_ne!(p, cumulus(2.5, 3000, 8));
    }

    #[test]
    fn cloudscape_lays_out_equal_clouds_on_a_grid() {
        let sky = cloudscape(9, 900, 7);
        assert_eq!(sky.len(), 9);
        for (i, cloud) in sky.iter().enumerate() {
            assert_eq!(cloud.particles.particles.len(), 100);
            // Its grid cell (3 × 3, 80 m apart), jittered by at most 0.3 of a cell.
            let cell = Vec2::new((i % 3) as f32 - 1.0, (i / 3) as f32 - 1.0) * 80.0;
            let at = Vec2::new(cloud.translation.x, cloud.translation.z);
            assert!(
                (at - cell).abs().max_element() <= 24.0 + 1e-3,
                "{at} off {cell}"
            );
            assert!((70.0..=110.0).contains(&cloud.translation.y));
            // Extinction 20 / size for a size of 25–60 m; the particles within that size.
            let size = 20.0 / cloud.medium.extinction;
            assert!((25.0..=60.0).contains(&size), "size {size}");
            assert!(
                cloud
                    .particles
                    .particles
                    .iter()
                    .all(|p| p.position.length() < size)
            );
        }
        // The particles' turn keeps their distances from the cloud's origin.
        let turned = &sky[0].particles.particles;
        let size = 20.0 / sky[0].medium.extinction;
        let unturned = cumulus(size, 100, 1000);
        for (a, b) in turned.iter().zip(&unturned.particles) {
            assert!((a.position.length() - b.position.length()).abs() < 1e-4);
            assert!((a.position.y - b.position.y).abs() < 1e-4);
        }
        assert_eq!(sky[3].translation, cloudscape(9, 900, 7)[3].translation);
    }

    #[test]
    fn from_sdf_fills_only_the_inside() {
        let ball = |p: Vec3| p.length() - 1.0;
        let p = from_sdf(ball, Vec3::splat(-1.5), Vec3::splat(1.5), 0.05, 10_000, 5);
        assert_eq!(p.particles.len(), 10_000);
        assert!(positions(&p).iter().all(|q| q.length() < 1.0));
        assert!(
            p.particles
                .iter()
                .all(|q| q.radius == 0.05 && q.density == 1.0)
        );
        // Uniform: the mean distance from the centre of a uniform unit ball is 3/4.
        let mean = positions(&p).iter().map(|q| q.length()).sum::<f32>() / 10_000.0;
        assert!((mean - 0.75).abs() < 0.01, "mean radius {mean}");
        // Deterministic per seed, also across chunk boundaries (10 000 > one chunk).
        assert_eq!(
            p,
            from_sdf(ball, Vec3::splat(-1.5), Vec3::splat(1.5), 0.05, 10_000, 5)
        );
        assert_ne!(
            p,
            from_sdf(ball, Vec3::splat(-1.5), Vec3::splat(1.5), 0.05, 10_000, 6)
        );
        // A prefix of a larger request is the same sample.
        let more = from_sdf(ball, Vec3::splat(-1.5), Vec3::splat(1.5), 0.05, 12_000, 5);
        assert_eq!(&more.particles[..CHUNK], &p.particles[..CHUNK]);
    }

    #[test]
    fn from_sdf_of_an_empty_shape_gives_nothing() {
        let p = from_sdf(|_| 1.0, Vec3::ZERO, Vec3::ONE, 0.1, 3, 1);
        assert_eq!(p.particles.len(), 0);
        assert_eq!(
            from_sdf(|_| -1.0, Vec3::ZERO, Vec3::ONE, 0.1, 0, 1)
                .particles
                .len(),
            0
        );
    }

    #[test]
    fn bunny_is_inside_its_bounds_and_has_its_parts() {
        let (lo, hi) = BUNNY_BOUNDS;
        let p = from_sdf(bunny_sdf, lo, hi, 0.02, 20_000, 11);
        assert_eq!(p.particles.len(), 20_000);
        assert!(positions(&p).iter().all(|&q| bunny_sdf(q) < 0.0));
        // The box contains the whole shape: its faces are outside the bunny.
        for i in 0..=41 {
            for j in 0..=41 {
                let (a, b) = (i as f32 / 41.0, j as f32 / 41.0);
                for q in [
                    Vec3::new(lo.x, lo.y + a * (hi.y - lo.y), lo.z + b * (hi.z - lo.z)),
                    Vec3::new(hi.x, lo.y + a * (hi.y - lo.y), lo.z + b * (hi.z - lo.z)),
                    Vec3::new(lo.x + a * (hi.x - lo.x), lo.y, lo.z + b * (hi.z - lo.z)),
                    Vec3::new(lo.x + a * (hi.x - lo.x), hi.y, lo.z + b * (hi.z - lo.z)),
                    Vec3::new(lo.x + a * (hi.x - lo.x), lo.y + b * (hi.y - lo.y), lo.z),
                    Vec3::new(lo.x + a * (hi.x - lo.x), lo.y + b * (hi.y - lo.y), hi.z),
                ] {
                    assert!(
                        bunny_sdf(q) > 0.0,
                        "the bunny pokes out of BUNNY_BOUNDS at {q}"
                    );
                }
            }
        }
        // Parts: ears above the head, a tail behind, symmetric in z.
        assert!(bunny_sdf(Vec3::new(0.38, 1.75, 0.18)) < 0.0, "ear");
        assert!(
            bunny_sdf(Vec3::new(0.38, 1.75, 0.0)) > 0.0,
            "gap between the ears"
        );
        assert!(bunny_sdf(Vec3::new(-0.9, 0.5, 0.0)) < 0.0, "tail");
        assert!(bunny_sdf(Vec3::new(0.6, 1.1, 0.0)) < 0.0, "head");
        let left = p.particles.iter().filter(|q| q.position.z > 0.0).count();
        assert!(
            (9_700..=10_300).contains(&left),
            "{left} of 20 000 on one side"
        );
    }

    #[test]
    fn from_mesh_volume_fills_a_box_mesh() {
        let mesh = Cuboid::new(2.0, 1.0, 0.5).mesh().build();
        let p = from_mesh_volume(&mesh, 0.05, 2000, 4).unwrap();
        assert_eq!(p.particles.len(), 2000);
        let half = Vec3::new(1.0, 0.5, 0.25);
        assert!(positions(&p).iter().all(|q| q.abs().cmple(half).all()));
        let (lo, hi) = p.bounds().unwrap();
        assert!(
            (lo + 0.05).cmplt(-half + 0.05).all() && (hi - 0.05).cmpgt(half - 0.05).all(),
            "{lo} {hi}"
        );
        assert_eq!(p, from_mesh_volume(&mesh, 0.05, 2000, 4).unwrap());
        assert_ne!(p, from_mesh_volume(&mesh, 0.05, 2000, 5).unwrap());
    }

    #[test]
    fn from_mesh_volume_respects_concavity() {
        // A torus (ring radius 1, tube radius 0.25): its hole must stay empty.
        let mesh = Torus::new(0.75, 1.25).mesh().build();
        let p = from_mesh_volume(&mesh, 0.05, 3000, 2).unwrap();
        assert_eq!(p.particles.len(), 3000);
        for q in positions(&p) {
            // The tessellated tube (32 × 24 segments) departs from the true one by under 4 mm.
            let tube = (Vec3::new(q.x, 0.0, q.z).length() - 1.0).hypot(q.y);
            assert!(
                tube <= 0.25 + 0.005,
                "{q} is outside the torus (tube distance {tube})"
            );
        }
        // And fills it: particles reach most of the way around the ring in every quadrant.
        for (sx, sz) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
            let n = p
                .particles
                .iter()
                .filter(|q| q.position.x * sx > 0.0 && q.position.z * sz > 0.0)
                .count();
            assert!(
                (650..=850).contains(&n),
                "{n} of 3000 in quadrant ({sx}, {sz})"
            );
        }
        let ball = Sphere::new(1.0).mesh().ico(3).unwrap();
        let b = from_mesh_volume(&ball, 0.05, 1000, 2).unwrap();
        assert!(positions(&b).iter().all(|q| q.length() <= 1.0 + 1e-5));
    }

    #[test]
    fn from_mesh_volume_refuses_a_mesh_without_triangles() {
        use bevy::{
            asset::RenderAssetUsages,
            mesh::{Indices, PrimitiveTopology},
        };
        let points = Mesh::new(PrimitiveTopology::PointList, RenderAssetUsages::default())
            .with_inserted_attribute(Mesh::ATTRIBUTE_POSITION, vec![[0.0f32, 0.0, 0.0]])
            .with_inserted_indices(Indices::U32(vec![0]));
        assert!(matches!(
            from_mesh_volume(&points, 0.1, 10, 1),
            Err(MeshTrianglesError::WrongTopology)
        ));
    }
}
