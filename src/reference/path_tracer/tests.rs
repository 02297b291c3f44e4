//! Analytic checks of the estimators and of the whole tracer. Monte Carlo comparisons use
//! tolerances of 4–5 standard errors (estimated from the samples themselves), so a correct
//! tracer fails them with negligible probability, and the seeds are fixed anyway.

use std::ops::ControlFlow;

use bevy::math::{DVec3, Vec3};

use super::estimators::cosine_direction_of;
use super::*;
use crate::math::{SplitMix64, henyey_greenstein, kernel_u2, particle_optical_depth};
use crate::particle::{LightSample, Medium, Particle};
use crate::reference::geometry::box_interval;
use crate::scene::{ObjectShape, SceneCamera};
use crate::scene::{ResolvedCloud, Scene, SceneObject};
use crate::settings::CloudQualitySettings;

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
fn assert_close(what: &str, (mean, error): (DVec3, DVec3), expected: DVec3, sigmas: f64, abs: f64) {
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

    fn segment_optical_depth(&self, _: DVec3, _: DVec3, segment: &Segment, t: f64) -> f64 {
        self.extinction * (t - segment.t0)
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
            .filter(|_| sample_free_flight(&media, origin, dir, f64::INFINITY, &mut rng).is_none())
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
    slab_follows_beer_lambert(2.5);
}

/// A majorant 100 times `σ_t` makes the slab's segments dense (more than `DENSE_SEGMENT`
/// expected tentative collisions): they are walked by their exact optical depth, with the same
/// statistics.
#[test]
fn dense_segments_follow_beer_lambert_by_their_exact_optical_depth() {
    assert!(1.7 * 100.0 > super::estimators::DENSE_SEGMENT);
    slab_follows_beer_lambert(100.0);
}

/// A particle of extinction 1e30 (a step of 1e-30 m is below the f64 resolution of its distance,
/// so null collisions never advanced): paths end at once, with finite radiance, the camera ray
/// colliding at the particle's surface and no light through it.
#[test]
fn a_medium_beyond_f64_resolution_ends_its_paths() {
    let clouds = vec![cloud(
        Vec3::ZERO,
        1e30,
        0.9,
        vec![particle(0.0, 0.0, 0.0, 1.0, 1.0)],
    )];
    let media = ParticleMedia::new(&clouds);
    let lighting = Lighting {
        background: DVec3::ONE,
        lights: vec![DirectionalLight {
            to_light: DVec3::Y,
            irradiance: DVec3::ONE,
        }],
        objects: vec![],
        fog: None,
    };
    let mut rng = SplitMix64::mixed(5);
    let origin = DVec3::new(0.0, 0.2, -5.0);
    for _ in 0..200 {
        let (t, c) = sample_free_flight(&media, origin, DVec3::Z, f64::INFINITY, &mut rng)
            .expect("an opaque particle stops every ray");
        // Within 0.1 mm of the surface: the exact optical depth of a chord's first micrometres
        // cancels to f64's 1e-16 of the whole chord's, so the collision lands a few µm deep.
        let surface = 5.0 - (1.0f64 - 0.04).sqrt();
        assert!(
            (t - surface).abs() < 1e-4 && c.extinction > 0.0,
            "{t} against {surface}: {c:?}"
        );
        assert_eq!(
            transmittance(&media, origin, DVec3::Z, f64::INFINITY, &mut rng),
            0.0
        );
        let l = radiance(
            &media,
            &lighting,
            origin,
            DVec3::Z,
            MAX_SCATTER_EVENTS,
            &mut rng,
        );
        assert!(l.is_finite() && l.min_element() >= 0.0, "{l}");
    }
}

fn slab_follows_beer_lambert(majorant_factor: f64) {
    let sigma = 1.7;
    let slab = HomogeneousBox {
        lo: DVec3::new(-50.0, -50.0, 0.0),
        hi: DVec3::new(50.0, 50.0, 1.0),
        extinction: sigma,
        albedo: 0.5,
        majorant_factor,
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
        let expected = background.as_dvec3() * t_total + lighting.lights[0].irradiance * scattered;
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
        time_limit: None,
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
        time_limit: None,
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
                time_limit: None,
            },
        );
        let elapsed = start.elapsed();
        let b = render(
            &s,
            &PathTracerSettings {
                samples_per_pixel: spp,
                seed: 2,
                progress: None,
                time_limit: None,
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
